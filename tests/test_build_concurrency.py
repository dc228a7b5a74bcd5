"""`apcg dataset build --shard I/N` run concurrently into one directory (a job array).

Real processes, real embree: the parts built at once must give the single-process dataset byte
for byte, and a second build of the same part must be refused while the first one lives.
"""

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("embreex")

# Small but with many shards, so that processes overlap on the plan files and on shards/.
CONFIG = """
description = "concurrency test: 3 types, 27 shards"
seed = 3
backend = "embree"
shard_size = 6
test_fraction = 0.2
sampling = "grid"
types = ["A320neo", "F-16C Fighting Falcon", "Mavic 3"]

[counts]
elevation = 1
range_m = 3
yaw = 4
pitch = 2
roll = 2
"""


def _build_cmd(cfg: Path, out: Path, spec: str | None) -> list[str]:
    cmd = [sys.executable, "-m", "apcg_core.cli", "dataset", "build", "--config", str(cfg),
           "-o", str(out), "--no-progress"]
    return cmd + (["--shard", spec] if spec else [])


def _files(directory: Path) -> dict[str, bytes]:
    return {str(p.relative_to(directory)): p.read_bytes()
            for p in sorted(directory.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "concurrency.toml"
    path.write_text(CONFIG)
    return path


@pytest.fixture(scope="module")
def reference(config, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("single") / "ds"
    subprocess.run(_build_cmd(config, out, None), check=True, capture_output=True)
    files = _files(out)
    assert "manifest.json" in files and len([f for f in files if f.startswith("shards/")]) == 27
    return files


@pytest.mark.parametrize("n_parts", [2, 4])
def test_concurrent_parts_equal_single_build(config, reference, tmp_path, n_parts):
    out = tmp_path / "ds"
    for _round in range(2):  # the second round starts from a finished dataset: all skipped
        procs = [subprocess.Popen(_build_cmd(config, out, f"{i}/{n_parts}"),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                 for i in range(n_parts)]
        results = [(p.wait(timeout=300), p.stderr.read().decode()) for p in procs]
        for p in procs:
            p.stdout.close()
            p.stderr.close()
        assert all(rc == 0 for rc, _ in results), results
        got = _files(out)
        assert sorted(got) == sorted(reference)  # no temporary or lock file left behind
        bad = [name for name in reference if got[name] != reference[name]]
        assert not bad


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_same_part_refused_while_its_builder_lives(config, tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    # A live process owning the lock of part 0/2, as a running build leaves it.
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = out / ".build-0-of-2.lock"
        lock.write_text(f"{holder.pid} {socket.gethostname()}\n")
        r = subprocess.run(_build_cmd(config, out, "0/2"), capture_output=True, text=True)
        assert r.returncode != 0
        assert "another build of --shard 0/2" in r.stderr and str(holder.pid) in r.stderr
        assert not list((out / "shards").glob("*.npz"))  # refused before building anything
        assert lock.read_text() == f"{holder.pid} {socket.gethostname()}\n"  # left alone
        # another part of the same dataset is not blocked by it
        r = subprocess.run(_build_cmd(config, out, "1/2"), capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
    finally:
        holder.kill()
        holder.wait()


def test_two_live_builds_of_one_part_one_refused(config, tmp_path, hold):
    out = tmp_path / "ds"
    point = "build.shard-written"
    first = subprocess.Popen(_build_cmd(config, out, "0/1"), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=hold.env(point))
    try:
        hold.wait(point, first)  # the first build holds its lock, waiting after a shard
        second = subprocess.run(_build_cmd(config, out, "0/1"), capture_output=True, text=True,
                                timeout=300)
    finally:
        hold.release(point)
        _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert second.returncode != 0
    assert f"pid {first.pid}" in second.stderr
    assert not (out / ".build-0-of-1.lock").exists()


def test_stale_lock_of_dead_process_taken_over(config, reference, tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    lock = out / ".build-0-of-1.lock"
    pid = _dead_pid()
    lock.write_text(f"{pid} {socket.gethostname()}\n")
    # a dead writer's temporary file, as a killed build leaves it
    (out / "shards").mkdir()
    (out / "shards" / f"train-00000.npz.{pid}.part").write_bytes(b"half a shard")
    r = subprocess.run(_build_cmd(config, out, None), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert not lock.exists()
    assert _files(out) == reference


def test_lock_of_other_host_refused(config, tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    lock = out / ".build-0-of-1.lock"
    lock.write_text(f"{os.getpid()} some-other-node.invalid\n")
    r = subprocess.run(_build_cmd(config, out, None), capture_output=True, text=True)
    assert r.returncode != 0 and "some-other-node.invalid" in r.stderr
    assert "delete the lock file" in r.stderr
