"""The rays of a batch of samples of one type (SPEC section 4), in the type's body frame.

The mesh never moves. For each sample we find the cells of the window that can see the target
(its angular bounding box), make one ray per cell (or k x k per cell), and move the rays into
the body frame, starting just outside the target's bounding sphere. Backends then only answer
"how far along this short ray is the first surface"; the slant range is the ray's start range
(float64) plus that distance, so float32 inside a backend costs micrometres, not millimetres,
even at 18 km.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from apcg_core.condition import FIELDS, Condition
from apcg_core.errors import InputError
from apcg_core.frames import body_to_observation_matrices, target_centres
from apcg_core.lidar import LidarParams

from . import kernels

# Cells added on each side of the box found from the mesh vertices. The extreme elevation of a
# triangle can lie inside an edge (a horizontal edge across the line of sight is highest in its
# middle); at the paper's ranges that shifts the box by < 0.1 cell, so one cell covers it.
BOX_PAD_CELLS = 1


def bounding_radius(vertices: np.ndarray) -> float:
    """Radius of the sphere about the body origin (centre of mass) holding every vertex."""
    return float(np.sqrt((np.asarray(vertices, dtype=np.float64) ** 2).sum(axis=1).max()))


def start_margin_m(radius: float) -> float:
    """How far outside the bounding sphere rays start (keeps the first surface strictly ahead)."""
    return max(1e-3 * radius, 0.01)


def check_conditions(conditions, radius: float) -> np.ndarray:
    """Conditions (N, 6) [type, r0, beta0, pitch, yaw, roll] as float64, each physically valid
    and with the lidar outside the target's bounding sphere."""
    table = np.atleast_2d(np.asarray(conditions, dtype=np.float64))
    if table.ndim != 2 or table.shape[1] != 6:
        raise InputError(f"conditions have shape (N, 6) {FIELDS}, got {table.shape}")
    half_turn, quarter_turn = np.pi, np.pi / 2
    ok = (np.isfinite(table).all(axis=1) & (table[:, 0] >= 0)
          & (table[:, 0] == np.round(table[:, 0])) & (table[:, 1] > 0)
          & (np.abs(table[:, 2]) < quarter_turn) & (np.abs(table[:, 3]) <= quarter_turn)
          & (np.abs(table[:, 4]) <= half_turn) & (np.abs(table[:, 5]) <= half_turn))
    if not ok.all():
        i = int(np.argmin(ok))
        try:
            Condition.from_array(table[i])  # its message names the field and accepted range
        except InputError as exc:
            raise InputError(f"condition {i}: {exc}") from exc
    need = radius + 2.0 * start_margin_m(radius)
    close = table[:, 1] <= need
    if close.any():
        i = int(np.argmax(close))
        raise InputError(
            f"condition {i}: range_m = {table[i, 1]:.6g} m puts the lidar inside the target's "
            f"bounding sphere (radius {radius:.3f} m); accepted: range_m > {need:.3f} m")
    return table


@dataclass
class AngularBoxes:
    """Per-sample cell box [w_lo, w_hi] x [h_lo, h_hi] (inclusive), already clipped to the window;
    ``clipped`` says where the target's box reached beyond the window (its image is cut)."""

    w_lo: np.ndarray
    w_hi: np.ndarray
    h_lo: np.ndarray
    h_hi: np.ndarray
    clipped: np.ndarray
    # the target's box lies wholly outside the window (the clipped box is then one edge
    # line, whose rays meet nothing); None where not known
    outside: np.ndarray | None = None

    def __getitem__(self, sl) -> AngularBoxes:
        return AngularBoxes(self.w_lo[sl], self.w_hi[sl], self.h_lo[sl], self.h_hi[sl],
                            self.clipped[sl],
                            None if self.outside is None else self.outside[sl])

    @property
    def n_cells(self) -> np.ndarray:
        return np.maximum(self.w_hi - self.w_lo + 1, 0) * np.maximum(self.h_hi - self.h_lo + 1, 0)


