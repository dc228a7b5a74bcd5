"""One live process per job: a lock file created with O_EXCL, holding "pid host".

A second build of the same shard, or a second training process on the same run, is refused
with a message naming the process that holds the job. A lock whose process is gone (a kill,
a crash, on this host) is taken over, so a killed job can always be run again.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

from .errors import InputError


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def lock_owner(text: str) -> tuple[int | None, str | None]:
    parts = text.split()
    if len(parts) != 2 or not parts[0].isdigit():
        return None, None
    return int(parts[0]), parts[1]


def is_lock_file(name: str, lock_name: str) -> bool:
    """Whether the file ``name`` is the lock ``lock_name`` or one it makes on the way (a
    taker's draft ``LOCK.PID.new``, a dead owner's lock moved aside ``LOCK.stale.PID``): what
    a directory check counts as the job's own, not a user's file."""
    if name == lock_name:
        return True
    rest = name[len(lock_name) + 1:] if name.startswith(lock_name + ".") else ""
    pid_new = rest.endswith(".new") and rest[:-len(".new")].isdigit()
    return pid_new or (rest.startswith("stale.") and rest[len("stale."):].isdigit())


class ProcessLock:
    """``path``, held by this process while the job runs; ``job`` names the job in messages
    ("a build of --shard 0/2 into data/x")."""

    def __init__(self, path, job: str) -> None:
        self.path = Path(path)
        self.job = job
        self.mine = f"{os.getpid()} {socket.gethostname()}\n"
        self.held = False
        self.made_parent = False

    def acquire(self) -> ProcessLock:
        # A job refused later leaves no empty directory made only to hold its lock.
        self.made_parent = not self.path.parent.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._drop_dead_drafts()
        for _ in range(10):
            try:
                self._create()
            except FileExistsError:
                self._take_over_if_stale()
                continue
            self.held = True
            return self
        raise InputError(f"could not take the lock {self.path}; delete it if no {self.job} runs")

    def _draft(self, pid: int) -> Path:
        return self.path.with_name(f"{self.path.name}.{pid}.new")

    def _create(self) -> None:
        """The lock file, whole or not at all: its text is written to a draft first and the
        draft linked to the lock's name (a link, like O_EXCL, fails if the name exists), so a
        process killed while taking the lock never leaves an empty one that reads as a live
        owner's. Where the file system has no hard links, O_EXCL and a write."""
        draft = self._draft(os.getpid())
        try:
            draft.write_text(self.mine)
            try:
                os.link(draft, self.path)
                return
            except FileExistsError:
                raise
            except OSError:  # no hard links here
                pass
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            with os.fdopen(fd, "w") as f:
                f.write(self.mine)
        finally:
            draft.unlink(missing_ok=True)

    def _drop_dead_drafts(self) -> None:
        """Drafts of processes killed between writing and linking them."""
        for draft in self.path.parent.glob(f"{self.path.name}.*.new"):
            pid = draft.name[len(self.path.name) + 1:-len(".new")]
            if pid.isdigit() and not pid_alive(int(pid)):
                draft.unlink(missing_ok=True)

    def _take_over_if_stale(self) -> None:
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return  # its owner just finished: try again
        pid, host = lock_owner(text)
        if pid is None or host != socket.gethostname() or pid_alive(pid):
            who = f"pid {pid} on {host}" if pid is not None else "an unreadable lock"
            raise InputError(
                f"another {self.job} is running ({who}, lock file {self.path}); wait for it to "
                "finish, or stop it, or delete the lock file if that process is gone")
        # Dead owner on this host: move its lock aside atomically (only one taker wins), check
        # that what we moved is still the dead one's, then create ours on the next round.
        aside = self.path.with_name(self.path.name + f".stale.{os.getpid()}")
        try:
            os.rename(self.path, aside)
        except FileNotFoundError:
            return
        if aside.read_text() != text:  # a live taker replaced it meanwhile: give it back
            try:
                os.link(aside, self.path)
            except FileExistsError:
                pass
        aside.unlink()

    def release(self) -> None:
        if self.held:
            try:
                if self.path.read_text() == self.mine:
                    self.path.unlink()
            except FileNotFoundError:
                pass
            self.held = False
            if self.made_parent:
                try:
                    self.path.parent.rmdir()  # only when nothing else was written there
                except OSError:
                    pass

    def __enter__(self) -> ProcessLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
