"""The command line's ``--lidar PRESET|FILE``: one definition for every command that takes a
lidar (simulate, generate, dataset build, evaluate, compare, teach, figure; a test walks the
parsers). The value is a preset name (``apcg_core/lidar_presets``; ``paper`` the default) or a
lidar file: the ``[lidar]`` table of the dataset configs, plus an optional ``[sensor]`` table
that ``--sensor`` reads when it is not given (``apcg_core.sensor.options``).
"""

from __future__ import annotations

import sys

from .lidar import (
    DEFAULT_LIDAR_PRESET,
    LIDAR_PRESET_DIR,
    LidarParams,
    lidar_from_table,
    lidar_preset_names,
    read_lidar_file,
)


def add_lidar_argument(p, default_help: str = "the paper's") -> None:
    """``--lidar``; ``default_help`` says what the command uses without it."""
    p.add_argument("--lidar", metavar="PRESET|FILE.toml",
                   help="the SPC-Lidar: a preset (" + ", ".join(lidar_preset_names())
                        + ") or a TOML file with a [lidar] table (r_alpha_deg, r_beta_deg, "
                        "r_r_m, width, height) and optionally a [sensor] table; default "
                        + default_help)


def _load_checked(ref) -> LidarParams:
    """The lidar of ``ref``, its file's ``[sensor]`` table (when it has one) checked too: a
    mistake there is named now, whether or not this command reads the table, instead of
    passing unseen."""
    from .sensor import sensor_from_table
    from .sensor.params import check_own_name
    path, doc = read_lidar_file(ref)
    lidar = lidar_from_table(doc["lidar"], source=str(path))
    if "sensor" in doc:
        sensor = sensor_from_table(doc["sensor"], source=str(path), name=path.stem)
        if sensor is not None and path.parent != LIDAR_PRESET_DIR:
            check_own_name(sensor, str(path))
    return lidar


def lidar_of(args) -> LidarParams | None:
    """The lidar ``--lidar`` names, None when it was not given (the command's default)."""
    ref = getattr(args, "lidar", None)
    return None if ref is None else _load_checked(ref)


def lidar_or_default(args) -> LidarParams:
    """``--lidar``'s lidar, else the default preset (``paper``)."""
    ref = getattr(args, "lidar", None)
    return _load_checked(DEFAULT_LIDAR_PRESET if ref is None else ref)


def model_at_lidar(model, args, command: str):
    """Point ``model`` at ``--lidar``'s lidar (when given): refused in one line by a family that
    draws at its training lidar only; a lidar outside those the model was measured on (its
    model.json) is said in one warning line. Returns the model."""
    lidar = lidar_of(args)
    if lidar is None:
        return model
    model.use_lidar(lidar)
    warning = model.lidar_warning(lidar)
    if warning:
        print(f"apcg {command}: warning: {warning}", file=sys.stderr, flush=True)
    return model
