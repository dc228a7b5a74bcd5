"""Where a build's shard tasks run: in this process, in a local process pool, or on a Dask
cluster (``apcg dataset build --engine dask [--address ADDR]``), one task per shard.

Every engine is handed the same small, picklable ``ShardTask``s and the same pure function
(``shards.run_task``), which computes one shard and writes it atomically itself; an engine only
decides where that happens and yields each finished task's result in completion order. So where
a shard was computed never shows in its bytes, and a task whose worker dies (a crash, a kill)
is simply run again: the rerun writes the same bytes under the same name.

Engines are found by name in ``ENGINES``. A cluster library is imported only when its engine
is used, so the project installs and builds without it.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import CancelledError
from dataclasses import dataclass
from pathlib import Path

from apcg_core.errors import APCGError, InputError
from apcg_core.testpoints import wait_point

from .shards import close_simulators

# fn(tasks) -> results as they finish
Runner = Callable[[Callable, Iterable], Iterator]


@dataclass(frozen=True)
class RunSettings:
    """How the user asked the shards to be run (the command line's --workers and friends)."""

    workers: int = 1
    address: str | None = None  # a running cluster's scheduler; None: start one here
    tasks_per_process: int | None = None  # as given; None: workers live for the whole build
    output: str = ""  # the dataset directory, which a cluster's workers must see too
    connect_timeout_s: float | None = None  # as given; None: CONNECT_TIMEOUT_S
    # the job's header in ``output``, written before the workers start: each worker must see
    # it as this machine does (a scene sequence's is sequence.json)
    record: str = "dataset.json"

    @property
    def writers_are_local(self) -> bool:
        """Every shard is written by a process of this machine, so the pid in a temporary
        file's name can be checked here (a cluster's workers are processes of other hosts)."""
        return self.address is None


def worker_init(parent: int | None = None) -> None:
    """Set-up of every worker process this machine starts.

    Ctrl-C reaches the whole foreground process group; the workers ignore it (they are also
    started with it blocked, see _sigint_held), so that only the build's own process reacts
    (stops the workers, reports, exits 130) and no worker prints a traceback of its own.

    A worker ends with the process that started it (``parent``, its pid): killed outright
    (SIGKILL, the OOM killer), that process cannot stop its pool, whose workers went on with
    their tasks and then printed pages of BrokenPipe tracebacks. Each worker now watches its
    parent (:func:`_end_with_parent`); a shard it was writing stays a temporary file, which
    the next run removes.

    A spawned child inherits its parent's sys.path; once the parent has imported the bpy
    module that includes Blender's own scripts/modules folder, whose ``bpy`` package would
    then shadow the bpy extension module in the child. Drop those entries."""
    with contextlib.suppress(ValueError):  # not the main thread: nothing to ignore there
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    marker = f"{os.sep}bpy{os.sep}"
    sys.path[:] = [p for p in sys.path if not (marker in p and f"{os.sep}scripts" in p)]
    if parent is not None:
        _end_with_parent(parent)


PARENT_CHECK_S = 1.0  # how often a worker looks for its parent


def _end_with_parent(parent: int) -> None:
    """A thread of the worker that ends it (quietly, exit 1) once its parent is gone: its
    parent pid is then another process's (the init process, or a subreaper). Not the
    kernel's PR_SET_PDEATHSIG: that follows the parent's *thread* that started the worker,
    and with --tasks-per-process the pool's workers were killed while the build lived (one
    build in three hung on a lost task)."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(1)

    threading.Thread(target=watch, name="apcg-parent-watch", daemon=True).start()


class LocalEngine:
    """This process (``--workers 1``), or a pool of ``--workers`` spawned processes."""

    name = "local"
    summary = "this machine: one process, or a process pool with --workers N (default)"

    def check(self, settings: RunSettings) -> None:
        if settings.address:
            raise InputError(f"--address needs a cluster engine: --engine "
                             f"{' or '.join(n for n in ENGINES if n != self.name)}")
        _check_timeout_needs_address(settings)

    @contextlib.contextmanager
    def start(self, settings: RunSettings) -> Iterator[Runner]:
        if settings.workers == 1 and not settings.tasks_per_process:
            yield map
            return
        per = settings.tasks_per_process
        # Imported only here: Debian's Blender 3.4 crashes at exit once multiprocessing has
        # been imported, and inside a Blender binary builds run with one worker.
        import multiprocessing as mp
        ctx = mp.get_context("spawn")
        # Leaving the stack terminates the pool (on Ctrl-C too) and waits for its workers.
        with contextlib.ExitStack() as stack:
            with _sigint_held():
                pool = stack.enter_context(ctx.Pool(settings.workers, initializer=worker_init,
                                                    initargs=(os.getpid(),),
                                                    maxtasksperchild=per))
                wait_point("build.workers-starting")
            yield pool.imap_unordered


DASK_PIP = "pip install 'apcg[engine]' (or: pip install 'dask[distributed]')"
DASK_PORT = 8786  # the port `dask scheduler` listens on by default
CONNECT_TIMEOUT_S = 10.0  # --connect-timeout-s's default


def _check_timeout_needs_address(settings: RunSettings) -> None:
    if settings.connect_timeout_s is not None and not settings.address:
        raise InputError(f"--connect-timeout-s {settings.connect_timeout_s:g} bounds the "
                         "connection to a running cluster's scheduler: it needs --engine dask "
                         "--address ADDR")


class DaskEngine:
    """A Dask cluster: the one at ``--address``, or a local one of ``--workers`` processes.

    Retries: when a worker dies, its scheduler gives the worker's tasks to another worker, up
    to ``distributed.scheduler.allowed-failures`` times (3 by default) per task."""

    name = "dask"
    summary = ("a Dask cluster: the scheduler at --address, or a local cluster of --workers "
               "processes")

    def check(self, settings: RunSettings) -> None:
        _import_distributed()
        if settings.tasks_per_process:
            raise InputError("--tasks-per-process applies to the local engine only (a cluster's "
                             "workers are long-lived)")
        if settings.address and settings.workers > 1:
            raise InputError("--workers sets the size of a local cluster; with --address the "
                             "cluster's own workers do the work: leave --workers out")
        _check_timeout_needs_address(settings)
        if settings.address:
            _check_scheduler(settings.address, _connect_timeout(settings))

    @contextlib.contextmanager
    def start(self, settings: RunSettings) -> Iterator[Runner]:
        distributed = _import_distributed()
        with _dask_client(distributed, settings) as client:
            where = (f"the Dask scheduler at {settings.address}" if settings.address
                     else "the local Dask cluster")
            yield lambda fn, tasks: _dask_results(distributed, client, fn, tasks, where)
            if settings.address:  # a long-lived cluster: free the workers' cached meshes
                with contextlib.suppress(Exception):
                    client.run(close_simulators)


ENGINES = {e.name: e for e in (LocalEngine(), DaskEngine())}


def get_engine(name: str):
    """The engine called ``name``, or a one-line error listing the known ones."""
    try:
        return ENGINES[name]
    except KeyError:
        known = "; ".join(f"{n}: {e.summary}" for n, e in ENGINES.items())
        raise InputError(f"unknown engine {name!r}; known engines: {known}") from None


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise InputError(f"--engine dask needs Dask's distributed scheduler, which is not "
                         f"installed ({exc}); install it with: {DASK_PIP}") from None
    return distributed


def _host_port(address: str) -> tuple[str, int]:
    from distributed.comm import parse_address, parse_host_port
    try:
        scheme, location = parse_address(address, strict=False)
        host, port = parse_host_port(location, default_port=DASK_PORT)
    except (ValueError, TypeError) as exc:
        raise InputError(f"--address {address!r} is not a scheduler address (e.g. "
                         f"tcp://head-node:{DASK_PORT} or head-node:{DASK_PORT}): {exc}") from None
    if scheme not in ("tcp", "tls"):
        raise InputError(f"--address {address!r}: only tcp:// and tls:// schedulers are "
                         f"supported, got {scheme}://")
    return host, int(port)


def _connect_timeout(settings: RunSettings) -> float:
    return settings.connect_timeout_s or CONNECT_TIMEOUT_S


def _check_scheduler(address: str, timeout_s: float) -> None:
    """Fail in seconds, before anything is written, unless a Dask scheduler answers at
    ``address``: nothing listening, a silent server, or a server of another protocol (an HTTP
    server, a database) get one line naming the address, never a wait without end."""
    import asyncio

    from distributed import Security
    from distributed.comm import connect

    host, port = _host_port(address)
    fix = (f"start one with `dask scheduler` on that machine (it listens on port {DASK_PORT}), "
           "or leave out --address to start a local cluster")
    try:  # first the plain socket: "refused" or "no route" say more than Dask's wrapping
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise InputError(f"cannot reach a Dask scheduler at --address {address} ({exc}); "
                         f"{fix}") from None

    tls = Security().get_connection_args("client")
    if address.startswith("tls://") and tls.get("ssl_context") is None:
        raise InputError(f"--address {address} is a TLS scheduler, and Dask's TLS settings are "
                         "not set: give distributed.comm.tls.ca-file, .client.cert and "
                         ".client.key in the Dask config (or DASK_DISTRIBUTED__COMM__TLS__* "
                         "variables)")

    async def identity():
        # Dask's own limit later than ours, so that a silent server is told as one
        comm = await connect(address, timeout=2 * timeout_s, **tls)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout_s))
    except TimeoutError:
        raise InputError(f"nothing at --address {address} answered as a Dask scheduler within "
                         f"{timeout_s:g} s (--connect-timeout-s): something else listens on port "
                         f"{port}, or a scheduler there is too busy to answer; {fix}, or raise "
                         "--connect-timeout-s") from None
    except Exception as exc:  # noqa: BLE001 - whatever another protocol makes Dask's comm raise
        # a network error says what happened; another protocol's bytes read as Dask's frames
        # give nonsense (an exabyte-sized message), better left out
        why = f" ({exc})" if isinstance(exc, OSError) else ""
        raise InputError(f"--address {address} is not a Dask scheduler: what answers there "
                         f"does not speak Dask's protocol{why}; {fix}") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise InputError(f"--address {address} is not a Dask scheduler (it answers as "
                         f"{kind or 'something else'}); {fix}")


@contextlib.contextmanager
def _dask_client(distributed, settings: RunSettings):
    if settings.address:
        with _dask_logs_quiet(), distributed.Client(
                settings.address, timeout=f"{_connect_timeout(settings)}s",
                set_as_default=False) as client:
            _check_workers(client, settings)
            yield client
        return
    with contextlib.ExitStack() as stack:
        with _sigint_held():
            # ":0", a free port: None does not turn the dashboard off (dask/distributed
            # issue 8136), and with a second cluster on the machine (another --shard part)
            # its default port 8787 is taken and a multi-line warning is printed
            cluster = stack.enter_context(distributed.LocalCluster(
                n_workers=settings.workers, threads_per_worker=1, processes=True,
                dashboard_address=":0", silence_logs=logging.ERROR))
            wait_point("build.workers-starting")
        client = stack.enter_context(distributed.Client(cluster, set_as_default=False))
        client.register_worker_callbacks(setup=worker_init)
        yield client


@contextlib.contextmanager
def _dask_logs_quiet():
    """Dask's client logs its own tracebacks on stderr (a lost scheduler, each reconnection
    tried); what went wrong is said once, in the build's own one line."""
    # Dask's logging config gives some of its loggers levels of their own
    logs = [logging.getLogger(name) for name in list(logging.root.manager.loggerDict)
            if name == "distributed" or name.startswith("distributed.")]
    levels = [log.level for log in logs]
    for log in logs:
        log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for log, level in zip(logs, levels, strict=True):
            log.setLevel(level)


