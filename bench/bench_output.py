"""How every bench writes: its result as indented JSON on stdout and in the ``--json`` file, and
any other file (a table, a config) through :func:`write_text`, so that a file appears under its
final name only when complete (``apcg_core.io.atomic``, as every command's files do).

Files a bench is asked to make beside its JSON (``--markdown``, a report's NAME.json / NAME.md)
follow the commands' rule (``apcg_core.outputs``): :func:`refuse` before any work, so an
existing file is kept unless ``--force`` and an input of the run is never replaced. The
``--json`` result is replaced in place, as the benches' documented commands refresh
``bench/results/`` (unchanged; now atomic).

The bench scripts run as ``python bench/NAME.py``, so this folder is on their path; they import
this inside ``main`` (``blender -b -P`` runs some of them without this folder on the path)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.io.atomic import atomic_path  # noqa: E402


def refuse(outputs, force: bool, inputs=()) -> None:
    """Stop (exit 2, one line) before any work when an output is one of ``inputs`` (never
    replaced), or exists and ``force`` is not set (kept)."""
    for out in (Path(o) for o in outputs if o):
        for given in (Path(i) for i in inputs if i):
            if out.resolve() == given.resolve() or (out.exists() and given.exists()
                                                    and out.samefile(given)):
                _stop(f"{out}: is also an input of this run; it is never replaced")
        if out.exists() and not force:
            _stop(f"{out} exists; --force replaces it")


def _stop(message: str) -> None:
    print(f"{Path(sys.argv[0]).name}: {message}", file=sys.stderr)
    raise SystemExit(2)


def write_text(path, text: str) -> None:
    """``text`` into ``path``, which appears only complete (a temporary beside it, renamed)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def emit(result: dict, json_path: str | None = None, show: bool = True) -> None:
    """Print ``result`` (unless ``show`` is False) and write it to ``json_path`` when given."""
    text = json.dumps(result, indent=1)
    if show:
        print(text)
    if json_path:
        write_text(json_path, text + "\n")
