"""Executors: where the runs of a sweep run (docs/design.md §10.2), behind one seam.

The seam is `concurrent.futures.Executor`: ``submit(fn, *args) -> Future``, ``shutdown(wait,
cancel_futures)`` and the context manager, plus ``terminate_workers()`` (the name Python 3.14 gives it
on ProcessPoolExecutor): cancel the pending tasks, stop the running ones now and shut down.

- ``local`` (`LocalExecutor`, the default): a ProcessPoolExecutor of ``workers`` processes, each running
  one task at a time with ``threads`` OpenMP / torch threads; ``workers × threads`` must fit the cores.
  Processes are spawned, not forked (torch and OpenMP state does not survive a fork). Workers ignore
  SIGINT and SIGHUP, so a Ctrl-C in the terminal or its closing reaches only the sweep, which decides what to
  stop (it stops its workers with SIGTERM, `gsbench.runs.sweep.run_sweep`).
- Both run every task in a fresh process: a run's peak memory is the process high-water mark
  (``ru_maxrss``, which never decreases), so a reused worker would report the largest earlier run's.
- ``ray`` (`RayExecutor`, extra ``gsbench[ray]``): each task is a Ray task with ``num_cpus = threads``,
  on the cluster at ``address`` or on a local cluster of ``workers × threads`` CPUs started for the
  sweep (no dashboard, usage statistics off, logs in a temp folder). No disk is shared (docs/cluster.md): a
  run runs in its node's own run folder and sends its outputs back through Ray, which the driver writes into
  ``--out`` (`gsbench.runs.node_runs`); its scene is generated, shipped or checked on the node
  (`gsbench.runs.scene_shipping`, ``scene_paths``). The driver sends a run again when its node or worker died, up
  to `NODE_DEATH_RETRIES` times, telling each task its attempt number. Its runs lock no folder in ``--out``
  (``runs_elsewhere``), so the sweep holds the lock of ``--out`` itself (`gsbench.runs.sweep.output_lock`): a second
  driver there is refused.

``slots``: how many runs an executor runs at once (the sweep's progress bar and its ETA).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import tempfile
import threading
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from concurrent.futures import wait as wait_for
from concurrent.futures.process import BrokenProcessPool

from tqdm import tqdm

from gsbench.config.run_config import RunConfig
from gsbench.errors import ConfigError, GsbenchError, missing_dependency
from gsbench.runs.node_runs import land_outputs, run_on_node
from gsbench.runs.scene_shipping import SceneShipper

KINDS = ("local", "ray")
NODE_DEATH_RETRIES = 3  # a run is sent again, to any node, when its node or worker dies, at most this many times


def cores() -> int:
    return os.cpu_count() or 1


def threads_per_run(requested: int | None, workers: int) -> int:
    """``requested`` threads per run, or (None / 0) the cores shared equally among the workers."""
    return requested or max(1, cores() // workers)


def check_fits_cores(workers: int, threads: int) -> None:
    """``workers × threads <= cores``: more would oversubscribe the CPU and slow every run down."""
    if workers * threads > cores():
        raise ConfigError(
            f"--workers {workers} × --threads {threads} = {workers * threads} threads, more than the {cores()} "
            f"cores of this machine; fix: lower --workers or --threads so that workers × threads <= {cores()}")


def make_executor(kind: str, *, workers: int, threads: int, address: str | None = None, scene_paths: str = "ship",
                  echo=print) -> Executor:
    """The executor ``kind`` (`KINDS`) running ``workers`` tasks at a time with ``threads`` threads each;
    ``scene_paths`` (`gsbench.runs.scene_shipping.SCENE_PATHS`) says how a Ray node gets a scene folder."""
    if kind not in KINDS:
        raise ConfigError(f"unknown executor '{kind}'; choose one of: {', '.join(KINDS)}")
    for name, value in (("workers", workers), ("threads", threads)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ConfigError(f"executor {name} must be a positive integer, got {value!r}")
    if kind == "ray":
        return RayExecutor(workers, threads, address=address, scene_paths=scene_paths, echo=echo)
    if address:
        raise ConfigError(f"--address {address} is for the ray executor; add --executor ray or drop --address")
    return LocalExecutor(workers, threads)


def _init_local_worker(threads: int) -> None:
    """In each spawned worker, before torch loads: its thread count; Ctrl-C and a closed terminal (SIGHUP) are the
    sweep's to handle; progress bars locked by a thread lock, not tqdm's default multiprocessing semaphore, which a
    terminated worker would leak (a warning when the sweep exits)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    tqdm.set_lock(threading.RLock())


