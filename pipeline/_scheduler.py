"""Running tile tasks on a dask scheduler, with progress.

``--scheduler`` takes ``threads`` (default), ``processes``, ``synchronous``, a
``tcp://`` address of a dask.distributed scheduler, or the path of a scheduler
file.  Local schedulers need no server.  Tiles, not OpenCV or BLAS, use the
cores: OpenCV and every BLAS library loaded (threadpoolctl) run one thread per
task.

Process-wide settings (:func:`configure_process`: OpenCV's and BLAS's thread
counts, the interpreter's switch interval, glibc's malloc thresholds and arenas) are made only in processes that exist to run
rsmb: the ``processes`` scheduler's worker processes, where each task makes
them once, and the ``rsmb`` command itself.  A program that imports rsmb as a
library keeps its settings: while :meth:`Runner.map` runs tasks in the calling
process (``threads``, ``synchronous``), OpenCV's and BLAS's thread counts are
set to one and restored when the run ends, and malloc is left alone.  So does a
dask.distributed worker (a cluster may be shared with other work): one thread
each while rsmb's tasks run there, its own counts back after the last of them.
"""

import contextlib
import ctypes
import json
import logging
import os
import sys
import threading
import time

import dask
import dask.callbacks

from rsmb.ops import InputError, ParameterError, RunError

#: Seconds a cluster run waits with no dask worker left before it fails.
WORKER_TIMEOUT = 60.0
from rsmb.ops._errors import one_line

__all__ = ["SCHEDULERS", "Runner", "check_scheduler", "configure_process", "open_runner"]

SCHEDULERS = ("threads", "processes", "synchronous")
log = logging.getLogger("rsmb")


#: The interpreter's switch interval (seconds) in a process that runs rsmb (Python's default is 0.005):
#: a thread coming back from work that released the GIL (a numba kernel of a tile task, a large numpy
#: operation, GDAL) waits up to one interval for a thread running Python (a capture's report being
#: drawn beside the next captures' tiles) to hand the GIL over, at every kernel call of a tile task.
SWITCH_INTERVAL = 0.001
_MMAP_THRESHOLD = 4 << 20
#: glibc keeps up to this much free memory at the top of a heap instead of returning it (M_TRIM_THRESHOLD) ...
_TRIM_THRESHOLD = 1 << 30
#: ... and grows a heap by this much more than asked (M_TOP_PAD): address space, resident only once used
_TOP_PAD = 64 << 20
_process_ready = False
_threads_lock = threading.Lock()
_blas_lock = threading.Lock()  # one change of BLAS thread counts at a time (tasks of a worker process)
_threads_runs = 0  # runs of Runner.map under way in this process
_threads_saved = None  # OpenCV's thread count and the BLAS limiter (threadpoolctl) set by the first of them
_blas_found = None  # (len(sys.modules) when found, the threadpoolctl controller of the libraries then loaded)


def _one_blas_thread():
    """Every BLAS library loaded in this process (numpy's, scipy's, OpenCV's
    OpenBLAS: threadpoolctl finds them) at one thread; returns the
    threadpoolctl limiter whose ``restore_original_limits()`` undoes it (call
    it through :func:`_as_blas_controller`).

    Finding the libraries walks every shared object of the process in Python
    (at the start of every map, while the workers wait), so they are found
    again only when a module was imported since the last search: a library
    comes with the import of the extension module that links it."""
    return _as_blas_controller(lambda: _blas_controller().limit(limits=1, user_api="blas"))


def _blas_controller():
    """The threadpoolctl controller of the libraries loaded now (found again
    when ``sys.modules`` has grown; call under :data:`_blas_lock`)."""
    global _blas_found
    from threadpoolctl import ThreadpoolController

    if _blas_found is None or _blas_found[0] != len(sys.modules):
        _blas_found = len(sys.modules), ThreadpoolController()  # the count before the search's own imports
    return _blas_found[1]


def _as_blas_controller(action):
    """Run ``action`` (a change of BLAS thread counts) as the thread that may
    make it, and give that right back after.

    threadpoolctl lets one Python thread at a time change a pthreads OpenBLAS
    (the first that did, while it lives; the others' calls do nothing), and
    the runs here start and end in different threads (a survey's drivers), so
    the right is taken before each change and released after, leaving it to
    whoever asks next."""
    import threadpoolctl

    clear = getattr(getattr(threadpoolctl, "OpenBLASController", None), "clear_controlling_thread", None)
    with _blas_lock:
        if clear is not None:  # threadpoolctl before 3.6 has no controlling thread
            clear(force=True)
        try:
            return action()
        finally:
            if clear is not None:
                clear(force=True)


