"""Results a user would not expect, said as warnings (stderr, exit 0): the job is still done.

The simulator accepts any range and pose (it is exact anywhere), but a drone at 17 km or a
cloud of one point is rarely what was meant. Each check returns its message or None, so every
command words the same case the same way.
"""

from __future__ import annotations

from .condition import ConditionSpace, in_range
from .errors import InputError, distinct
from .lidar import MAX_WINDOW_SIDE

# Fewer points than this is a cloud few detectors or metrics can use.
SPARSE_POINTS = 10


def range_band_warning(t, range_m: float) -> str | None:
    """``range_m`` outside the Table 1 band of the type ``t`` (far: 3-18 km, near: 100-600 m,
    SPEC section 3): the trained models and the committed datasets never saw it."""
    space = ConditionSpace()
    lo, hi = space.drone_range_m if t.range_band == "near" else space.aircraft_range_m
    if in_range(range_m, lo, hi):  # as a model's condition space takes it
        return None
    return (f"{t.name} is a {t.range_band}-band type ({t.kind}): its Table 1 range is "
            f"{lo:g}-{hi:g} m, and {distinct(range_m, lo if range_m < lo else hi)} m lies "
            "outside it")


def band_share_warning(n_outside: int, n_total: int) -> str | None:
    """Samples of a dataset whose range lies outside their type's Table 1 band."""
    if not n_outside:
        return None
    space = ConditionSpace()
    return (f"{n_outside:,} of {n_total:,} samples lie outside their type's Table 1 range band "
            f"(far types {space.aircraft_range_m[0]:g}-{space.aircraft_range_m[1]:g} m, near "
            f"types {space.drone_range_m[0]:g}-{space.drone_range_m[1]:g} m): the shipped "
            "models never saw such ranges, and far-off small targets give empty clouds")


# Why a photon cloud holds little of its target when the geometry is not the cause.
SENSOR_CAUSE = ("the single-photon lidar detected little of it (range, reflectivity, "
                "visibility, pulse energy, efficiencies, threshold: the sensor's values)")


def empty_clouds_warning(n_empty: int, n_total: int, sensor: bool = False) -> str | None:
    """Empty clouds among many generated at once (``sensor``: drawn through a photon stage,
    which may return nothing of a target the lidar's cells do see)."""
    if not n_empty:
        return None
    cause = (f"the target too small or too far for the lidar, or {SENSOR_CAUSE}" if sensor
             else "no cell of the lidar's window sees the target: too small or too far for "
                  "the lidar")
    return (f"{n_empty:,} of {n_total:,} clouds are empty ({cause}); they are counted in "
            "`sample` but hold no points")


def sparse_cloud_warning(n_points: int, what: str,
                         covered_cells: int | None = None, clipped: bool = False) -> str | None:
    """An empty or near-empty cloud. ``covered_cells`` (a photon cloud: the cells the target
    covers, ``n_points`` its signal points): when the target covers enough cells, the sensor
    is the cause, not the geometry. ``clipped``: the target reaches past the window, so an
    empty cloud's parts may all lie outside it (not too small to resolve)."""
    if covered_cells is not None and covered_cells >= SPARSE_POINTS \
            and n_points < SPARSE_POINTS:
        return (f"{what} holds {n_points} signal point{'s' * (n_points != 1)} though the "
                f"target covers {covered_cells} lidar cells: {SENSOR_CAUSE}")
    if n_points == 0:
        why = ("its parts lie outside the lidar's window, which it reaches past" if clipped
               else "too small or too far for the lidar's resolution")
        return f"{what} is empty: no cell of the lidar's window sees the target ({why})"
    if n_points < SPARSE_POINTS:
        return (f"{what} has only {n_points} point{'s' * (n_points > 1)}: the target covers "
                f"fewer than {SPARSE_POINTS} lidar cells at this range")
    return None


def _lidar_words(lidar: dict) -> str:
    known = ("r_alpha_deg", "r_beta_deg", "r_r_m", "width", "height")
    def g(v):
        return f"{v:.6g}" if isinstance(v, float) else str(v)
    words = (f"{g(lidar.get('r_alpha_deg'))} x {g(lidar.get('r_beta_deg'))} deg cells, "
             f"{g(lidar.get('r_r_m'))} m bins, {lidar.get('width')} x {lidar.get('height')} "
             "cells")
    rest = [f"{k} {lidar[k]}" for k in sorted(lidar) if k not in known]
    return words + "".join(f", {r}" for r in rest)


def _same_value(a, b) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) \
            and not isinstance(a, bool) and not isinstance(b, bool):
        return abs(a - b) <= 1e-9 * max(abs(a), abs(b), 1e-300)
    return a == b


def lidar_mismatch_warning(data_lidar: dict, data_name, model_lidar: dict,
                           model_name) -> str | None:
    """A dataset made by another lidar than the one a model was trained for (its model.json):
    the model's clouds and the dataset's standard clouds are not comparable cell for cell.
    ``model_lidar`` is the lidar the model generates at (its own, or ``--lidar``'s)."""
    data_lidar, model_lidar = dict(data_lidar or {}), dict(model_lidar or {})
    differ = [k for k in sorted(set(data_lidar) | set(model_lidar))
              if not _same_value(data_lidar.get(k), model_lidar.get(k))]
    if not differ:
        return None
    return (f"the dataset {data_name} was made by another lidar ({_lidar_words(data_lidar)}) "
            f"than the model {model_name} generates at ({_lidar_words(model_lidar)}; "
            "--lidar sets it); "
            f"they differ in {', '.join(differ)}, so its scores compare clouds of two lidars")