def sample_frames(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample body->observation matrices M (N, 3, 3) and centres C (N, 3)."""
    return (body_to_observation_matrices(table[:, 3], table[:, 4], table[:, 5]),
            target_centres(table[:, 1], table[:, 2]))


def angular_boxes(vertices: np.ndarray, table: np.ndarray, lidar: LidarParams,
                  m: np.ndarray, c: np.ndarray, compiled: bool | None = None) -> AngularBoxes:
    """The window cells that can see the target, from its vertices' directions (+ padding).
    ``compiled``: screen the vertices with the compiled kernel (default: when this process has
    loaded the kernels, :func:`kernels.use_for`); the boxes are the same either way."""
    a_lo, a_hi, b_lo, b_hi = _angle_extremes(np.asarray(vertices, dtype=np.float64), m, c,
                                             compiled)
    # an edge between two vertices rises above both (or sinks below): by at most what an arc
    # as long as the target's angular diameter can, from the highest (lowest) vertex
    reach = _angular_radius(vertices, c)
    b_hi = _arc_top(b_hi, 2.0 * reach)
    b_lo = -_arc_top(-b_lo, 2.0 * reach)
    w_lo, h_lo = lidar.cell_of_angles(a_lo, b_lo, table[:, 2])
    w_hi, h_hi = lidar.cell_of_angles(a_hi, b_hi, table[:, 2])
    w_lo, h_lo = w_lo - BOX_PAD_CELLS, h_lo - BOX_PAD_CELLS
    w_hi, h_hi = w_hi + BOX_PAD_CELLS, h_hi + BOX_PAD_CELLS
    W2, H2 = lidar.width // 2, lidar.height // 2
    # A target whose bounding sphere reaches the zenith or the nadir: the window's rows past
    # the pole (elevation beyond +-90 deg: rays over the top, azimuth turned half a turn) meet
    # it too, but no vertex has such an elevation; every column and every row on that side
    # is cast instead.
    north, south = _reaches_pole(reach, c)
    w_lo = np.where(north | south, np.minimum(w_lo, -W2), w_lo)
    w_hi = np.where(north | south, np.maximum(w_hi, W2 - 1), w_hi)
    h_hi = np.where(north, np.maximum(h_hi, H2 - 1), h_hi)
    h_lo = np.where(south, np.minimum(h_lo, -H2), h_lo)
    clipped = (w_lo < -W2) | (w_hi > W2 - 1) | (h_lo < -H2) | (h_hi > H2 - 1)
    outside = (w_hi < -W2) | (w_lo > W2 - 1) | (h_hi < -H2) | (h_lo > H2 - 1)
    return AngularBoxes(np.clip(w_lo, -W2, W2 - 1), np.clip(w_hi, -W2, W2 - 1),
                        np.clip(h_lo, -H2, H2 - 1), np.clip(h_hi, -H2, H2 - 1), clipped,
                        outside)


def _angular_radius(vertices, c) -> np.ndarray:
    """Per sample: the angle the target's bounding sphere (about its centre ``c``) subtends
    from the lidar, half its angular diameter."""
    radius = bounding_radius(vertices) if len(vertices) else 0.0
    dist = np.linalg.norm(c, axis=1)
    return np.arcsin(np.minimum(1.0, radius / np.maximum(dist, 1e-300)))


def _arc_top(top: np.ndarray, length: np.ndarray) -> np.ndarray:
    """The highest elevation a great-circle arc of angular ``length`` whose ends lie at or
    below elevation ``top`` can reach (a straight edge seen from the lidar is such an arc):
    its ends both at ``top``, their azimuths as far apart as ``length`` allows (cos length =
    sin^2 top + cos^2 top cos dA), its middle at atan(tan top / cos(dA / 2)). Below the
    horizon's far side, or where the arc could pass over the pole, the zenith. At the
    paper's elevations and ranges it adds ~1e-6 rad (a thousandth of a cell); near the zenith
    whole rows that the vertices alone missed (a 64 m box at 3 km and 88.7 deg: 4 rows)."""
    top = np.asarray(top, np.float64)
    cos_top = np.cos(top)
    with np.errstate(divide="ignore", invalid="ignore"):
        one_minus = (1.0 - np.cos(length)) / (cos_top * cos_top)  # 1 - cos dA
        half = 0.5 * np.arccos(np.clip(1.0 - one_minus, -1.0, 1.0))  # dA / 2
        rise = np.arctan(np.tan(top) / np.cos(half))
    over = (one_minus >= 2.0) | (cos_top <= 0.0) | ~np.isfinite(rise) | (half >= np.pi / 2)
    return np.where(over, np.pi / 2, np.maximum(top, np.where(top >= 0.0, rise, top)))


def _reaches_pole(reach, c) -> tuple[np.ndarray, np.ndarray]:
    """Per sample: whether the target's bounding sphere (about its centre ``c``, of angular
    radius ``reach``: :func:`_angular_radius`) reaches the zenith, and the nadir (the centre's
    elevation +- ``reach``)."""
    beta = np.arctan2(c[:, 1], np.hypot(c[:, 0], c[:, 2]))
    return beta + reach >= np.pi / 2, beta - reach <= -np.pi / 2


def _exact_angles(m, vertices, c):
    """Azimuth and elevation of body points (float64): the one definition the boxes use."""
    obs = np.einsum("nij,vj->nvi", m, vertices) + c[:, None, :]
    alpha = np.arctan2(obs[..., 0], obs[..., 2])
    beta = np.arctan2(obs[..., 1], np.hypot(obs[..., 0], obs[..., 2]))
    return alpha, beta


# Relative width of the band of near-extreme vertices kept by the float32 screen below, in
# units of the screen's own worst-case error (about 5e-7 of the target's angular half-size).
_SCREEN_TOL = 1e-5


def _angle_extremes(vertices, m, c, compiled=None):
    """Per sample min / max of the vertices' azimuth and elevation, as :func:`_exact_angles` of
    every vertex gives them.

    Evaluating arctan2 in float64 for every vertex of every sample was a third of a build's time.
    Azimuth is monotonic in x / z and elevation in y / hypot(x, z) while z > 0, so a float32
    screen of those ratios finds, per sample and extreme, the few vertices within a band ~20
    times wider than the screen's rounding error; only they get the float64 evaluation, and the
    extreme over them is the extreme over all vertices. numpy's SIMD arctan2 may differ by an
    ulp between memory layouts, so an extreme can differ from the all-vertex one by 1-2 ulp
    (~1e-19 rad); the cell indices made from it do not (checked on 72,000 samples of every type,
    and the shards of the committed configs are byte-identical: docs/SCALE.md)."""
    n = len(m)
    radius = float(np.sqrt((vertices**2).sum(axis=1).max())) if len(vertices) else 0.0
    z_floor = c[:, 2] - radius
    if n == 0 or len(vertices) < 16 or not (z_floor > 4.0 * radius).all():
        # near-zenith or tiny meshes: no screen, every vertex exactly
        alpha, beta = _exact_angles(m, vertices, c)
        return alpha.min(axis=1), alpha.max(axis=1), beta.min(axis=1), beta.max(axis=1)
    if kernels.use_for(0) if compiled is None else compiled:  # once the kernels are loaded
        ns, vs = _screen_compiled(vertices, m, c, radius, z_floor)
    else:
        ns, vs = np.nonzero(_screen_numpy(vertices, m, c, radius, z_floor))
    # (ns, vs) row-major: grouped by sample, each sample present
    # The same float64 arithmetic as _exact_angles, pair by pair (einsum sums the three
    # products in the same order for any operand shape).
    obs = np.einsum("nij,nj->ni", m[ns], vertices[vs]) + c[ns]
    alpha = np.arctan2(obs[:, 0], obs[:, 2])
    beta = np.arctan2(obs[:, 1], np.hypot(obs[:, 0], obs[:, 2]))
    start = np.searchsorted(ns, np.arange(n))
    return (np.minimum.reduceat(alpha, start), np.maximum.reduceat(alpha, start),
            np.minimum.reduceat(beta, start), np.maximum.reduceat(beta, start))


def _screen_numpy(vertices, m, c, radius, z_floor):
    """keep[s, v]: the vertices within the band of sample s's extreme ratios (float32)."""
    n = len(m)
    v32 = np.ascontiguousarray(vertices.T, dtype=np.float32)
    u = (m.reshape(-1, 3).astype(np.float32) @ v32).reshape(n, 3, -1)  # M v, small: ~radius
    c32 = c.astype(np.float32)
    x = u[:, 0]
    y = u[:, 1]
    y += c32[:, 1, None]
    z = u[:, 2]
    z += c32[:, 2, None]
    ta = x / z
    h = np.sqrt(x * x + z * z)
    tb = y / h
    # float32 keeps the ratios to ~5e-7 of (radius / distance) plus their own size; the band
    # is _SCREEN_TOL of that scale: ~20 times wider than the worst error.
    scale = (radius / z_floor).astype(np.float32)[:, None]
    tol_a = _SCREEN_TOL * scale
    tol_b = _SCREEN_TOL * (scale + np.abs(tb).max(axis=1, keepdims=True))
    keep = ta >= ta.max(axis=1, keepdims=True) - tol_a
    keep |= ta <= ta.min(axis=1, keepdims=True) + tol_a
    keep |= tb >= tb.max(axis=1, keepdims=True) - tol_b
    keep |= tb <= tb.min(axis=1, keepdims=True) + tol_b
    return keep


