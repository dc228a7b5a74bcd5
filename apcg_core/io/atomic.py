"""Every file the project writes appears under its final name only when complete, and only
where the running command may write it (``apcg_core.outputs``: the guard of every output)."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

# The running command's output guards (apcg_core.outputs.Guard; a stack, innermost last): set
# by apcg_core.outputs.guarding, asked by every write here. Empty outside a command.
GUARDS: list = []


def active():
    """The running command's guard, or None."""
    return GUARDS[-1] if GUARDS else None


def claim(path) -> bool:
    """Ask the running command's guard before a file is made for ``path``: an InputError when
    it may not be replaced (a user's file without --force, an input of the command); True when
    the file is to be held until the command ends. Outside a command: False."""
    guard = active()
    return guard.claim(path) if guard is not None else False


def scratch(path) -> Path:
    """``path``, a temporary name the command writes and then renames or removes (``NAME.part``,
    a spill file beside an output), once the running command's guard has seen it: an input
    of the command is refused (InputError), whatever the name; a leftover one of a killed run
    is written over. Every temporary name goes through here (atomic_path, CloudWriter)."""
    guard = active()
    if guard is not None:
        guard.scratch(path)
    return Path(path)


def refuse_directory(path) -> None:
    """A file is never written over a directory (nor is its temporary name made for one), nor
    under a file taken for a directory."""
    from ..errors import InputError
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path} is a directory; give a file name")
    up = path.parent
    while not up.exists() and up != up.parent:
        up = up.parent
    if up.exists() and not up.is_dir():
        raise InputError(f"{up} is a file, so {path} cannot be made under it")


def publish(tmp, path, held: bool | None = None) -> None:
    """``tmp`` (complete) becomes ``path``: renamed now, or, for a command's own result, moved
    beside ``path`` and renamed when the command ends (``apcg_core.outputs.Guard.commit``)."""
    path = Path(path)
    if held is None:
        held = claim(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    guard = active()
    if held and guard is not None:
        waiting = path.with_name(path.name + ".part")
        if Path(tmp) != waiting:
            os.replace(tmp, scratch(waiting))
        guard.hold(waiting, path)
    else:
        os.replace(tmp, path)


@contextmanager
def atomic_path(path, suffix: str = ".part"):
    """A temporary name beside ``path`` to write to: renamed to ``path`` when the block ends
    without error (when the running command ends, for a command's result), removed when it
    fails (a full disk, Ctrl-C), so a file under its final name is always complete and no
    half-written one is left. The guard is asked first, so a refusal costs no work. Missing
    parent directories are made."""
    path = Path(path)
    refuse_directory(path)
    held = claim(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = scratch(path.with_name(path.name + suffix))
    try:
        yield tmp
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        name_the_file(exc, path, tmp)
        raise
    publish(tmp, path, held)


def name_the_file(exc: BaseException, path, tmp=None) -> None:
    """A write that failed on a file object (a full disk) raises an OSError with no file
    name, one on the temporary file names that: give it the final name, so the message says
    which output could not be written."""
    if isinstance(exc, OSError) and (exc.filename is None or (
            tmp is not None and str(exc.filename) == str(tmp))):
        exc.filename = str(path)