@contextlib.contextmanager
def _sigint_held():
    """Block SIGINT in this thread while it starts worker processes, and the threads that will
    start more (a pool's, a cluster's event loop): a blocked signal stays blocked in every
    thread and process made meanwhile, so no worker ever sees Ctrl-C, not even while it boots
    (before worker_init), and only this process answers it. A Ctrl-C that came meanwhile is
    not lost: it is delivered here when the block is lifted."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signals are the main thread's business
        return
    # multiprocessing starts its resource tracker at the first spawn and then unblocks SIGINT
    # in the spawning thread: start it before blocking.
    from multiprocessing import resource_tracker
    resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


WORKERS_WAIT_S = 60


def _check_workers(client, settings: RunSettings) -> None:
    """A cluster's workers must run this apcg and see the dataset directory (shared storage):
    refuse otherwise, naming the workers, rather than fail shard by shard."""
    try:
        client.wait_for_workers(1, timeout=WORKERS_WAIT_S)
    except TimeoutError:
        raise InputError(f"no worker joined the scheduler at {settings.address} within "
                         f"{WORKERS_WAIT_S} s; start workers with `dask worker "
                         f"{settings.address}`") from None
    from apcg_core import __version__
    want = (__version__, _file_digest(Path(settings.output) / settings.record))
    try:
        seen = client.run(worker_view, settings.output, settings.record)
    except ImportError as exc:
        raise InputError(f"the workers at {settings.address} cannot import apcg ({exc}); "
                         "install the same apcg (with its sim extra) on every worker") from None
    wrong_version = sorted(w for w, (version, _) in seen.items() if version != want[0])
    if wrong_version:
        raise InputError(f"workers {wrong_version} run another apcg version than {want[0]}; "
                         "install the same one everywhere")
    blind = sorted(w for w, (_, digest) in seen.items() if digest != want[1])
    if blind:
        raise InputError(f"workers {blind} do not see the dataset directory {settings.output} "
                         "as this machine does; it must be shared storage mounted at the same "
                         "path on every machine")


def worker_view(output: str, record: str = "dataset.json") -> tuple[str, str | None]:
    """Run on each worker: its apcg version and the digest of the job's header it sees."""
    from apcg_core import __version__
    return __version__, _file_digest(Path(output) / record)