def configure_process():
    """Process-wide settings for a process that runs rsmb and nothing else.

    One OpenCV thread and one BLAS thread (tiles, not libraries, use the
    cores), a short switch interval (:data:`SWITCH_INTERVAL`: threads that
    released the GIL get it back sooner from a thread running Python), and
    on glibc arrays of 4 MiB and more served by mmap: glibc
    otherwise raises its mmap threshold as large blocks are freed and keeps
    freed tile buffers in the heap, so the resident size grows with the number
    of tiles.  Below that size, freed memory stays in the heaps for the next
    arrays (:data:`_TRIM_THRESHOLD`, :data:`_TOP_PAD`) and there is at most
    one heap (arena) per core: by default glibc gives memory back to the
    kernel as soon as the top of a heap is free, and the next array of the
    same size takes its pages again, each first touch a page fault (the
    system time of a night of small captures, whose every capture allocates
    and frees the buffers of a whole tile).  Called by every task in a
    worker process and meant for the ``rsmb`` command's entry point; never call
    it in a program that uses rsmb as a library (the malloc setting cannot be
    undone).  Idempotent.
    """
    global _process_ready
    import cv2

    cv2.setNumThreads(1)
    _one_blas_thread()  # numpy's may be loaded since the last task (scipy's, OpenCV's)
    if _process_ready:
        return
    _process_ready = True
    sys.setswitchinterval(SWITCH_INTERVAL)
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.mallopt(-3, _MMAP_THRESHOLD)  # -3: M_MMAP_THRESHOLD
            libc.mallopt(-1, _TRIM_THRESHOLD)  # -1: M_TRIM_THRESHOLD
            libc.mallopt(-2, _TOP_PAD)  # -2: M_TOP_PAD
            libc.mallopt(-8, max(2, os.cpu_count() or 1))  # -8: M_ARENA_MAX
        except (OSError, AttributeError):  # not glibc
            pass


@contextlib.contextmanager
def _one_thread_each():
    """One OpenCV thread and one thread per OpenBLAS in this process while
    tasks may run in it; the thread counts they had are restored when the last
    of the runs under way ends."""
    global _threads_runs, _threads_saved
    import cv2

    with _threads_lock:
        if _threads_runs == 0:
            _threads_saved = cv2.getNumThreads(), _one_blas_thread()
            cv2.setNumThreads(1)
        _threads_runs += 1
    try:
        yield
    finally:
        with _threads_lock:
            _threads_runs -= 1
            if _threads_runs == 0:
                cv2.setNumThreads(_threads_saved[0])
                _as_blas_controller(_threads_saved[1].restore_original_limits)


class _Progress:
    """A bar on a terminal, a log line every ``interval`` seconds otherwise."""

    def __init__(self, label, total, *, interval=10.0, stream=None):
        self.label, self.total, self.done = label, total, 0
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = self.last = time.monotonic()
        self.interval = interval

    def step(self, n=1):
        self.done += n
        now = time.monotonic()
        if self.tty:
            width = 30
            filled = int(width * self.done / max(self.total, 1))
            self.stream.write(f"\r{self.label:<12} [{'#' * filled}{'.' * (width - filled)}] "
                              f"{self.done}/{self.total} {now - self.start:6.1f}s")
            if self.done >= self.total:
                self.stream.write("\n")
            self.stream.flush()
        elif now - self.last >= self.interval or self.done >= self.total:
            self.last = now
            log.info("%s: %d/%d tasks done (%.1f s)", self.label, self.done, self.total, now - self.start)


