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


# Loaded into each worker of the test's cluster (`dask worker --preload`): the first shard
# task still running DELAY_S after it started gets its worker process SIGKILLed, once for the
# whole cluster (the marker file, created with O_EXCL, says which task and worker).
KILLER = '''
import os, signal, threading
from distributed import WorkerPlugin

MARKER = os.environ["APCG_TEST_KILL_MARKER"]
DELAY_S = 0.02


class KillMidShard(WorkerPlugin):
    def setup(self, worker):
        self.worker, self.timer = worker, None

    def transition(self, key, start, finish, **kwargs):
        if not str(key).startswith("apcg-shard-"):
            return
        if finish == "executing" and not os.path.exists(MARKER):
            self.timer = threading.Timer(DELAY_S, self.kill, args=(key,))
            self.timer.start()
        elif start == "executing" and self.timer is not None:
            self.timer.cancel()  # finished first: try the next one

    def kill(self, key):
        state = self.worker.state.tasks.get(key)
        if state is None or state.state != "executing":
            return
        try:
            fd = os.open(MARKER, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
        except FileExistsError:
            return
        os.write(fd, f"{key} {os.getpid()}".encode())
        os.close(fd)
        os.kill(os.getpid(), signal.SIGKILL)


async def dask_setup(worker):
    await worker.plugin_add(KillMidShard(), name="kill-mid-shard")
'''


def _dask_cli(*args: str) -> list[str]:
    return [str(Path(sys.executable).with_name("dask")), *args]


@pytest.fixture
def cluster_with_killer(tmp_path, request):
    """A scheduler and two single-threaded workers (nannies restart a killed one), started as
    the docs' cluster recipe does; yields (address, marker). The scheduler reruns a task whose
    worker died ``request.param`` times (Dask's default, 3, when not parametrized)."""
    killer = tmp_path / "kill_mid_shard.py"
    killer.write_text(KILLER)
    marker = tmp_path / "killed"
    env = {**os.environ, "APCG_TEST_KILL_MARKER": str(marker)}
    if hasattr(request, "param"):
        env["DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES"] = str(request.param)
    scheduler_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "cluster.log", "w")  # noqa: SIM115 - closed below
    # Each in its own process group, so that the teardown stops a nanny's workers too.
    procs = [subprocess.Popen(_dask_cli("scheduler", "--host", "127.0.0.1", "--port", "0",
                                        "--no-dashboard", "--scheduler-file",
                                        str(scheduler_file)), stdout=log, stderr=log,
                              env=env, start_new_session=True)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        address = json.loads(scheduler_file.read_text())["address"]
        elsewhere = tmp_path / "workers-cwd"  # not the build's working directory
        elsewhere.mkdir()
        procs.append(subprocess.Popen(
            _dask_cli("worker", address, "--nworkers", "2", "--nthreads", "1",
                      "--no-dashboard", "--local-directory", str(tmp_path / "scratch"),
                      "--preload", str(killer)),
            stdout=log, stderr=log, env=env, cwd=elsewhere, start_new_session=True))
        yield address, marker
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


def test_worker_killed_mid_shard_is_redone_byte_identical(cpu_reference, cluster_with_killer,
                                                          tmp_path):
    address, marker = cluster_with_killer
    # -o relative to the build's own working directory, which the workers do not share
    r = subprocess.run(_build_cmd(Path("ds"), "--engine", "dask", "--address", address),
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    # the kill happened, to a worker running a shard task, and that process is gone
    key, pid = marker.read_text().split()
    assert key.startswith("apcg-shard-") and not _alive(int(pid))
    _assert_same(tmp_path / "ds", cpu_reference)


@pytest.mark.parametrize("cluster_with_killer", [0], indirect=True)
def test_without_retries_the_killed_shard_fails_the_build_in_one_line(cluster_with_killer,
                                                                      tmp_path):
    # The other side of the test above: the rerun is what saved that build.
    address, marker = cluster_with_killer
    r = subprocess.run(_build_cmd(tmp_path / "ds", "--engine", "dask", "--address", address),
                       capture_output=True, text=True, timeout=300)
    assert marker.exists()
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("apcg dataset: error: every worker "
                                                        "that ran shard task apcg-shard-")
    assert not (tmp_path / "ds" / "manifest.json").exists()


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
    (["--address", "tcp://127.0.0.1:8786"], "--address needs a cluster engine: --engine dask"),
    (["--engine", "dask", "--tasks-per-process", "2"], "applies to the local engine only"),
    (["--engine", "dask", "--workers", "2", "--address", "tcp://127.0.0.1:{port}"],
     "with --address the cluster's own workers build the shards"),
], ids=["unknown", "unreachable", "malformed", "scheme", "no-engine", "tasks-per-process",
        "workers-and-address"])
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