def _screen_compiled(vertices, m, c, radius, z_floor):
    """np.nonzero(:func:`_screen_numpy`) in one compiled pass per sample. Its float32
    arithmetic is not numpy's (order, no BLAS), which only moves the band's edges by an ulp;
    the band is ~20 times wider than either's error, so both keep every vertex that can be an
    extreme (tests/test_ray_kernel.py compares the boxes)."""
    k = kernels.require()
    n, nv = len(m), len(vertices)
    ns = np.empty(n * nv, np.int64)  # pages past the few kept pairs are never touched
    vs = np.empty(n * nv, np.int64)
    n_kept = k.screen(np.ascontiguousarray(vertices.T, dtype=np.float32),
                      np.ascontiguousarray(m, dtype=np.float32),
                      np.ascontiguousarray(c, dtype=np.float32),
                      (radius / z_floor).astype(np.float32), np.float32(_SCREEN_TOL), ns, vs,
                      np.empty(nv, np.float32), np.empty(nv, np.float32))
    return ns[:n_kept], vs[:n_kept]


@dataclass
class RayBatch:
    """Rays of several samples, k*k consecutive rays per cell.

    ``origin``/``direction`` are in the body frame (float64, unit directions); a ray's slant
    range from the lidar at its origin is ``t_start[sample]``; ``t_max`` bounds the search.
    """

    sample: np.ndarray  # (C,) sample index of each cell
    w: np.ndarray  # (C,) centred cell indices
    h: np.ndarray
    origin: np.ndarray  # (C * k * k, 3)
    direction: np.ndarray  # (C * k * k, 3)
    t_start: np.ndarray  # (N,)
    t_max: float
    k: int

    @property
    def n_rays(self) -> int:
        return len(self.origin)