class Runner:
    """Runs lists of independent tasks (function, args) on one scheduler.

    One runner may serve several runs at once (``rsmb survey`` runs captures
    concurrently on one runner): a local runner with a ``pool`` hands every
    run's tasks to that one executor, a distributed runner to its one client.

    Parameters
    ----------
    scheduler : str
        A name of :data:`SCHEDULERS`, or "distributed" with ``client``.
    client : distributed.Client, optional
    workers : int, optional
        Worker count of a local scheduler without a ``pool``.
    pool : concurrent.futures.Executor, optional
        The executor of a local scheduler, shared by every :meth:`map`.
    progress : bool
        Show a bar (or log lines) per :meth:`map`.
    worker_timeout : float
        Seconds a distributed run waits with no worker left before it gives up.
    """

    def __init__(self, scheduler, client=None, workers=None, pool=None, progress=True, worker_timeout=WORKER_TIMEOUT):
        self.scheduler = scheduler
        self.client = client
        self.workers = workers
        self.pool = pool
        self._pool_threads = None
        self.progress = progress
        self.worker_timeout = float(worker_timeout)
        # when the last worker was first seen gone: one clock for every map of
        # the runner (a night's captures share it), not one per map
        self._alone_since = None
        self._alone_lock = threading.Lock()
        self.stopped = threading.Event()  # see stop()

    def stop(self):
        """Refuse every task not yet started, of every run on this runner
        (their map raises :class:`ops.RunError`); running tasks finish.  For a
        night whose running captures were abandoned: they start nothing
        more beside the night's end.  A ``processes`` runner refuses at the
        next map only (its pool's queue is its own)."""
        self.stopped.set()

    def describe(self):
        """The scheduler in use, for the log: ``threads (2 workers)``,
        ``dask.distributed at tcp://127.0.0.1:8786 (4 workers)`` ..."""
        if self.client is not None:
            try:
                info = self.client.scheduler_info()
                return f"dask.distributed at {info.get('address', '?')} ({len(info.get('workers', {}))} workers)"
            except (OSError, TimeoutError):
                return "dask.distributed (scheduler out of reach)"
        if self.scheduler == "synchronous":
            return "synchronous (1 worker)"
        return f"{self.scheduler} ({self.local_workers()} workers)"

    def local_workers(self):
        """The workers of a local scheduler (its pool's, the count asked for,
        or one per core); for a cluster, the count asked for or this
        machine's cores, a guess that asks the scheduler nothing."""
        if self.scheduler == "synchronous":
            return 1
        return getattr(self.pool, "_max_workers", None) or self.workers or os.cpu_count() or 1

    def _alone_for(self, workers_left):
        """Seconds since the last worker left (0 while some are there)."""
        with self._alone_lock:
            if workers_left:
                self._alone_since = None
                return 0.0
            if self._alone_since is None:
                self._alone_since = time.monotonic()
            return time.monotonic() - self._alone_since

    def map(self, label, func, argument_lists):
        """``[func(*args) for args in argument_lists]`` on the scheduler; results
        in order, and tasks started in the order of the list as far as the
        scheduler allows (callers put the longest first, so that no core idles
        at the end while one long task finishes)."""
        argument_lists = list(argument_lists)
        if not argument_lists:
            return []
        if self.stopped.is_set():
            raise RunError(f"{label}: the runner was stopped")
        progress = _Progress(label, len(argument_lists)) if self.progress else None
        with _one_thread_each():
            if self.client is not None:
                return self._map_distributed(progress, func, argument_lists)
            return self._map_local(progress, label, func, argument_lists)

    def _map_distributed(self, progress, func, argument_lists):
        from distributed import wait

        n, owner = len(argument_lists), os.getpid()
        # a cluster's workers are not rsmb's own: its tasks leave their settings as they found them
        futures = [self.client.submit(_call, func, args, owner, False, pure=False, priority=n - i)
                   for i, args in enumerate(argument_lists)]
        pending = set(futures)
        while pending:
            try:
                done = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = set()
            pending -= done
            if progress is not None and done:
                progress.step(len(done))
            if not pending:
                break
            if self.stopped.is_set():
                self.client.cancel(list(pending))
                raise RunError(f"the runner was stopped ({len(pending)} of {n} tasks unfinished)")
            if self._alone_for(self._workers_left()) > self.worker_timeout:
                self.client.cancel(list(pending))
                raise RunError(f"scheduler: no dask worker left for {self.worker_timeout:g} s "
                               f"({len(pending)} of {n} tasks unfinished); see --worker-timeout")
        return self.client.gather(futures)

    def _workers_left(self):
        try:
            return len(self.client.scheduler_info().get("workers", {})) > 0
        except (OSError, TimeoutError):  # the scheduler itself is out of reach
            return False

    def _map_local(self, progress, label, func, argument_lists):
        # dask's local schedulers start independent tasks in descending key order
        n, owner = len(argument_lists), os.getpid()
        token = f"{label}-{id(argument_lists):x}"  # runs sharing a pool keep their own keys
        tasks = [dask.delayed(_call, pure=False)(func, args, owner, dask_key_name=f"{token}-{n - i:08d}")
                 for i, args in enumerate(argument_lists)]
        kw, tracked = {}, None
        if self.scheduler == "threads":
            # a task that fails makes dask raise while the others still run: the
            # caller's clean-up (removing a .partial store) must wait for them
            tracked = kw["pool"] = _Tracked(self.pool or self._threads(), self.stopped)
        elif self.pool is not None and self.scheduler != "synchronous":
            kw["pool"] = self.pool
        elif self.workers and self.scheduler != "synchronous":
            kw["num_workers"] = self.workers
        try:
            with _DaskProgress(progress) if progress is not None else contextlib.nullcontext():
                return list(dask.compute(*tasks, scheduler=_local_get(self.scheduler), **kw))
        except BaseException:
            if tracked is not None:
                tracked.settle()
            raise

    def _threads(self):
        """This runner's own thread pool (dask's context-aware one), made once."""
        if self._pool_threads is None:
            try:
                from dask.threaded import ContextAwareThreadPoolExecutor as Executor
            except ImportError:  # dask before 2024.12
                from concurrent.futures import ThreadPoolExecutor as Executor

            self._pool_threads = Executor(self.workers or os.cpu_count() or 1)
        return self._pool_threads


