"""Results a user would not expect, said as warnings (stderr, exit 0): the job is still done.

The simulator accepts any range and pose (it is exact anywhere), but a drone at 17 km or a
cloud of one point is rarely what was meant. Each check returns its message or None, so every
command words the same case the same way.
"""

from __future__ import annotations

from .condition import ConditionSpace

# Fewer points than this is a cloud few detectors or metrics can use.
SPARSE_POINTS = 10


def range_band_warning(t, range_m: float) -> str | None:
    """``range_m`` outside the Table 1 band of the type ``t`` (far: 3-18 km, near: 100-600 m,
    SPEC section 3): the trained models and the committed datasets never saw it."""
    space = ConditionSpace()
    lo, hi = space.drone_range_m if t.range_band == "near" else space.aircraft_range_m
    if lo <= range_m <= hi:
        return None
    return (f"{t.name} is a {t.range_band}-band type ({t.kind}): its Table 1 range is "
            f"{lo:g}-{hi:g} m, and {range_m:g} m lies outside it")


def band_share_warning(n_outside: int, n_total: int) -> str | None:
    """Samples of a dataset whose range lies outside their type's Table 1 band."""
    if not n_outside:
        return None
    space = ConditionSpace()
    return (f"{n_outside:,} of {n_total:,} samples lie outside their type's Table 1 range band "
            f"(far types {space.aircraft_range_m[0]:g}-{space.aircraft_range_m[1]:g} m, near "
            f"types {space.drone_range_m[0]:g}-{space.drone_range_m[1]:g} m): the shipped "
            "models never saw such ranges, and far-off small targets give empty clouds")


def empty_clouds_warning(n_empty: int, n_total: int) -> str | None:
    """Empty clouds among many generated at once."""
    if not n_empty:
        return None
    return (f"{n_empty:,} of {n_total:,} clouds are empty (no cell of the lidar's window sees "
            "the target: too small or too far for the lidar); they are counted in `sample` but "
            "hold no points")


def sparse_cloud_warning(n_points: int, what: str) -> str | None:
    """An empty or near-empty cloud: the target covers too few lidar cells."""
    if n_points == 0:
        return (f"{what} is empty: no cell of the lidar's window sees the target (too small "
                "or too far for the lidar's resolution)")
    if n_points < SPARSE_POINTS:
        return (f"{what} has only {n_points} point{'s' * (n_points > 1)}: the target covers "
                f"fewer than {SPARSE_POINTS} lidar cells at this range")
    return None


def _lidar_words(lidar: dict) -> str:
    known = ("r_alpha_deg", "r_beta_deg", "r_r_m", "width", "height")
    words = (f"{lidar.get('r_alpha_deg')} x {lidar.get('r_beta_deg')} deg cells, "
             f"{lidar.get('r_r_m')} m bins, {lidar.get('width')} x {lidar.get('height')} cells")
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
    the model's clouds and the dataset's standard clouds are not comparable cell for cell."""
    data_lidar, model_lidar = dict(data_lidar or {}), dict(model_lidar or {})
    differ = [k for k in sorted(set(data_lidar) | set(model_lidar))
              if not _same_value(data_lidar.get(k), model_lidar.get(k))]
    if not differ:
        return None
    return (f"the dataset {data_name} was made by another lidar ({_lidar_words(data_lidar)}) "
            f"than the model {model_name} was trained for ({_lidar_words(model_lidar)}); "
            f"they differ in {', '.join(differ)}, so its scores compare clouds of two lidars")