def sub_ray_offsets(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (in cells) of the k x k rays of a cell: a centred regular grid; (0, 0) for k = 1."""
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"supersample must be an integer >= 1 (rays per cell side), got {k!r}")
    g = (np.arange(k) + 0.5) / k - 0.5
    du, dv = np.meshgrid(g, g, indexing="xy")
    return du.ravel(), dv.ravel()


def make_rays(table: np.ndarray, boxes: AngularBoxes, lidar: LidarParams, m: np.ndarray,
              c: np.ndarray, radius: float, k: int = 1) -> RayBatch:
    """Rays through the cells of each sample's box, moved into the body frame."""
    n_cells = boxes.n_cells
    sample = np.repeat(np.arange(len(table)), n_cells)
    first = np.concatenate([[0], np.cumsum(n_cells)[:-1]])
    j = np.arange(len(sample)) - first[sample]
    nw = (boxes.w_hi - boxes.w_lo + 1)[sample]
    w = boxes.w_lo[sample] + j % nw
    h = boxes.h_lo[sample] + j // nw

    du, dv = sub_ray_offsets(k)
    kk = len(du)
    if kk > 1:
        rs = np.repeat(sample, kk)
        iw = (np.repeat(w - lidar.w_min, kk) * kk) + np.tile(np.arange(kk), len(w))
        ih = (np.repeat(h - lidar.h_min, kk) * kk) + np.tile(np.arange(kk), len(w))
    else:
        rs, iw, ih = sample, w - lidar.w_min, h - lidar.h_min
    # Trigonometry on small tables, gathered per ray: azimuth depends on the cell column only,
    # elevation on the sample's beta0 and the cell row.
    g = np.arange(lidar.width)[:, None] + lidar.w_min
    alpha = ((g + du[None, :]).ravel() if kk > 1 else g.ravel()) * lidar.r_alpha
    sa, ca = np.sin(alpha)[iw], np.cos(alpha)[iw]
    rows = np.arange(lidar.height)[:, None] + lidar.h_min
    rows = (rows + dv[None, :]).ravel() if kk > 1 else rows.ravel()
    beta = table[:, 2, None] + rows[None, :] * lidar.r_beta  # (N, H * kk)
    flat = rs * beta.shape[1] + ih
    sb, cb = np.sin(beta).ravel()[flat], np.cos(beta).ravel()[flat]

    margin = start_margin_m(radius)
    t_start = table[:, 1] - radius - margin
    origin, direction = _body_rays(sa, ca, sb, cb, m, c, rs, t_start)
    return RayBatch(sample=sample, w=w.astype(np.int32), h=h.astype(np.int32), origin=origin,
                    direction=direction, t_start=t_start,
                    t_max=2.0 * (radius + 2.0 * margin), k=kk)


def _body_rays(sa, ca, sb, cb, m, c, rs, t_start):
    """Origins and unit directions (float64, body frame) of rays of azimuth sines / cosines
    (sa, ca) and elevation sines / cosines (sb, cb), ray i belonging to sample rs[i]."""
    # Body frame: d_body = M^T d_obs, and with d_obs = (cb sa, sb, cb ca) that is
    # cb (sa M[0] + ca M[2]) + sb M[1] (rows of M).
    direction = np.empty((len(rs), 3))
    for i in range(3):
        direction[:, i] = cb * (sa * m[rs, 0, i] + ca * m[rs, 2, i]) + sb * m[rs, 1, i]
    # The origin is the point at range t_start along the ray: M^T (t_start d_obs - C). Both terms
    # are ~r0 long; float64 keeps their small difference exact to picometres.
    lidar_body = np.einsum("nji,nj->ni", m, c)  # M^T C
    origin = t_start[rs, None] * direction - lidar_body[rs]
    return origin, direction


def cell_rays(table: np.ndarray, w: np.ndarray, h: np.ndarray, lidar: LidarParams,
              m: np.ndarray, c: np.ndarray, radius: float):
    """The ray through cell (w[i], h[i]) of sample i (rows of table, m, c), one ray per cell:
    :func:`make_rays`' numbers for those cells (sines and cosines of the same angles, numpy's
    being elementwise, then the same arithmetic), without the per-row tables a box needs.
    Returns origin, direction (float64, body frame), t_start per ray and t_max."""
    alpha = np.asarray(w, dtype=np.int64) * lidar.r_alpha
    beta = table[:, 2] + np.asarray(h, dtype=np.int64) * lidar.r_beta
    margin = start_margin_m(radius)
    t_start = table[:, 1] - radius - margin
    origin, direction = _body_rays(np.sin(alpha), np.cos(alpha), np.sin(beta), np.cos(beta), m,
                                   c, np.arange(len(table)), t_start)
    return origin, direction, t_start, 2.0 * (radius + 2.0 * margin)


# Rays per block of the float32 path: the per-ray temporaries (~100 bytes a ray) stay in the
# CPU's cache, where numpy runs several times faster than from memory.
BLOCK_RAYS = 32_768


@dataclass
class RayBlock:
    """One-ray-per-cell rays of consecutive samples, ready for a float32 ray caster: the same
    numbers as :func:`make_rays` gives (k = 1), rounded once to float32.

    Rays run sample by sample, then row (h) by row, then column (w); ``row_*`` describe each
    box row so that a ray index maps back to its cell without per-ray index arrays."""

    origin: np.ndarray  # (n, 3) float32
    direction: np.ndarray  # (n, 3) float32
    row_start: np.ndarray  # (R,) first ray of each row
    row_sample: np.ndarray  # (R,) sample of each row (index into the whole table)
    row_h: np.ndarray  # (R,) centred elevation index of each row
    w_lo: np.ndarray  # (N,) first column of each sample's box (whole table)
    t_start: np.ndarray  # (N,) slant range at the rays' origins (whole table)
    t_max: float

    def cells(self, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample, w and h of rays given by index (ascending or not)."""
        row = np.searchsorted(self.row_start, ray, side="right") - 1
        s = self.row_sample[row]
        return s, self.w_lo[s] + (ray - self.row_start[row]), self.row_h[row]


def _block_plan(table, boxes, lidar, radius):
    """What every block of one table shares: box sizes, column sines, start ranges, t_max."""
    nw = np.maximum(boxes.w_hi - boxes.w_lo + 1, 0)
    nh = np.maximum(boxes.h_hi - boxes.h_lo + 1, 0)
    g = (np.arange(lidar.width) + lidar.w_min) * lidar.r_alpha
    margin = start_margin_m(radius)
    t_start = table[:, 1] - radius - margin
    t_max = 2.0 * (radius + 2.0 * margin)
    return nw, nh, np.sin(g), np.cos(g), t_start, t_max


def _block_spans(n_cells, block_rays):
    """(start, stop, first ray, rays) of each block of samples [start, stop): whole samples,
    about ``block_rays`` rays (more when one sample has more)."""
    n = len(n_cells)
    ends = np.cumsum(n_cells)
    start = 0
    while start < n:
        first = int(ends[start - 1]) if start else 0
        stop = int(np.searchsorted(ends, first + block_rays, side="right"))
        stop = min(max(stop, start + 1), n)
        yield start, stop, first, int(ends[stop - 1]) - first
        start = stop


def _block_elevations(table, lidar, start, stop):
    """sin and cos of every window row's elevation for samples [start, stop), (n, H)."""
    rows = np.arange(lidar.height) + lidar.h_min
    beta = table[start:stop, 2, None] + rows[None, :] * lidar.r_beta  # (n, H), as make_rays
    return np.sin(beta), np.cos(beta)


def ray_blocks(table: np.ndarray, boxes: AngularBoxes, lidar: LidarParams, m: np.ndarray,
               c: np.ndarray, radius: float, block_rays: int = BLOCK_RAYS):
    """:func:`make_rays` for k = 1 in blocks of whole samples, written straight to float32.

    Every float64 operation of make_rays is kept, operand for operand and in the same order
    (the float32 rays, hence embree's answers, must not change by a bit); what changes is that
    the factors that depend on the sample and column, or on the sample and row, are made once
    per column or row instead of once per ray, and per-ray gathers become row repeats."""
    nw, nh, sin_a, cos_a, t_start, t_max = _block_plan(table, boxes, lidar, radius)
    for start, stop, _, _ in _block_spans(nw * nh, block_rays):
        yield _block(table, boxes, lidar, m, c, start, stop, nw, nh, sin_a, cos_a, t_start,
                     t_max)


def cast_cells(caster, table: np.ndarray, boxes: AngularBoxes, lidar: LidarParams,
               m: np.ndarray, c: np.ndarray, radius: float, compiled: bool | None = None,
               block_rays: int = BLOCK_RAYS):
    """(sample, w, h, float64 range) of every hit cell, one ray per cell, for a caster with
    ``cast_hits`` (and ``distances32`` for the compiled path): the build's hot loop.

    ``compiled`` (default: :func:`kernels.use_for` these rays) makes each block's rays and
    reads its hits in compiled loops (:mod:`dataset_builder.kernels`); otherwise
    :func:`ray_blocks` and the caster's ``cast_hits`` do it in numpy. Both give the same
    bytes."""
    if compiled is None:
        compiled = (hasattr(caster, "distances32")
                    and kernels.use_for(int(boxes.n_cells.sum())))
    if compiled:
        return _cast_cells_compiled(caster, table, boxes, lidar, m, c, radius, block_rays)
    parts = []
    for blk in ray_blocks(table, boxes, lidar, m, c, radius, block_rays):
        ray, t = caster.cast_hits(blk.origin, blk.direction, blk.t_max)
        s, w, h = blk.cells(ray)
        parts.append((s, w.astype(np.int32), h.astype(np.int32), blk.t_start[s] + t))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0)
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(4))


