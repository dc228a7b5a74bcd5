"""Where commands write: output options declared with their kind, checked before a command runs.

A file output that already exists is replaced only with ``--force`` (added here to every command
that writes files), so nothing a user made is overwritten by a second run or a typo. A
directory output given as an existing file, or a file output given as a directory, is refused
by name. Directory outputs keep their command's own rules (a build or training run resumes in
its directory; ``export`` and ``teach`` refuse a non-empty one without ``--force``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import option_name

FILE, DIRECTORY = "file", "directory"
# What matplotlib writes for the pictures (figures, contact sheets, previews).
PICTURE_SUFFIXES = (".png", ".pdf", ".svg")


def add_output(parser: argparse.ArgumentParser, *flags: str, kind: str = FILE,
               suffixes: tuple[str, ...] = (), **kwargs):
    """``parser.add_argument(*flags, **kwargs)`` for a path the command writes (``kind``:
    FILE or DIRECTORY; a file's accepted ``suffixes``, checked before the command runs)."""
    action = parser.add_argument(*flags, **kwargs)
    key = "_file_outputs" if kind == FILE else "_directory_outputs"
    parser.set_defaults(**{key: (*(parser.get_default(key) or ()), action.dest)})
    if suffixes:
        parser.set_defaults(_output_suffixes={**(parser.get_default("_output_suffixes") or {}),
                                              action.dest: tuple(suffixes)})
    if kind == FILE and not any(a.dest == "force" for a in parser._actions):
        parser.add_argument("--force", action="store_true",
                            help="replace output files that already exist")
    return action


def output_problems(args: argparse.Namespace) -> list[str]:
    """Messages for output paths the command must not write to as they are."""
    out = []
    for dest in getattr(args, "_file_outputs", ()):
        value = getattr(args, dest, None)
        if value is None or value == "-":
            continue
        path = Path(value)
        accepted = getattr(args, "_output_suffixes", {}).get(dest)
        if accepted and path.suffix.lower() not in accepted:
            out.append(f"{option_name(dest)} {value}: unsupported format "
                       f"{path.suffix.lower() or '(no suffix)'!r}; accepted: {', '.join(accepted)}")
        elif path.is_dir():
            out.append(f"{option_name(dest)} {value} is a directory; give a file name")
        elif path.exists() and not getattr(args, "force", False):
            out.append(f"{option_name(dest)} {value} already exists; choose another name, or "
                       "--force to replace it")
        elif (blocker := _file_on_the_way(path)) is not None:
            out.append(f"{option_name(dest)} {value}: {blocker} is a file, not a directory")
    for dest in getattr(args, "_directory_outputs", ()):
        value = getattr(args, dest, None)
        if value is not None and (Path(value).is_file() or _file_on_the_way(Path(value))):
            out.append(f"{option_name(dest)} {value} is a file; give a directory")
    return out


def _file_on_the_way(path: Path) -> Path | None:
    """The first existing parent of ``path`` that is a file (so nothing can be made below)."""
    for parent in path.absolute().parents:
        if parent.exists():
            return parent if not parent.is_dir() else None
    return None
