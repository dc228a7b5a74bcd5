"""Model families: one registry that every command, the trainer and the add-on talk to.

A family is an object with a ``name`` and the parts it provides:

* ``load(directory, runtime)`` -> a model (:class:`apcg_core.families.base.ModelTypes`) whose
  ``generate(conditions, count, seed)`` turns :class:`~apcg_core.typetable.Conditions` into
  clouds. Every family has it.
* training parts (``networks``, ``train_step``, ``export``, ``untrained`` ...), provided by the
  package that trains the family (``training/families/<family>.py``).

Families register under the ``apcg.model_families`` entry points (value: the family object).
The core names its own loaders (:data:`BUILTIN`, ``module:attribute`` like an entry point,
imported when first asked for), so a model directory opens in a Python that has no entry-point
metadata (Blender's legacy add-on folder) and the core keeps importing numpy alone. Nothing
outside a family's own modules branches on its name: it asks the registry.
"""

from __future__ import annotations

import json
import os
from importlib import import_module
from pathlib import Path

from ..errors import InputError

ENTRY_POINTS = "apcg.model_families"
# the loaders the core ships (model.json "family" -> "module:attribute")
BUILTIN = {"cgan": "apcg_core.families.cgan:LOADER",
           "apcg-plus": "apcg_core.families.apcg_plus:LOADER"}
_BUILTIN: dict = {}
_FROM_ENTRY_POINTS: dict | None = None


def register(family):
    """Register a family object in this process (the entry points take precedence)."""
    _BUILTIN[family.name] = family
    return family


def _builtin(name: str):
    """The family registered in this process, or the core's own loader called ``name``."""
    if name not in _BUILTIN and name in BUILTIN:
        module, attr = BUILTIN[name].split(":")
        _BUILTIN[name] = getattr(import_module(module), attr)
    return _BUILTIN.get(name)


def _entry_point_families() -> dict:
    global _FROM_ENTRY_POINTS
    if _FROM_ENTRY_POINTS is None:
        try:
            from importlib.metadata import entry_points
            _FROM_ENTRY_POINTS = {ep.name: ep for ep in entry_points(group=ENTRY_POINTS)}
        except Exception:  # noqa: BLE001 - no metadata (e.g. a bare sys.path folder in Blender)
            _FROM_ENTRY_POINTS = {}
    return _FROM_ENTRY_POINTS


def family_names() -> list[str]:
    return sorted(set(_BUILTIN) | set(BUILTIN) | set(_entry_point_families()))


def get_family(name: str, need: str = "load"):
    """The family called ``name``, with the part ``need`` (a method name); refuses a family
    that is unknown or lacks the part, naming what is installed."""
    eps = _entry_point_families()
    fam = None
    if name in eps:
        try:
            fam = eps[name].load()
        except ImportError as exc:  # its package is installed without its extra (torch)
            if _builtin(name) is None:
                raise InputError(f"model family {name!r} needs a package that is not "
                                 f"installed ({exc}); pip install 'apcg[train]'") from exc
    if fam is None:
        fam = _builtin(name)
    if fam is None:
        raise InputError(f"unknown model family {name!r}; installed: "
                         f"{', '.join(family_names()) or 'none'}")
    if not callable(getattr(fam, need, None)):
        raise InputError(f"model family {name!r} as installed cannot {need.replace('_', ' ')} "
                         "(training a family needs pip install 'apcg[train]')")
    return fam


# model.json's "format" and the newest "format_version" this package reads (training/export.py
# writes both; a model.json without them is a first-version model, from before they were
# written).
MODEL_FORMAT = "apcg-model"
MODEL_FORMAT_VERSION = 1


def read_model_meta(directory) -> dict:
    """A model directory's ``model.json``, checked to be one."""
    if not isinstance(directory, (str, os.PathLike)):
        raise InputError(f"a model is given by its directory (a path), got {directory!r}")
    d = Path(directory)
    meta = d / "model.json"
    if not d.is_dir():
        what = "is a file, not a directory" if d.exists() else "does not exist"
        raise InputError(f"model directory {d} {what} (a model is a directory made by "
                         "`apcg export`)")
    if not meta.is_file():
        raise InputError(f"{d} is not an APCG model directory (no model.json; `apcg export "
                         "--run RUN -o DIR` makes one from a training run)")
    try:
        out = json.loads(meta.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{meta} is not a readable model.json: {exc}") from exc
    if not isinstance(out, dict) or "types" not in out or "condition_space" not in out:
        raise InputError(f"{meta} is not an APCG model.json (needs 'types' and "
                         "'condition_space')")
    fmt, version = out.get("format", MODEL_FORMAT), out.get("format_version", 1)
    if fmt != MODEL_FORMAT:
        raise InputError(f"{meta}: format {fmt!r} is not an APCG model's ({MODEL_FORMAT!r})")
    if isinstance(version, bool) or not isinstance(version, int) \
            or not 1 <= version <= MODEL_FORMAT_VERSION:
        raise InputError(f"{meta}: format_version {version!r} is not one this apcg reads "
                         f"(1 to {MODEL_FORMAT_VERSION}); a newer apcg made it: upgrade, or "
                         "export the model again with this one")
    return out


def family_of(directory) -> str:
    """The family that made the model in ``directory`` (model.json ``family``; the cGAN's
    model.json from before families were recorded has none)."""
    return str(read_model_meta(directory).get("family", "cgan"))


__all__ = ["BUILTIN", "ENTRY_POINTS", "family_names", "family_of", "get_family", "read_model_meta",
           "register"]