def _cast_cells_compiled(caster, table, boxes, lidar, m, c, radius, block_rays):
    k = kernels.require()
    blocks = compiled_ray_blocks(table, boxes, lidar, m, c, radius, block_rays)
    plan = next(blocks)
    limit = np.float32(plan.t_max)
    hit_limit = float(limit) * (1.0 - 1e-6)  # backends.is_hit, in the kernel
    # Hits land here in ray order; pages never written (the misses' share) are never touched.
    out_s = np.empty(plan.n_rays, np.int64)
    out_w = np.empty(plan.n_rays, np.int32)
    out_h = np.empty(plan.n_rays, np.int32)
    out_r = np.empty(plan.n_rays)
    t_buf = np.empty(plan.biggest, np.float32)
    n_hits = 0
    for start, stop, o, d in blocks:
        t32 = caster.distances32(o, d, limit, out=t_buf[:len(o)])
        n_hits = k.hits(start, stop, plan.nw, plan.nh, plan.w_lo, plan.h_lo, plan.t_start, t32,
                        d, limit, hit_limit, out_s, out_w, out_h, out_r, n_hits)
    return out_s[:n_hits], out_w[:n_hits], out_h[:n_hits], out_r[:n_hits]


@dataclass
class CompiledPlan:
    """What the compiled blocks of one table share (first item of compiled_ray_blocks)."""

    nw: np.ndarray  # (N,) int64 box columns and rows of each sample
    nh: np.ndarray
    w_lo: np.ndarray  # (N,) int64
    h_lo: np.ndarray
    t_start: np.ndarray  # (N,) float64
    t_max: float
    n_rays: int
    biggest: int  # rays in the largest block