def _file_digest(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _dask_results(distributed, client, fn: Callable, tasks: list, where: str) -> Iterator:
    # Named keys: the dashboard shows which shard runs where; the token keeps two builds on
    # one cluster apart. pure=False: a rerun after a crash must run, not be looked up.
    token = uuid.uuid4().hex[:8]
    futures = client.map(fn, tasks, pure=False,
                         key=[f"apcg-shard-{t.index:05d}-{token}" for t in tasks])
    try:
        for future in distributed.as_completed(futures, loop=client.loop):
            try:
                yield future.result()
            except distributed.KilledWorker:
                raise APCGError(f"every worker that ran shard task {future.key} died "
                                "(distributed.scheduler.allowed-failures + 1 times): out of "
                                "memory? See the workers' logs. Finished shards are kept: run "
                                "the same command again to resume") from None
            except CancelledError as exc:  # the scheduler went away, or someone cancelled it
                raise APCGError(f"shard task {future.key} was cancelled by {where} "
                                f"({getattr(exc, 'reason', None) or exc}): did the scheduler "
                                "stop? Finished shards are kept: run the same command again "
                                "to resume") from None
    finally:
        # Stopped early (Ctrl-C, an error): unstarted tasks must not run on a shared cluster;
        # a scheduler that is gone has nothing left to cancel.
        with contextlib.suppress(Exception):
            client.cancel(futures)
