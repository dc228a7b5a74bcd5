"""How every bench writes: its result as indented JSON on stdout and in the ``--json`` file, and
any other file (a table, a config) through :func:`write_text`, a picture through
:func:`save_figure`, so that a file appears under its final name only when complete
(``apcg_core.io.atomic``, as every command's files do). A log that grows row by row in a
bench's own work directory is added to through :func:`append_line`. No bench writes a file
itself (tests/test_bench_outputs.py reads every bench/*.py and names any that does).

Files a bench is asked to make beside its JSON (``--markdown``, ``--plot``, a report's
NAME.json / NAME.md) follow the commands' rule (``apcg_core.outputs``): :func:`refuse` before
any work, so an existing file is kept unless ``--force`` and an input of the run is never
replaced. The ``--json`` result is replaced in place, as the benches' documented commands
refresh ``bench/results/`` (unchanged; now atomic). Files a bench writes into a fresh
temporary or work directory of its own run (a config, a child's result) need no refusal.

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


def save_figure(fig, path, **kw) -> None:
    """A matplotlib figure into ``path`` (``fig.savefig(path, **kw)``), which appears only
    complete: saved to a temporary beside it with the same suffix (NAME.part.png), so that
    matplotlib takes the format from the suffix as it would from ``path``, then renamed."""
    path = Path(path)
    if not path.suffix and "format" not in kw:  # savefig's own default, not ".part"
        import matplotlib
        kw["format"] = matplotlib.rcParams["savefig.format"]
    with atomic_path(path, suffix=".part" + path.suffix) as tmp:
        fig.savefig(tmp, **kw)


def append_line(path, line: str) -> None:
    """``line`` and a newline added to the end of ``path`` in one write (append mode: the rows
    of several processes never interleave). Only for a log in a bench's own work directory
    that grows row by row and is read back by the bench itself: it has no complete state to
    rename into place, so it is not atomic."""
    with open(path, "a") as f:
        f.write(line + "\n")


def emit(result: dict, json_path: str | None = None, show: bool = True) -> None:
    """Print ``result`` (unless ``show`` is False) and write it to ``json_path`` when given."""
    text = json.dumps(result, indent=1)
    if show:
        print(text)
    if json_path:
        write_text(json_path, text + "\n")