def compiled_ray_blocks(table: np.ndarray, boxes: AngularBoxes, lidar: LidarParams,
                        m: np.ndarray, c: np.ndarray, radius: float,
                        block_rays: int = BLOCK_RAYS):
    """:func:`ray_blocks`' rays made by the compiled kernel: first a :class:`CompiledPlan`,
    then (start, stop, origin, direction) per block of samples [start, stop). The float32
    arrays are one buffer reused by every block: use (or copy) them before the next."""
    k = kernels.require()
    nw, nh, sin_a, cos_a, t_start, t_max = _block_plan(table, boxes, lidar, radius)
    i64 = np.int64
    nw, nh = nw.astype(i64), nh.astype(i64)
    w_lo, h_lo = boxes.w_lo.astype(i64), boxes.h_lo.astype(i64)
    m = np.ascontiguousarray(m, dtype=np.float64)
    n_cells = nw * nh
    spans = list(_block_spans(n_cells, block_rays))
    biggest = max((sp[3] for sp in spans), default=0)
    yield CompiledPlan(nw, nh, w_lo, h_lo, t_start, t_max, int(n_cells.sum()), biggest)
    # sin and cos of the elevation of every box row, once per table: the numbers rays._block
    # takes from its (n, H) tables, numpy's sin and cos being elementwise (the same number for
    # the same input in any array; tests/test_ray_kernel.py compares the rays); M^T C too
    row_ends = np.cumsum(nh)
    beta = np.empty(int(row_ends[-1]) if len(row_ends) else 0)
    k.row_elevations(nh, h_lo, np.ascontiguousarray(table[:, 2]), float(lidar.r_beta), beta)
    sin_b, cos_b = np.sin(beta), np.cos(beta)
    lidar_body = np.einsum("nji,nj->ni", m, c)  # as make_rays (the same for any block)
    origin = np.empty((biggest, 3), np.float32)
    direction = np.empty((biggest, 3), np.float32)
    u = np.empty((lidar.width, 3))
    for start, stop, _, n_rays in spans:
        o, d = origin[:n_rays], direction[:n_rays]
        k.rays(start, stop, int(row_ends[start - 1]) if start else 0, nw, nh, w_lo,
               lidar.w_min, sin_a, cos_a, sin_b, cos_b, m, t_start, lidar_body, u, o, d)
        yield start, stop, o, d