def _local_get(scheduler):
    """dask's scheduler function for a local scheduler's name.  Given the
    function rather than the name, ``dask.compute`` does not look for a
    dask.distributed client first, which imports dask.distributed (a
    fraction of a second of the run's serial start, in a run that uses no
    cluster); the function is the one the name stands for."""
    if scheduler == "threads":
        import dask.threaded

        return dask.threaded.get
    if scheduler == "processes":
        import dask.multiprocessing

        return dask.multiprocessing.get
    if scheduler == "synchronous":
        import dask.local

        return dask.local.get_sync
    return scheduler


class _Tracked:
    """An executor that remembers what it was given, so that a failed map can
    cancel the tasks not started and wait for the running ones; once
    ``stopped`` is set (:meth:`Runner.stop`) what it is given fails at once."""

    def __init__(self, pool, stopped):
        self.pool, self.futures, self.stopped = pool, [], stopped
        self._max_workers = pool._max_workers

    def submit(self, fn, *args, **kwargs):
        future = self.pool.submit(_refused if self.stopped.is_set() else fn, *args, **kwargs)
        self.futures.append(future)
        return future

    def settle(self):
        import concurrent.futures

        for future in self.futures:
            future.cancel()
        concurrent.futures.wait(self.futures)


def _refused(*args, **kwargs):
    raise RunError("the runner was stopped")


def _call(func, args, owner_pid, owned=True):
    """Run one task.  In a worker process rsmb owns (``processes``), make the
    process-wide settings first (:func:`configure_process`); in a worker it
    does not own (``owned`` False: a dask.distributed worker, possibly
    shared), one OpenCV and one BLAS thread while rsmb's tasks run there, the
    worker's own counts restored after the last of them, and malloc left
    alone (its setting cannot be undone)."""
    if os.getpid() == owner_pid:
        return func(*args)
    if owned:
        configure_process()
        return func(*args)
    with _one_thread_each():
        return func(*args)


class _DaskProgress(dask.callbacks.Callback):
    def __init__(self, progress):
        super().__init__()
        self.progress = progress

    def _posttask(self, key, result, dsk, state, worker_id):
        self.progress.step()


def check_scheduler(scheduler):
    """Raise :class:`ops.ParameterError` unless ``scheduler`` names a local
    scheduler, a ``tcp://host:port`` address, a dask scheduler file (JSON with
    an ``address``), or
    ``slurm`` / ``pbs`` with dask-jobqueue installed and the ``cores`` and
    ``memory`` of a job in dask's jobqueue configuration (checked before any
    work, so a night never starts only to fail when its cluster is made)."""
    if scheduler in SCHEDULERS:
        return
    if scheduler in JOBQUEUE:
        _check_jobqueue(scheduler)
        return
    if isinstance(scheduler, str) and scheduler.startswith("tcp://"):
        host, _, port = scheduler[len("tcp://"):].rpartition(":")
        if host and port.isdigit():
            return
        raise ParameterError(f"scheduler: expected tcp://HOST:PORT, got {scheduler!r}")
    if isinstance(scheduler, str) and os.path.isfile(scheduler):
        _check_scheduler_file(scheduler)
        return
    raise ParameterError(f"scheduler: expected one of {', '.join(SCHEDULERS + JOBQUEUE)}, a tcp:// address or "
                         f"a scheduler file, got {scheduler!r}")


