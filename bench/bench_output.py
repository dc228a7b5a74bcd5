"""How every bench reports: its result as indented JSON on stdout, and in the ``--json`` file.

The bench scripts run as ``python bench/NAME.py``, so this folder is on their path; they import
this inside ``main`` (``blender -b -P`` runs some of them without this folder on the path)."""

from __future__ import annotations

import json
from pathlib import Path


def emit(result: dict, json_path: str | None = None, show: bool = True) -> None:
    """Print ``result`` (unless ``show`` is False) and write it to ``json_path`` when given."""
    text = json.dumps(result, indent=1)
    if show:
        print(text)
    if json_path:
        Path(json_path).write_text(text + "\n")
