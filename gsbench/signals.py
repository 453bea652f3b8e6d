"""Stop signals held back while a threaded native call runs.

scipy's ``cKDTree`` answers a query with ``workers=-1`` from Python threads that the calling thread joins. A
signal handler that raises (SIGTERM's `gsbench.errors.Interrupted`, Ctrl-C's ``KeyboardInterrupt``) raises inside
that join: the call is left while its threads still write into the query's arrays, which the unwinding frees. A
sweep stopped during a DTU evaluation wrote its record (status ``interrupted``) and then died of SIGSEGV as it
exited. Inside `signals_deferred` a stop signal is only noted; when the block ends the previous handlers are back
and the noted signals are raised again, so the handler runs once every thread has joined.
"""

import signal
import threading
from contextlib import contextmanager

DEFERRED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)  # Ctrl-C, `kill`, a closed terminal


@contextmanager
def signals_deferred():
    """Note `DEFERRED_SIGNALS` during the block and raise them again, in order, when it ends (main thread only: Python
    runs handlers there; elsewhere the block runs as it is). Signals that are ignored, or handled outside Python,
    are left alone."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    noted: list[int] = []
    deferred = [s for s in DEFERRED_SIGNALS if signal.getsignal(s) not in (signal.SIG_IGN, None)]
    previous = {s: signal.signal(s, lambda signum, _frame: noted.append(signum)) for s in deferred}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in noted:
            signal.raise_signal(signum)
