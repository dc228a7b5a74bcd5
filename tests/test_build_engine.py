"""`apcg dataset build --engine dask`: shards computed on a Dask cluster, and Ctrl-C.

Real processes, a real Dask cluster (a local one the engine starts, or a `dask scheduler` and
`dask worker` this test starts), real embree: the directory an engine build leaves must equal a
single-process build byte for byte, also when a worker process is killed (SIGKILL) in the
middle of a shard; Ctrl-C must stop a build with exit 130, a line saying how far it got, no
temporary file left, and the same command must then finish the same bytes.
"""

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("embreex")
pytest.importorskip("distributed")

from dataset_builder.build import build_dataset, time_engine_build  # noqa: E402

# A sixth of the committed `cpu` config (33 of its 196 shards: 8,400 of 49,000 samples over
# 33 of its 98 types, both splits): the whole config takes 7-15 s a build on 2 cores, and the
# tests below build it many times.
CPU_PART = "0/6"


def _build_cmd(out: Path, *extra: str, config: str = "cpu") -> list[str]:
    part = ["--shard", CPU_PART] if config == "cpu" else []
    return [sys.executable, "-m", "apcg_core.cli", "dataset", "build", "--config", config,
            "-o", str(out), "--no-progress", *part, *extra]


def _files(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def _assert_same(got: Path, want: dict[str, bytes]) -> None:
    files = _files(got)
    assert sorted(files) == sorted(want)  # no temporary or lock file, nothing missing
    assert [name for name in want if files[name] != want[name]] == []


@pytest.fixture(scope="module")
def demo_reference(tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("demo_single") / "ds"
    build_dataset("demo", out, progress=False)
    files = _files(out)
    assert "manifest.json" in files and sum(f.startswith("shards/") for f in files) == 18
    return files


@pytest.fixture(scope="module")
def cpu_reference(tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("cpu_single") / "ds"
    build_dataset("cpu", out, shard_spec=CPU_PART, progress=False)
    files = _files(out)
    assert sum(f.startswith("shards/") for f in files) == 33
    return files


def test_local_cluster_build_of_demo_equals_single_process(demo_reference, tmp_path):
    # The bench entry point: a local 2-worker cluster started and stopped by the engine.
    timing = time_engine_build("demo", engine="dask", workers=2, out_dir=tmp_path / "ds")
    _assert_same(tmp_path / "ds", demo_reference)
    assert timing["shards"] == 18 and timing["samples"] == 960
    assert timing["rays"] > 960 and timing["seconds"] > 0


def test_blender_backend_on_a_local_cluster_equals_one_process(tmp_path):
    """Each Dask worker imports bpy and keeps its casters across shards; the bytes are a
    single-process Blender build's."""
    outs = {}
    for name, extra in (("one", []), ("dask", ["--engine", "dask", "--workers", "2"])):
        outs[name] = tmp_path / name
        r = subprocess.run(_build_cmd(outs[name], "--backend", "blender", *extra,
                                      config="demo"),
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
    one = _files(outs["one"])
    assert sum(f.startswith("shards/") for f in one) == 18
    _assert_same(outs["dask"], one)


def test_engine_build_of_cpu_part_equals_single_process(cpu_reference, tmp_path):
    r = subprocess.run(_build_cmd(tmp_path / "ds", "--engine", "dask", "--workers", "2"),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["built_shards"] == 33
    _assert_same(tmp_path / "ds", cpu_reference)


def _dask_cli(*args: str) -> list[str]:
    return [str(Path(sys.executable).with_name("dask")), *args]


@contextlib.contextmanager
def _dask_cluster(tmp_path: Path, env: dict, *worker_args: str):
    """A `dask scheduler` and `dask worker WORKER_ARGS`, started as the docs' cluster recipe
    does, each in its own process group (the teardown stops a nanny's workers too), the
    workers in a directory that is not the build's; yields (address, processes)."""
    scheduler_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "cluster.log", "w")  # noqa: SIM115 - closed below
    procs = [subprocess.Popen(_dask_cli("scheduler", "--host", "127.0.0.1", "--port", "0",
                                        "--no-dashboard", "--scheduler-file",
                                        str(scheduler_file)), stdout=log, stderr=log,
                              env=env, start_new_session=True)]
    try:
        deadline = time.monotonic() + 120
        while not scheduler_file.exists():
            assert time.monotonic() < deadline, "no scheduler in 120 s"
            time.sleep(0.05)
        address = json.loads(scheduler_file.read_text())["address"]
        elsewhere = tmp_path / "workers-cwd"
        elsewhere.mkdir()
        procs.append(subprocess.Popen(
            _dask_cli("worker", address, "--nthreads", "1", "--no-dashboard",
                      "--local-directory", str(tmp_path / "scratch"), *worker_args),
            stdout=log, stderr=log, env=env, cwd=elsewhere, start_new_session=True))
        yield address, procs
    finally:
        for p in procs:  # the test is over: no orderly shutdown needed
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        log.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _kill_a_worker_mid_shard(cmd, hold, cwd=None) -> tuple[subprocess.CompletedProcess, int]:
    """Run the build ``cmd`` on a cluster whose workers hold at build.shard-computing; SIGKILL
    the first worker process seen running a shard task there, then let the others go on:
    (the build's result, the killed pid)."""
    point = "build.shard-computing"
    build = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             cwd=cwd)
    try:
        pid = hold.wait(point, build)
        os.kill(pid, signal.SIGKILL)
        while _alive(pid):  # gone (the nanny reaps it) before the others may finish
            time.sleep(0.01)
        hold.release(point)
        out, err = build.communicate(timeout=300)
    finally:
        if build.poll() is None:
            build.kill()
            build.wait()
    return subprocess.CompletedProcess(cmd, build.returncode, out, err), pid


@pytest.mark.parametrize("retries", [None, 0], ids=["rerun", "no-retries"])
def test_a_worker_killed_mid_shard(cpu_reference, tmp_path, hold, retries):
    """A shard task whose worker dies is run again (Dask's allowed-failures, 3 by default) and
    the dataset is the single-process one byte for byte; without retries the build fails in
    one line and writes no manifest."""
    env = hold.env("build.shard-computing")
    if retries is not None:
        env["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] = str(retries)
    with _dask_cluster(tmp_path, env, "--nworkers", "2") as (address, _):
        # -o relative to the build's own working directory, which the workers do not share
        r, pid = _kill_a_worker_mid_shard(
            _build_cmd(Path("ds"), "--engine", "dask", "--address", address), hold,
            cwd=tmp_path)
    assert not _alive(pid)
    if retries is None:
        assert r.returncode == 0, r.stderr
        _assert_same(tmp_path / "ds", cpu_reference)
        return
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("apcg dataset: error: every worker "
                                                        "that ran shard task apcg-shard-")
    assert not (tmp_path / "ds" / "manifest.json").exists()


def test_a_scheduler_lost_mid_build_is_one_line_and_the_build_resumes(demo_reference,
                                                                       tmp_path, hold):
    point = "build.shard-written"
    with _dask_cluster(tmp_path, hold.env(point), "--nworkers", "1") as (address, procs):
        cmd = _build_cmd(tmp_path / "ds", "--engine", "dask", "--address", address,
                         config="demo")
        build = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True)
        try:
            hold.wait(point, build)  # a shard written, the worker holding its task
            os.killpg(procs[0].pid, signal.SIGKILL)  # the scheduler, and nothing else
            procs[0].wait()
            hold.release(point)
            t0 = time.monotonic()
            _, err = build.communicate(timeout=300)
            took = time.monotonic() - t0
        finally:
            if build.poll() is None:
                build.kill()
                build.wait()
    assert build.returncode == 2 and len(err.strip().splitlines()) == 1, err
    last = err.strip()
    assert last.startswith("apcg dataset: error: shard task apcg-shard-") and (
        f"was cancelled by the Dask scheduler at {address}" in last and
        "run the same command again to resume" in last), err
    assert took < 120, took  # Dask's reconnection attempts, then the line: no hang
    r = subprocess.run(_build_cmd(tmp_path / "ds", config="demo"), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    _assert_same(tmp_path / "ds", demo_reference)


def _ctrl_c_at(cmd, hold, point: str) -> tuple[int, str]:
    """Run ``cmd`` in its own process group (a shell's foreground job, which Ctrl-C reaches
    whole), held at the test point ``point``; once a process of it waits there, send SIGINT
    to the group, then let the point go: (exit code, stderr)."""
    build = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True, env=hold.env(point))
    try:
        hold.wait(point, build)
        os.killpg(build.pid, signal.SIGINT)
        hold.release(point)
        _, err = build.communicate(timeout=300)
    finally:
        if build.poll() is None:
            os.killpg(build.pid, signal.SIGKILL)
            build.wait()
    return build.returncode, err


@pytest.mark.parametrize("how", [[], ["--workers", "2"], ["--engine", "dask", "--workers", "2"]],
                         ids=["one-process", "local-pool", "dask"])
def test_ctrl_c_stops_cleanly_and_the_same_command_resumes(cpu_reference, tmp_path, hold, how):
    out = tmp_path / "ds"
    cmd = _build_cmd(out, *how)
    # Ctrl-C once a shard is written, while every worker that wrote one waits: it lands
    # among the shards, never after the last
    rc, err = _ctrl_c_at(cmd, hold, "build.shard-written")
    assert rc == 130, err
    assert "Traceback" not in err
    done = len(list((out / "shards").glob("*.npz")))
    assert 1 <= done < 33
    assert (f"apcg dataset: interrupted: {done} of 33 shards of --shard {CPU_PART} are done"
            in err) and "run the same command again to resume" in err
    left = [p.name for p in out.rglob("*") if ".part" in p.name or ".lock" in p.name]
    assert left == []
    assert not (out / "manifest.json").exists()  # a part never writes it; nor does a stop
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["skipped_shards"] == done
    _assert_same(out, cpu_reference)


@pytest.mark.parametrize("how", [["--workers", "2"], ["--engine", "dask", "--workers", "2"]],
                         ids=["local-pool", "dask"])
def test_ctrl_c_while_the_workers_start_is_not_lost(tmp_path, hold, how):
    # Held just after the pool or cluster is started: Ctrl-C lands while its workers boot,
    # when a worker that saw it would print a traceback and a build that ignored it would
    # run on to the end.
    out = tmp_path / "ds"
    rc, err = _ctrl_c_at(_build_cmd(out, *how), hold, "build.workers-starting")
    assert rc == 130, err
    assert "Traceback" not in err and "run the same command again" in err.lower(), err
    assert [p.name for p in out.rglob("*") if ".part" in p.name or ".lock" in p.name] == []
    assert not list((out / "shards").glob("*.npz"))  # stopped before any shard


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nothing listens once it is closed


@pytest.mark.parametrize("extra, says", [
    (["--engine", "ray"], "unknown engine 'ray'; known engines: local: "),
    (["--engine", "dask", "--address", "tcp://127.0.0.1:{port}"],
     "cannot reach a Dask scheduler at --address tcp://127.0.0.1:{port}"),
    (["--engine", "dask", "--address", "tcp://head:node:x"], "is not a scheduler address"),
    (["--engine", "dask", "--address", "inproc://x"], "only tcp:// and tls://"),
    (["--engine", "dask", "--address", "tls://127.0.0.1:{port}"],
     "cannot reach a Dask scheduler at --address tls://127.0.0.1:{port}"),
    (["--address", "tcp://127.0.0.1:8786"], "--address needs a cluster engine: --engine dask"),
    (["--engine", "dask", "--tasks-per-process", "2"], "applies to the local engine only"),
    (["--engine", "dask", "--workers", "2", "--address", "tcp://127.0.0.1:{port}"],
     "with --address the cluster's own workers do the work"),
    (["--connect-timeout-s", "5"], "--connect-timeout-s 5 bounds the connection to a running "
     "cluster's scheduler: it needs --engine dask --address ADDR"),
    (["--engine", "dask", "--connect-timeout-s", "5"], "it needs --engine dask --address ADDR"),
    (["--engine", "dask", "--address", "tcp://127.0.0.1:{port}", "--connect-timeout-s", "0"],
     "--connect-timeout-s 0.0 not accepted: a number of seconds > 0 and <= 3600"),
], ids=["unknown", "unreachable", "malformed", "scheme", "tls-unreachable", "no-engine",
        "tasks-per-process",
        "workers-and-address", "timeout-without-address", "timeout-local-cluster",
        "timeout-zero"])
def test_engine_mistakes_get_one_line_and_write_nothing(tmp_path, extra, says):
    port = _closed_port()
    extra = [e.format(port=port) for e in extra]
    t0 = time.monotonic()
    r = subprocess.run(_build_cmd(tmp_path / "ds", *extra, config="demo"), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("apcg dataset: error: ")
    assert says.format(port=port) in lines[0]
    assert not (tmp_path / "ds").exists()  # refused before anything was written
    assert time.monotonic() - t0 < 60


@contextlib.contextmanager
def _server(kind: str, tmp_path: Path):
    """A real server on a free port of this machine that is not a Dask scheduler; yields the
    port. silent: accepts and never says a word; http: Python's HTTP server; hangs-up: writes
    a line and closes; dask-worker: a Dask worker (a Dask server, not a scheduler)."""
    import http.server
    import threading
    if kind == "dask-worker":
        port = _closed_port()
        with _dask_cluster(tmp_path, dict(os.environ), "--no-nanny", "--host", "127.0.0.1",
                           "--worker-port", str(port)):
            deadline = time.monotonic() + 120
            while True:  # listening once a connection is accepted
                assert time.monotonic() < deadline, "no worker in 120 s"
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=5).close()
                    break
                except OSError:
                    time.sleep(0.05)
            yield port
        return
    if kind == "http":
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                 http.server.SimpleHTTPRequestHandler)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield server.server_address[1]
        finally:
            server.shutdown()
            server.server_close()
        return
    listener = socket.create_server(("127.0.0.1", 0))
    held = []

    def serve():
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:  # closed: the test is over
                return
            if kind == "hangs-up":
                conn.sendall(b"220 mail.example.org ESMTP ready\r\n")
                conn.close()
            else:
                held.append(conn)  # silent: open, and nothing said

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1]
    finally:
        listener.close()
        for conn in held:
            conn.close()


@pytest.mark.parametrize("kind, timeout_s, says", [
    ("silent", "2", "nothing at --address tcp://127.0.0.1:{port} answered as a Dask scheduler "
                    "within 2 s (--connect-timeout-s)"),
    ("silent", None, "answered as a Dask scheduler within 10 s (--connect-timeout-s)"),
    ("http", "2", "answered as a Dask scheduler within 2 s"),
    ("hangs-up", "2", "--address tcp://127.0.0.1:{port} is not a Dask scheduler: what answers "
                      "there does not speak Dask's protocol"),
    ("dask-worker", "2", "--address tcp://127.0.0.1:{port} is not a Dask scheduler (it answers "
                         "as Worker)"),
], ids=["silent", "silent-default-timeout", "http", "hangs-up", "dask-worker"])
def test_an_address_where_no_scheduler_answers_fails_in_seconds(tmp_path, kind, timeout_s,
                                                                 says):
    with _server(kind, tmp_path) as port:
        extra = ["--engine", "dask", "--address", f"tcp://127.0.0.1:{port}"]
        if timeout_s:
            extra += ["--connect-timeout-s", timeout_s]
        t0 = time.monotonic()
        r = subprocess.run(_build_cmd(tmp_path / "ds", *extra, config="demo"),
                           capture_output=True, text=True, timeout=120)
        took = time.monotonic() - t0
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("apcg dataset: error: "), r.stderr
    assert says.format(port=port) in lines[0]
    assert not (tmp_path / "ds").exists()  # refused before anything was written
    # the timeout bounds the wait (start-up aside); without it this waited for ever
    assert took < 60, took


def test_a_tls_address_without_dasks_tls_settings_is_named(tmp_path):
    with _server("silent", tmp_path) as port:
        r = subprocess.run(_build_cmd(tmp_path / "ds", "--engine", "dask", "--address",
                                      f"tls://127.0.0.1:{port}", config="demo"),
                           capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert (f"--address tls://127.0.0.1:{port} is a TLS scheduler, and Dask's TLS settings are "
            "not set: give distributed.comm.tls.ca-file") in r.stderr
    assert not (tmp_path / "ds").exists()


def _build_without_dask(out: Path, *extra: str) -> subprocess.CompletedProcess:
    """`apcg dataset build` in a process where Dask cannot be imported (each import of it
    fails, as when it is not installed), not a fake engine."""
    argv = ["dataset", "build", "--config", "demo", "-o", str(out), "--no-progress", *extra]
    code = ("import sys; sys.modules.update(dask=None, distributed=None); "
            f"from apcg_core.cli import main; rc = main({argv!r}); "
            "assert not [m for m in sys.modules if m.startswith(('dask.', 'distributed.'))]; "
            "sys.exit(rc)")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)


def test_missing_dask_names_the_pip_command(tmp_path):
    r = _build_without_dask(tmp_path / "ds", "--engine", "dask")
    assert r.returncode == 2, r.stderr
    assert "pip install 'apcg[engine]'" in r.stderr and "Traceback" not in r.stderr


def test_local_builds_need_no_dask(tmp_path):
    r = _build_without_dask(tmp_path / "ds", "--shard", "0/6", "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["built_shards"] == 3


def test_a_local_dask_cluster_beside_another_says_nothing_of_its_dashboard(tmp_path,
                                                                          demo_reference):
    """Another cluster on the machine (a second --shard part) holds Dask's dashboard port:
    the build is quiet about it (dashboard_address None did not turn the dashboard off)."""
    import socket
    with socket.socket() as taken:
        try:
            taken.bind(("", 8787))
        except OSError:
            pass  # already held by something else: the case itself
        taken.listen()
        r = subprocess.run(_build_cmd(tmp_path / "ds", "--engine", "dask", "--workers", "2",
                                      config="demo"), capture_output=True, text=True,
                           timeout=600)
    assert r.returncode == 0, r.stderr
    assert "8787" not in r.stderr and "Warning" not in r.stderr, r.stderr
    _assert_same(tmp_path / "ds", demo_reference)


def test_a_killed_builds_workers_end_with_it(tmp_path, hold):
    """SIGKILL of a build (the OOM killer, kill -9) leaves no worker behind: each ends with
    its parent (PR_SET_PDEATHSIG) instead of finishing its shard into a closed pipe and
    printing tracebacks. Here a worker holds mid-shard, so without that it would wait."""
    point = "build.shard-computing"
    cmd = _build_cmd(tmp_path / "ds", "--workers", "2")
    build = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=hold.env(point))
    try:
        worker = hold.wait(point, build)
        assert worker != build.pid  # a pool worker holds, not the build
        build.kill()
        build.wait()
        deadline = time.monotonic() + 30
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(worker), "a worker outlived its killed build"
    finally:
        hold.release(point)
        if build.poll() is None:
            build.kill()
            build.wait()
        with contextlib.suppress(ProcessLookupError, UnboundLocalError):
            os.kill(worker, signal.SIGKILL)
    assert not list((tmp_path / "ds").glob("manifest.json"))
