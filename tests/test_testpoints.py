"""The test points of apcg_core/testpoints.py: each named one is passed by the code, the code
passes no unnamed one, and a point holds only the process that was asked to hold."""

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from apcg_core.testpoints import POINTS, wait_point

ROOT = Path(__file__).resolve().parents[1]


def test_every_point_is_passed_and_every_passed_point_is_named():
    called = set()
    for package in ("apcg_core", "dataset_builder", "training", "blender_addon"):
        for path in (ROOT / package).rglob("*.py"):
            called |= set(re.findall(r'wait_point\("([^"]+)"\)', path.read_text()))
    assert called == set(POINTS)


def test_a_point_holds_until_go_and_only_when_asked(tmp_path, monkeypatch):
    wait_point("build.shard-written")  # not asked: passes at once
    code = ("import sys; from apcg_core.testpoints import wait_point; "
            "wait_point('generate.block-written'); wait_point('build.shard-written'); "
            "print('passed')")
    env = {"APCG_TEST_WAIT_AT": "build.shard-written", "APCG_TEST_WAIT_DIR": str(tmp_path)}
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, **env})
    try:
        while not (tmp_path / "build.shard-written.reached").exists():
            assert proc.poll() is None
            time.sleep(0.005)
        assert int((tmp_path / "build.shard-written.reached").read_text()) == proc.pid
        assert proc.poll() is None  # held
        (tmp_path / "build.shard-written.go").touch()
        assert proc.communicate(timeout=60)[0].strip() == "passed"
    finally:
        if proc.poll() is None:
            proc.kill()
    monkeypatch.setenv("APCG_TEST_WAIT_AT", "x")
    monkeypatch.setenv("APCG_TEST_WAIT_DIR", str(tmp_path))
    with pytest.raises(ValueError, match="unknown test point 'nowhere'"):
        wait_point("nowhere")
    monkeypatch.setenv("APCG_TEST_WAIT_AT", "build.shard-written")
    monkeypatch.setenv("APCG_TEST_WAIT_S", "0.05")
    (tmp_path / "build.shard-written.go").unlink()
    with pytest.raises(RuntimeError, match="no .*build.shard-written.go within 0.05 s"):
        wait_point("build.shard-written")