# Conditions a command checks against the window (the first ones, in order): enough for any
# request a person types, and bounded for 10^6-cloud requests (issue 33).
WINDOW_CHECK_ROWS = 1024
WINDOW_CHECK_POINTS = 1 << 20  # (row, vertex) pairs transformed at once: ~25 MB


def _angle_extremes(obs):
    """(min, max) azimuth and (min, max) elevation of each row's points ``obs`` (N, V, 3), in
    the observation frame: found on tan alpha = x / z and tan beta = y / hypot(x, z), which the
    angles follow where z > 0 (a target in front), the arctangents taken of those four points
    alone; arctangents of every point otherwise."""
    import numpy as np

    x, y, z = obs[..., 0], obs[..., 1], obs[..., 2]
    h = np.hypot(x, z)
    if not (z > 0).all():
        alpha, beta = np.arctan2(x, z), np.arctan2(y, h)
        return np.stack([alpha.min(1), alpha.max(1), beta.min(1), beta.max(1)], axis=1)
    n = np.arange(len(obs))[:, None]
    ta, tb = x / z, y / h
    ia = np.stack([ta.argmin(1), ta.argmax(1)], axis=1)
    ib = np.stack([tb.argmin(1), tb.argmax(1)], axis=1)
    return np.concatenate([np.arctan2(x[n, ia], z[n, ia]), np.arctan2(y[n, ib], h[n, ib])],
                          axis=1)


def window_fit(lidar, vertices_of, names, table) -> tuple[int, int, int, int]:
    """(targets cut by the window, targets checked, W, H): W x H the smallest even window at
    ``lidar``'s cells holding every checked target whole. ``vertices_of(name)`` gives a type's
    body-frame vertices; ``table`` rows are (code, r0 m, beta0, pitch, yaw, roll) rad, one per
    name; the first :data:`WINDOW_CHECK_ROWS` rows are checked, from the exact directions of the
    vertices (the simulator's angular boxes without their padding)."""
    import numpy as np

    from .frames import body_to_observation_matrices, target_centres
    table = np.asarray(table, np.float64)[:WINDOW_CHECK_ROWS]
    names = list(names)[:WINDOW_CHECK_ROWS]
    if not len(table):
        return 0, 0, lidar.width, lidar.height
    m = body_to_observation_matrices(table[:, 3], table[:, 4], table[:, 5])
    c = target_centres(table[:, 1], table[:, 2])
    ext = np.zeros((len(table), 4))
    for name in dict.fromkeys(names):
        rows = np.flatnonzero(np.array(names) == name)
        v = np.asarray(vertices_of(name), np.float64)
        step = max(1, WINDOW_CHECK_POINTS // max(len(v), 1))  # rows a pass: bounded memory
        for at in range(0, len(rows), step):
            part = rows[at:at + step]
            ext[part] = _angle_extremes(np.matmul(v, m[part].transpose(0, 2, 1))
                                        + c[part, None, :])
    w_lo, h_lo = lidar.cell_of_angles(ext[:, 0], ext[:, 2], table[:, 2])
    w_hi, h_hi = lidar.cell_of_angles(ext[:, 1], ext[:, 3], table[:, 2])
    cut = ~(lidar.inside(w_lo, h_lo) & lidar.inside(w_hi, h_hi))
    width, height = lidar.window_that_fits(ext[:, 0], ext[:, 1], ext[:, 2], ext[:, 3],
                                           table[:, 2])
    return int(cut.sum()), len(table), max(width, lidar.width), max(height, lidar.height)


def window_warning(lidar, n_cut: int, n_checked: int, width: int, height: int,
                   what: str) -> str | None:
    """"window too small": the lidar's window cuts the target (its cloud ends at the window's
    edge), with the window at the same cells that holds it whole."""
    if not n_cut:
        return None
    share = "" if n_checked == 1 else f" ({n_cut:,} of the {n_checked:,} checked)"
    head = (f"window too small: the lidar's {lidar.width} x {lidar.height} window cuts "
            f"{what}{share} at its edge; ")
    them = "it" if n_checked == 1 else "them"
    try:  # a window a lidar file may hold (LidarParams' rules and its side), else none
        type(lidar)(lidar.r_alpha, lidar.r_beta, lidar.r_r, width, height)
        fits = max(width, height) <= MAX_WINDOW_SIDE
    except InputError:
        fits = False
    if not fits:
        return (head + f"no window at these cells holds {them} whole (it would need "
                f"{width} x {height} cells; a window is at most {MAX_WINDOW_SIDE} cells a side "
                "and 180 x 90 deg): use coarser cells (r_alpha_deg, r_beta_deg) or a longer "
                "range")
    return (head + f"a window of width = {width}, height = {height} at the same cells holds "
            f"{them} whole (the [lidar] table's width and height)")