def _check_scheduler_file(path):
    """A dask scheduler file: JSON whose ``address`` is a string (what
    ``dask scheduler --scheduler-file`` writes)."""
    try:
        with open(path, encoding="utf-8") as f:
            info = json.load(f)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ParameterError(f"scheduler: {path} is not a dask scheduler file (JSON with an 'address'): "
                             f"{type(exc).__name__}") from None
    if not isinstance(info, dict) or not isinstance(info.get("address"), str) or not info["address"]:
        raise ParameterError(f"scheduler: {path} is not a dask scheduler file (JSON with an 'address')")


JOBQUEUE = ("slurm", "pbs")


def _check_jobqueue(kind):
    """dask-jobqueue importable, and what every job of ``kind`` needs in dask's
    configuration (``jobqueue.<kind>.cores`` and ``.memory``, which it has no
    default for)."""
    try:
        import dask_jobqueue  # noqa: F401 - importing it loads its defaults into dask's configuration
    except ImportError:
        raise ParameterError(f"scheduler: {kind} needs dask-jobqueue: pip install 'rsmb[cluster]'") from None
    missing = [f"jobqueue.{kind}.{key}" for key in ("cores", "memory")
               if dask.config.get(f"jobqueue.{kind}.{key}", None) is None]
    if missing:
        raise ParameterError(f"scheduler: {kind}: dask's jobqueue configuration has no {' and no '.join(missing)}; "
                             f"see the README's section on SLURM")


@contextlib.contextmanager
def open_runner(scheduler="threads", *, workers=None, shared=False, progress=True, worker_timeout=WORKER_TIMEOUT):
    """A :class:`Runner` for ``scheduler`` (see the module docstring).

    ``shared`` gives a local scheduler one executor of ``workers`` (default: one
    per core) for every run the runner serves at once.  ``slurm`` and ``pbs``
    build a dask-jobqueue cluster from dask's own jobqueue configuration
    (``jobqueue.slurm.*`` / ``jobqueue.pbs.*``), ``workers`` jobs of it.

    Raises
    ------
    ParameterError
        For an unknown scheduler name or a scheduler file that does not exist.
    InputError
        When the dask.distributed scheduler cannot be reached, or a jobqueue
        cluster cannot be made.
    """
    check_scheduler(scheduler)
    if scheduler in SCHEDULERS:
        if not shared or scheduler == "synchronous":
            yield Runner(scheduler, workers=workers, progress=progress)
            return
        from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

        executor = ThreadPoolExecutor if scheduler == "threads" else ProcessPoolExecutor
        with executor(workers or os.cpu_count() or 1) as pool:
            yield Runner(scheduler, workers=workers, pool=pool, progress=progress)
        return
    from distributed import Client

    with contextlib.ExitStack() as stack:
        if scheduler in JOBQUEUE:
            cluster = stack.enter_context(jobqueue_cluster(scheduler))
            cluster.scale(jobs=workers or 1)
            kw = {"address": cluster}
        else:
            kw = {"address": scheduler} if scheduler.startswith("tcp://") else {"scheduler_file": scheduler}
        try:
            client = stack.enter_context(Client(timeout="30s", **kw))
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"scheduler: cannot connect to {scheduler} ({one_line(exc)})") from None
        yield Runner("distributed", client=client, progress=progress, worker_timeout=worker_timeout)


def jobqueue_cluster(kind):
    """A dask-jobqueue cluster (``slurm`` or ``pbs``) configured by dask's
    jobqueue configuration alone; needs the ``cluster`` extra.

    Raises
    ------
    InputError
        Without dask-jobqueue, or when its configuration is incomplete.
    """
    try:
        import dask_jobqueue
    except ImportError:
        raise InputError(f"scheduler: {kind} needs dask-jobqueue: pip install 'rsmb[cluster]'") from None
    cls = {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[kind]
    try:
        return cls()
    except (ValueError, TypeError, KeyError) as exc:
        raise InputError(f"scheduler: {kind}: dask's jobqueue configuration ({kind}) is incomplete "
                         f"({one_line(exc)}); see the README's section on SLURM") from None
