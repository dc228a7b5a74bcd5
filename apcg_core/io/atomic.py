"""Every file the project writes appears under its final name only when complete."""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path, suffix: str = ".part"):
    """A temporary name beside ``path`` to write to: renamed to ``path`` when the block ends
    without error, removed when it fails (a full disk, Ctrl-C), so a file under its final name
    is always complete and no half-written one is left. Missing parent directories are made."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + suffix)
    try:
        yield tmp
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        name_the_file(exc, path)
        raise
    os.replace(tmp, path)


def name_the_file(exc: BaseException, path) -> None:
    """A write that failed on a file object (a full disk) raises an OSError with no file
    name: give it the final name, so the message says which output could not be written."""
    if isinstance(exc, OSError) and exc.filename is None:
        exc.filename = str(path)
