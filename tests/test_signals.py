"""Stop signals during threaded KD-tree queries (gsbench/signals.py): the handler runs after the query's threads
have joined, so a stopped run never leaves threads writing into freed arrays (a SIGSEGV at exit before)."""

import os
import signal
import threading

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gsbench.errors import Interrupted
from gsbench.evaluators import pointsets
from gsbench.runs.runner import interrupts_raised
from gsbench.signals import signals_deferred


def test_a_signal_in_the_block_is_raised_when_it_ends():
    reached = []
    with interrupts_raised():
        raising_handler = signal.getsignal(signal.SIGTERM)
        with pytest.raises(Interrupted):
            with signals_deferred():
                signal.raise_signal(signal.SIGTERM)
                reached.append("end of block")
        assert reached == ["end of block"]
        assert signal.getsignal(signal.SIGTERM) is raising_handler


def test_ignored_signals_stay_ignored():
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with signals_deferred():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            signal.raise_signal(signal.SIGHUP)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


def test_sigterm_during_a_threaded_query_waits_for_its_threads():
    """SIGTERM lands while `nn_distances` runs cKDTree's worker threads: Interrupted comes after they have joined.
    With the handler raising inside the join (no `signals_deferred`), two of them were still alive here."""
    rng = np.random.default_rng(0)
    tree = cKDTree(rng.random((200_000, 3)))
    queries = rng.random((6 * pointsets.QUERY_CHUNK, 3))
    threads_before = threading.active_count()
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM))
    with interrupts_raised():
        timer.start()
        with pytest.raises(Interrupted):
            for _ in range(20):  # seconds of queries on any machine: the signal lands inside one
                pointsets.nn_distances(queries, tree, workers=2)
    timer.join()
    assert threading.active_count() == threads_before
