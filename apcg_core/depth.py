"""Depth images: PC2Im (eq. 15), Norm (eq. 17), DeNorm (eq. 1), Im2PC (eqs. 3-5). SPEC 5-6.

Images are float arrays (..., H, W); row 0 is the top (h = H/2 - 1), column 0 the left
(w = -W/2). A batch is any leading shape; per-sample scalars (r0, beta0, l, q) broadcast
against it. Background pixels are -1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cloud import PointCloud
from .condition import check_elevation, check_range_m
from .errors import InputError, check_finite, check_int
from .frames import cartesian_to_spherical, spherical_to_cartesian
from .lidar import LidarParams

DEPTH_SCALE = 1.8  # the paper's coefficient in eq. 15: target depths land in about [-0.9, 0.9]
BACKGROUND = -1.0
# Lowest value a target pixel may take: exactly representable in float16 (the dataset's
# storage type) and clearly above background, so no target pixel ever reads as empty.
TARGET_FLOOR = -1.0 + 2.0**-9
# Im2PC threshold: a tanh generator never outputs exactly -1, so "d > -1" would keep every
# pixel. -0.95 is the starting value of SPEC section 6; the evaluation measures and sets it.
TAU_DEFAULT = -0.95
# Absorbs float rounding in floor(w / q) and ceil(w q) so that DeNorm(Norm(d)) == d holds
# exactly where SPEC section 5 says it must (w q that is mathematically an integer).
_INDEX_TOL = 1e-9
DEFAULT_LIDAR = LidarParams()  # frozen, so safe as a shared default


@dataclass
class Pc2imStats:
    """What PC2Im did with a cloud: nothing is dropped without being counted here."""

    n_points: int  # points given
    n_outside: int  # points whose cell lies outside the W x H window (not in the image)
    n_hidden: int  # points behind a nearer point of the same cell (occluded; nearest kept)
    n_clamped: int  # target pixels whose depth fell outside [TARGET_FLOOR, 1] and was clamped
    n_pixels: int  # target pixels written


def _per_sample(name: str, value, n: int) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise InputError(f"{name} must be a scalar or have one value per sample ({n}), "
                         f"got shape {a.shape}")
    if not np.isfinite(a).all():
        raise InputError(f"{name} must be finite")
    return a


def _sample_scalars(who: str, range_m, elevation, length_m, n: int):
    """(r0, beta0, l), one per sample, each what a Condition takes (apcg_core.condition, the
    one home of those ranges): any other is no target's, and its image silently wrong (an
    elevation in degrees puts every point outside the window; r0 <= 0 clamps every depth)."""
    r0 = _per_sample("range_m", range_m, n)
    b0 = _per_sample("elevation", elevation, n)
    length = _per_sample("length_m", length_m, n)
    try:
        check_range_m(r0)
    except InputError as exc:
        raise InputError(f"{who}: {exc}") from None
    try:
        check_elevation(b0)
    except InputError as exc:  # the usual cause: degrees given where radians are taken
        raise InputError(f"{who}: {exc} (elevation is taken in radians)") from None
    if (length <= 0).any():  # every depth would collapse onto r0 (or divide by 0)
        raise InputError(f"{who}: length_m must be > 0, got {float(length[length <= 0][0])!r}")
    return r0, b0, length


def _points(points) -> np.ndarray:
    """(N, 3) float64 points from any array whose last axis is (x, y, z), or from nothing."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1:] != (3,) and pts.shape != (0,):  # reshape would regroup the values
        raise InputError(f"pc2im: points have shape (N, 3) (x, y, z), got shape {pts.shape}")
    return pts.reshape(-1, 3)