class LocalExecutor(ProcessPoolExecutor):
    """``workers`` spawned processes with ``threads`` threads each, a new one per task (module docstring)."""

    def __init__(self, workers: int, threads: int):
        check_fits_cores(workers, threads)
        super().__init__(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                         initializer=_init_local_worker, initargs=(threads,), max_tasks_per_child=1)
        self.slots = workers

    def _adjust_process_count(self) -> None:
        """Replace an exited worker, unless the executor is shut down: with ``max_tasks_per_child`` a worker exits
        after each run, and when that exit reaches the pool's manager thread after ``shutdown(wait=False)``
        (a Ctrl-C while a run ends), CPython (3.11) replaces it from ``_processes``, which the shutdown set to
        None; the TypeError killed the manager thread, the running futures never ended and the sweep hung.

        Once shut down, when the last worker has exited, the tasks already handed to the call queue (their
        futures "running", so the shutdown cannot cancel them) would never run and the manager thread would
        wait for their results forever (a run that stops cleanly on SIGTERM leaves no broken worker to end
        them): they end with `BrokenProcessPool`. This runs in the manager thread, which owns that table."""
        if self._processes is not None:
            super()._adjust_process_count()
            return
        manager = threading.current_thread()
        if any(process.is_alive() for process in getattr(manager, "processes", {}).values()):
            return
        orphans = getattr(manager, "pending_work_items", {})
        for work_item in orphans.values():
            if not work_item.future.done():
                work_item.future.set_exception(BrokenProcessPool("the pool was shut down before this task ran"))
        orphans.clear()

    if sys.version_info < (3, 14):
        def terminate_workers(self) -> None:
            """Python 3.14's ``ProcessPoolExecutor.terminate_workers``: cancel the pending tasks, terminate
            the worker processes (their running tasks end with ``BrokenProcessPool``), shut down."""
            processes = dict(self._processes or {})
            self.shutdown(wait=False, cancel_futures=True)
            for process in processes.values():
                if process.is_alive():
                    process.terminate()


def import_ray():
    """Import ray lazily; missing, it is an error naming the extra to install."""
    try:
        import ray  # noqa: PLC0415
    except ImportError as exc:
        raise missing_dependency("ray", 'pip install "gsbench[ray]"') from exc
    return ray


