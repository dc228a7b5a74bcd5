"""The one reader of every TOML file the project reads (sensor, lidar, scene and dataset files).

TOML's integers are 64-bit: "if an integer cannot be represented losslessly, an error must be
thrown" (toml.io, v1.0.0, Integer). Python's tomllib reads any number of digits, and such an
integer then fails deep inside (``float(10**400)`` raises OverflowError), so every file is
checked here once, naming the key, before any field reader sees it.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from ..errors import InputError

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


def read_toml(path, label: str | None = None) -> dict:
    """The parsed document of the TOML file ``path``; an InputError naming ``label`` (default:
    the path) when it is missing, not a file, unreadable, not TOML (a UTF-8 byte-order mark is
    allowed, as spreadsheets and Windows editors write one) or holds an integer outside TOML's
    64-bit range."""
    path = Path(path)
    label = label or str(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise InputError(f"{label} does not exist") from None
    except IsADirectoryError:
        raise InputError(f"{label} is a directory, not a TOML file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{label}: not a readable TOML file ({exc})") from None
    except OSError as exc:
        raise InputError(f"{label}: cannot be read ({exc.strerror})") from None
    _check_integers(doc, label, "")
    return doc


def _check_integers(value, label: str, key: str) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _check_integers(v, label, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _check_integers(v, label, f"{key}[{i}]")
    elif isinstance(value, int) and not isinstance(value, bool) \
            and not INT64_MIN <= value <= INT64_MAX:
        digits = str(abs(value))
        shown = f"{'-' if value < 0 else ''}{digits[:12]}... ({len(digits)} digits)"
        raise InputError(f"{label}: {key} = {shown} is outside TOML's 64-bit integers "
                         f"[{INT64_MIN}, {INT64_MAX}]")