def pc2im(points, range_m, elevation, length_m, lidar: LidarParams = DEFAULT_LIDAR,
          sample=None, n_samples: int | None = None, dtype=np.float32, image: bool = True):
    """PC2Im, paper eq. 15: d(w, h) = 1.8 (r(w, h) - r0) / l, background -1.

    ``points`` (N, 3) are in the observation frame. For a batch, ``sample`` gives each point's
    sample index in [0, n_samples) and ``range_m``, ``elevation``, ``length_m`` are per-sample
    arrays; the result is then (n_samples, H, W). When several points fall into one cell the
    nearest is kept (the lidar's first return). Target depths outside [TARGET_FLOOR, 1] are
    clamped so they stay distinguishable from background, and counted.

    Returns ``(image, Pc2imStats)``; ``image`` False: ``(None, Pc2imStats)``, without the
    dense (N, H, W) image (a 65536 x 65536 window's is 16 GiB).
    """
    pts = _points(points)
    batch = sample is not None
    if batch:
        sample = np.asarray(sample, dtype=np.int64).reshape(-1)
        if n_samples is None:
            raise InputError("pc2im: a batch needs n_samples")
        n_samples = check_int("n_samples", n_samples, 0)
        if len(sample) != len(pts):
            raise InputError(f"pc2im: {len(sample)} sample indices for {len(pts)} points")
        if len(sample) and (sample.min() < 0 or sample.max() >= n_samples):
            raise InputError(f"pc2im: sample indices must lie in [0, {n_samples})")
    else:
        n_samples = 1
        sample = np.zeros(len(pts), dtype=np.int64)
    if not np.isfinite(pts).all():
        raise InputError("pc2im: points must be finite (found NaN or inf)")
    r0, b0, length = _sample_scalars("pc2im", range_m, elevation, length_m, n_samples)

    H, W = lidar.height, lidar.width
    alpha, beta, r = cartesian_to_spherical(pts)
    w, h = lidar.cell_of_angles(alpha, beta, b0[sample])
    inside = lidar.inside(w, h)
    s, r, w, h = sample[inside], r[inside], w[inside], h[inside]
    key = (s * H + lidar.row_of_h(h)) * W + lidar.col_of_w(w)
    order = np.lexsort((r, key))  # by pixel, nearest first
    first = np.ones(len(order), dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    keep = order[first]
    d = DEPTH_SCALE * (r[keep] - r0[s[keep]]) / length[s[keep]]
    dc = np.clip(d, TARGET_FLOOR, 1.0)
    stats = Pc2imStats(n_points=len(pts), n_outside=int((~inside).sum()),
                       n_hidden=int(len(order) - len(keep)),
                       n_clamped=int((d != dc).sum()), n_pixels=int(len(keep)))
    if not image:
        return None, stats
    img = np.full(n_samples * H * W, BACKGROUND, dtype=dtype)
    img[key[keep]] = dc
    img = img.reshape(n_samples, H, W)
    return (img if batch else img[0]), stats


def _centred_indices(n: int) -> np.ndarray:
    return np.arange(n) - n // 2


def _resample(d, q, src) -> np.ndarray:
    """out[..., i, j] = d[..., row(src(h)), col(src(w))] (one index map for both axes), -1
    where the source is outside."""
    d = np.asarray(d)
    if d.ndim < 2 or 0 in d.shape[-2:]:
        raise InputError(f"a depth image has shape (..., H, W) with H, W >= 1, got {d.shape}")
    H, W = d.shape[-2:]
    lead = d.shape[:-2]
    flat = d.reshape((-1, H, W))
    q = np.asarray(q, dtype=np.float64)
    try:
        q = np.broadcast_to(q, lead).reshape(-1)
    except ValueError:
        raise InputError(f"q must be a scalar or have the images' batch shape {lead}, got "
                         f"shape {q.shape}") from None
    if not np.isfinite(q).all() or (q <= 0).any():
        raise InputError(f"q must be finite and > 0, got {q[~(np.isfinite(q) & (q > 0))][:3]}")
    w = _centred_indices(W)[None, :].astype(np.float64)
    h = (H // 2 - 1 - np.arange(H))[None, :].astype(np.float64)
    sw = src(w, q[:, None]).astype(np.int64)  # (B, W) centred source w
    sh = src(h, q[:, None]).astype(np.int64)  # (B, H) centred source h
    cols = sw + W // 2
    rows = H // 2 - 1 - sh
    ok_c = (cols >= 0) & (cols < W)
    ok_r = (rows >= 0) & (rows < H)
    b = np.arange(len(flat))[:, None, None]
    out = flat[b, np.clip(rows, 0, H - 1)[:, :, None], np.clip(cols, 0, W - 1)[:, None, :]]
    out = np.where(ok_r[:, :, None] & ok_c[:, None, :], out, np.asarray(BACKGROUND, d.dtype))
    return out.reshape(d.shape).astype(d.dtype, copy=False)


def _denorm_source(x, q):
    """DeNorm's source index ceil(x q), rounding error absorbed (:data:`_INDEX_TOL`)."""
    return np.ceil(x * q - _INDEX_TOL)


def _norm_source(x, q):
    """Norm's source index floor(x / q), computed as the largest w whose DeNorm source
    :func:`_denorm_source` is at most x (the same integer wherever floor(x / q) is not within
    rounding of an integer). Taken from DeNorm's own rounding, so DeNorm(Norm(d)) == d holds
    at every q >= 1, knife edges included: two tolerances applied with opposite signs
    disagreed where (q - 1) |w| is about their size (317 pixels at q = 1 + 1e-9, probe finding
    of stop 53)."""
    k = np.floor(x / q + _INDEX_TOL)  # within one of the answer
    k = np.where(_denorm_source(k, q) > x, k - 1.0, k)
    return np.where(_denorm_source(k + 1.0, q) <= x, k + 1.0, k)


def norm(d, q) -> np.ndarray:
    """Norm, paper eq. 17: d_n(w, h) = d(floor(w / q), floor(h / q)).

    Magnifies a far target (q > 1) to its size at the reference range. ``q`` is a scalar or
    has the batch shape of ``d``. Sources outside the image (possible when q < 1) give -1.
    """
    return _resample(d, q, _norm_source)


def denorm(d_n, q) -> np.ndarray:
    """DeNorm, paper eq. 1: d(w, h) = d_n(ceil(w q), ceil(h q)); sources outside give -1."""
    return _resample(d_n, q, _denorm_source)


def denorm_source_inside(shape: tuple[int, int], q: float) -> np.ndarray:
    """Mask (H, W) of pixels whose DeNorm source (ceil(w q), ceil(h q)) lies in the image."""
    H, W = shape
    w = _denorm_source(_centred_indices(W), q)
    h = _denorm_source(H // 2 - 1 - np.arange(H), q)
    ok_w = (w >= -(W // 2)) & (w < W // 2)
    ok_h = (h >= -(H // 2)) & (h < H // 2)
    return ok_h[:, None] & ok_w[None, :]


def check_tau(tau) -> float:
    """``tau`` if it is an Im2PC threshold: -1 <= tau < 1 (depths lie in [-1, 1], background
    -1; below -1 every background pixel would become a point, at 1 or above none could)."""
    t = check_finite("tau", tau)
    if not -1.0 <= t < 1.0:
        raise InputError(f"tau = {tau!r} is out of range; accepted: -1 <= tau < 1 (depths lie "
                         "in [-1, 1], background -1)")
    return t


def im2pc(d, range_m, elevation, length_m, lidar: LidarParams = DEFAULT_LIDAR,
          tau: float = TAU_DEFAULT) -> PointCloud:
    """Im2PC, paper eqs. 3-5: every pixel with d > tau becomes one point.

    alpha = w R_alpha, beta = h R_beta + beta0, r = d l / 1.8 + r0, then spherical to
    Cartesian. ``d`` is (H, W) or a batch (B, H, W) with per-sample r0, beta0, l; a batch
    returns one stacked cloud whose ``sample`` attribute says which image each point came from.
    """
    d = np.asarray(d)
    if d.shape[-2:] != (lidar.height, lidar.width):
        raise InputError(f"im2pc: image shape {d.shape} does not match the lidar window "
                         f"(H, W) = ({lidar.height}, {lidar.width})")
    batch = d.ndim == 3
    if d.ndim not in (2, 3):
        raise InputError(f"im2pc: expected (H, W) or (B, H, W), got {d.shape}")
    dd = d if batch else d[None]
    n = dd.shape[0]
    r0, b0, length = _sample_scalars("im2pc", range_m, elevation, length_m, n)
    check_tau(tau)  # checked, not converted: the comparison keeps the caller's type
    if not np.isfinite(dd).all():  # an inf pixel would be an inf point; NaN a silent gap
        raise InputError("im2pc: depth images must be finite (found NaN or inf)")
    s, row, col = np.nonzero(dd > tau)
    w = lidar.w_of_col(col)
    h = lidar.h_of_row(row)
    val = dd[s, row, col].astype(np.float64)
    alpha, beta = lidar.cell_centre_angles(w, h, b0[s])
    r = val * length[s] / DEPTH_SCALE + r0[s]
    xyz = spherical_to_cartesian(alpha, beta, r)
    return PointCloud(xyz, r, w, h, s if batch else None)
