"""The one-live-process lock (apcg_core/lock.py): a process killed at any moment while it takes
the lock leaves either no lock or a whole one naming it, so the job can always be run again.
Real processes, killed by SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from apcg_core.lock import ProcessLock

TAKER = """
import sys, time
from apcg_core.lock import ProcessLock
ProcessLock(sys.argv[1], "test job").acquire()
print("held", flush=True)
time.sleep(60)
"""


def test_a_lock_taker_killed_at_any_moment_never_blocks_the_next(tmp_path):
    lock = tmp_path / "job" / ".job.lock"
    held_seen = 0
    for i in range(40):
        p = subprocess.Popen([sys.executable, "-c", TAKER, str(lock)], stdout=subprocess.PIPE,
                             text=True)
        if i % 2:  # half the time wait until it holds the lock, half kill it at once
            assert p.stdout.readline().strip() == "held"
            held_seen += 1
        else:
            time.sleep(0.002 * (i % 10))
        p.send_signal(signal.SIGKILL)
        p.wait()
        if lock.exists():
            owner = lock.read_text().split()
            assert len(owner) == 2 and owner[0] == str(p.pid), owner  # whole, the dead one's
        mine = ProcessLock(lock, "test job").acquire()  # taken over, never "unreadable"
        assert lock.read_text().split()[0] == str(os.getpid())
        mine.release()
        assert not lock.exists()
        assert not list(tmp_path.rglob("*.new"))
    assert held_seen == 20


def test_a_dead_processs_draft_is_cleared_and_a_live_ones_kept(tmp_path):
    lock = tmp_path / ".job.lock"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / f".job.lock.{dead.pid}.new").write_text(f"{dead.pid} host\n")
    live = tmp_path / f".job.lock.{os.getppid()}.new"
    live.write_text("x")
    with ProcessLock(lock, "test job"):
        assert lock.read_text().split()[0] == str(os.getpid())
    assert not (tmp_path / f".job.lock.{dead.pid}.new").exists() and live.exists()


def test_a_lock_and_its_drafts_are_a_jobs_own_files_not_a_users(tmp_path):
    import pytest

    from apcg_core.errors import InputError
    from apcg_core.lock import is_lock_file
    from dataset_builder.scene import SEQUENCE_LOCK, check_sequence_directory
    lock = ".job.lock"
    assert all(is_lock_file(n, lock) for n in (lock, f"{lock}.123.new", f"{lock}.stale.9"))
    assert not any(is_lock_file(n, lock) for n in (f"{lock}.x.new", f"{lock}.123", "job.lock",
                                                   f"{lock}.stale.", "notes.txt"))
    # a sequence directory holding a dead writer's draft is still a new one; a user's file not
    (tmp_path / f"{SEQUENCE_LOCK}.4242.new").write_text("4242 host\n")
    assert check_sequence_directory(tmp_path, b"header") is False
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"holds other files \(notes\.txt\)"):
        check_sequence_directory(tmp_path, b"header")