class RayExecutor(Executor):
    """Each task a Ray task with ``num_cpus = threads`` (module docstring). A task whose one argument is a
    `RunConfig` is a run: it runs on its node by `run_on_node` (sent again up to `NODE_DEATH_RETRIES` times when its
    node or worker dies), and its Future ends once the driver has written its outputs (`land_outputs`). Another task's
    Future is ``ObjectRef.future()``, and it is not retried.

    The driver counts the attempts itself (it sees each task end), so nothing but the runs is placed on the cluster.

    A process that has started a local Ray cluster is refused a connection to an external one afterwards: Ray 2.60
    then kills that process's actors at creation ("all references to the actor were removed") and loses its objects
    on some nodes (``OwnerDiedError``). One connection after another is fine (experiments/cluster/scaling.py). The
    local cluster also sets ``RAY_AUTH_MODE=token`` in the process's environment and leaves it there: inherited by
    the nodes and drivers the process starts later, it breaks them the same way, so shutdown puts the environment
    back as it was."""

    local_sessions_in_process = 0  # local Ray clusters this process has started

    runs_elsewhere = True

    def __init__(self, workers: int, threads: int, *, address: str | None = None, scene_paths: str = "ship",
                 echo=print):
        self.ray = import_ray()
        self.threads = threads
        self._remote_fns: dict = {}
        self._tasks: list = []  # (ObjectRef, Future)
        self._runs: list[Future] = []  # each run's landed Future, across its attempts
        self._closing = False
        self._environ = dict(os.environ)  # put back at shutdown: Ray leaves RAY_AUTH_MODE=token behind (class doc)
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no network calls from the cluster
        quiet = {"logging_level": logging.WARNING, "log_to_driver": False}
        if address:
            self._check_no_local_session_before(address)
            self.ray.init(address=address, **quiet)
            echo(f"ray: connected to the cluster at {address}")
            self._check_a_node_fits(address)
        else:
            check_fits_cores(workers, threads)
            logs = tempfile.mkdtemp(prefix="gsbench-ray-")
            # Ray starts its workers at niceness 15: beside any other process the runs would starve, and their
            # timings with them. The local cluster runs them at the driver's priority.
            self.ray.init(address="local", num_cpus=workers * threads, include_dashboard=False, _temp_dir=logs,
                          _system_config={"worker_niceness": 0}, **quiet)
            RayExecutor.local_sessions_in_process += 1
            echo(f"ray: local cluster with {workers * threads} CPUs, logs in {logs}")
        self.scenes = SceneShipper(self.ray.put, scene_paths)
        self._run_task = self.ray.remote(num_cpus=threads, max_retries=0, max_calls=1)(run_on_node)
        self._node_deaths = (self.ray.exceptions.WorkerCrashedError, self.ray.exceptions.NodeDiedError,
                             self.ray.exceptions.LocalRayletDiedError)
        self.slots = max(1, int(self.ray.cluster_resources().get("CPU", threads) // threads))

    @classmethod
    def _check_no_local_session_before(cls, address: str) -> None:
        if cls.local_sessions_in_process:
            raise GsbenchError(f"this Python process has run a local Ray cluster before, and Ray cannot then connect "
                               f"it to the cluster at {address} reliably (its actors and objects die); fix: run the "
                               "sweep in a new process (the gsbench command starts one)")

    def _check_a_node_fits(self, address: str) -> None:
        largest = max((node["Resources"].get("CPU", 0) for node in self.ray.nodes() if node["Alive"]), default=0)
        if largest < self.threads:
            self.ray.shutdown()
            raise ConfigError(f"no node of the Ray cluster at {address} has {self.threads} CPUs for a run "
                              f"(the largest has {largest:g}); fix: lower --threads")

    def submit(self, fn, /, *args, **kwargs) -> Future:
        if len(args) == 1 and not kwargs and isinstance(args[0], RunConfig):
            return self._submit_run(fn, args[0])
        if fn not in self._remote_fns:
            self._remote_fns[fn] = self.ray.remote(num_cpus=self.threads, max_retries=0, max_calls=1)(fn)
        ref = self._remote_fns[fn].remote(*args, **kwargs)
        future = ref.future()
        self._tasks.append((ref, future))
        return future

    def _submit_run(self, fn, cfg: RunConfig) -> Future:
        """``fn(cfg)`` on a node (`run_on_node`); the Future's result is its value once its outputs are in ``cfg.out``
        here (`land_outputs`), its exception the task's, the landing's, or the scene's when it cannot be sent
        (`SceneShipper.ticket`)."""
        landed = Future()
        landed.set_running_or_notify_cancel()
        self._runs.append(landed)
        try:
            ticket = self.scenes.ticket(cfg.scene)
        except GsbenchError as exc:  # a scene that cannot reach the nodes: this run fails, unsent; the others go on
            landed.set_exception(exc)
            return landed
        self._send(fn, cfg, ticket, landed, attempt=1)
        return landed

    def _send(self, fn, cfg: RunConfig, ticket, landed: Future, attempt: int) -> None:
        """Attempt ``attempt`` of a run; when its node or worker dies it is sent again (``attempt + 1``) up to
        `NODE_DEATH_RETRIES` times, unless the executor is shutting its tasks down."""
        ref = self._run_task.remote(fn, cfg, ticket, attempt)

        def land(task: Future) -> None:
            try:
                landed.set_result(land_outputs(task.result(), cfg, ticket.content_hash))
            except self._node_deaths as exc:
                if attempt <= NODE_DEATH_RETRIES and not self._closing:
                    self._send(fn, cfg, ticket, landed, attempt + 1)
                else:
                    landed.set_exception(exc)
            except BaseException as exc:  # noqa: BLE001  (the task's error, or the landing's, ends the run's Future)
                landed.set_exception(exc)

        task = ref.future()
        self._tasks.append((ref, task))
        task.add_done_callback(land)

    def _cancel_unfinished(self, *, force: bool) -> None:
        for ref, future in self._tasks:
            if not future.done():
                self.ray.cancel(ref, force=force)

    def shutdown(self, wait=True, *, cancel_futures=False) -> None:
        """Disconnect from (or stop the local) cluster. ``cancel_futures`` cancels every unfinished task, the
        running ones too (Ray cannot cancel only the queued ones): those get a KeyboardInterrupt."""
        if not self.ray.is_initialized():
            return
        if cancel_futures:
            self._closing = True
            self._cancel_unfinished(force=False)
        if wait:
            wait_for([future for _, future in self._tasks] + self._runs)
        self.ray.shutdown()
        for key in set(os.environ) | set(self._environ):
            if key not in self._environ:
                del os.environ[key]
            elif os.environ.get(key) != self._environ[key]:
                os.environ[key] = self._environ[key]

    def terminate_workers(self) -> None:
        """Cancel the queued tasks, kill the running ones (their futures end with a Ray error), shut down."""
        if self.ray.is_initialized():
            self._closing = True
            self._cancel_unfinished(force=True)
            self.shutdown(wait=True)