def _block(table, boxes, lidar, m, c, start, stop, nw, nh, sin_a, cos_a, t_start, t_max):
    sl = slice(start, stop)
    samples = np.arange(start, stop)
    sin_b, cos_b = _block_elevations(table, lidar, start, stop)
    # per box row: its sample, h, cos/sin of its elevation
    row_sample = np.repeat(samples, nh[sl])
    first_row = np.concatenate([[0], np.cumsum(nh[sl])[:-1]])
    row_h = boxes.h_lo[row_sample] + (np.arange(len(row_sample)) - first_row[row_sample - start])
    flat = (row_sample - start) * lidar.height + (row_h - lidar.h_min)
    cb, sb = cos_b.ravel()[flat], sin_b.ravel()[flat]
    row_nw = nw[row_sample]
    row_start = np.concatenate([[0], np.cumsum(row_nw)[:-1]])
    n_rays = int(row_nw.sum())
    # per box column of each sample: sa M[0] + ca M[2] (rows of M), the column's factor
    col_sample = np.repeat(samples, nw[sl])
    first_col = np.concatenate([[0], np.cumsum(nw[sl])[:-1]])
    col_w = boxes.w_lo[col_sample] + (np.arange(len(col_sample)) - first_col[col_sample - start])
    iw = col_w - lidar.w_min
    sa, ca = sin_a[iw], cos_a[iw]
    mc = m[col_sample]
    u = sa[:, None] * mc[:, 0, :] + ca[:, None] * mc[:, 2, :]  # (C, 3)
    # every ray's column in u: rows of one sample share its columns
    col_of_row = first_col[row_sample - start]
    col = np.arange(n_rays) - np.repeat(row_start - col_of_row, row_nw)
    u_ray = u[col]
    lidar_body = np.einsum("nji,nj->ni", m[sl], c[sl])  # M^T C, as make_rays
    mr = m[row_sample]
    per_row = np.empty((len(row_sample), 8))
    per_row[:, 0] = cb
    per_row[:, 1:4] = sb[:, None] * mr[:, 1, :]
    per_row[:, 4] = t_start[row_sample]
    per_row[:, 5:8] = lidar_body[row_sample - start]
    p = np.repeat(per_row, row_nw, axis=0)
    direction = np.empty((n_rays, 3), np.float32)
    origin = np.empty((n_rays, 3), np.float32)
    d = np.empty(n_rays)
    for i in range(3):
        np.multiply(p[:, 0], u_ray[:, i], out=d)
        d += p[:, 1 + i]
        direction[:, i] = d
        d *= p[:, 4]
        np.subtract(d, p[:, 5 + i], out=origin[:, i])
    return RayBlock(origin, direction, row_start, row_sample, row_h, boxes.w_lo, t_start, t_max)
