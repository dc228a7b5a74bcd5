"""Model families at generation time: the registry, the runtime every family shares, and one
module per family.

Where a model family lives (docs/DESIGN.md, "Layout"):

* ``apcg_core/families/<family>.py``: its runtime (numpy, onnxruntime where it runs): the model
  class that opens a model directory and generates, and the core's loader for it;
* ``apcg_core/nn/<family>.py``: its torch networks;
* ``training/families/<family>.py``: its training (batches, step, export, untrained), the family
  object registered under the ``apcg.model_families`` entry points (pyproject.toml).

Here: :mod:`.registry` (the families by name), :mod:`.base` (what every model shares:
:class:`ModelTypes`, :func:`load_model`), :mod:`.cgan` (the paper's cGAN), :mod:`.apcg_plus`
(APCG+), :mod:`.baselines` (the comparison families point-gan, voxel-gan, diffusion).
"""

from .base import (
    DEFAULT_MODEL_DIR,
    RUNTIMES,
    GenerationResult,
    ModelTypes,
    conditions_from_csv,
    default_model_dir,
    load_model,
)
from .registry import (
    BUILTIN,
    ENTRY_POINTS,
    family_names,
    family_of,
    get_family,
    read_model_meta,
    register,
)

__all__ = ["BUILTIN", "DEFAULT_MODEL_DIR", "ENTRY_POINTS", "RUNTIMES", "GenerationResult",
           "ModelTypes", "conditions_from_csv", "default_model_dir", "family_names",
           "family_of", "get_family", "load_model", "read_model_meta", "register"]
