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

    def __getitem__(self, sl) -> AngularBoxes:
        return AngularBoxes(self.w_lo[sl], self.w_hi[sl], self.h_lo[sl], self.h_hi[sl],
                            self.clipped[sl])

    @property
    def n_cells(self) -> np.ndarray:
        return np.maximum(self.w_hi - self.w_lo + 1, 0) * np.maximum(self.h_hi - self.h_lo + 1, 0)


def sample_frames(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample body->observation matrices M (N, 3, 3) and centres C (N, 3)."""
    return (body_to_observation_matrices(table[:, 3], table[:, 4], table[:, 5]),
            target_centres(table[:, 1], table[:, 2]))


def angular_boxes(vertices: np.ndarray, table: np.ndarray, lidar: LidarParams,
                  m: np.ndarray, c: np.ndarray) -> AngularBoxes:
    """The window cells that can see the target, from its vertices' directions (+ padding)."""
    obs = np.einsum("nij,vj->nvi", m, vertices) + c[:, None, :]
    alpha = np.arctan2(obs[..., 0], obs[..., 2])
    beta = np.arctan2(obs[..., 1], np.hypot(obs[..., 0], obs[..., 2]))
    w_lo, h_lo = lidar.cell_of_angles(alpha.min(axis=1), beta.min(axis=1), table[:, 2])
    w_hi, h_hi = lidar.cell_of_angles(alpha.max(axis=1), beta.max(axis=1), table[:, 2])
    w_lo, h_lo = w_lo - BOX_PAD_CELLS, h_lo - BOX_PAD_CELLS
    w_hi, h_hi = w_hi + BOX_PAD_CELLS, h_hi + BOX_PAD_CELLS
    W2, H2 = lidar.width // 2, lidar.height // 2
    clipped = (w_lo < -W2) | (w_hi > W2 - 1) | (h_lo < -H2) | (h_hi > H2 - 1)
    return AngularBoxes(np.clip(w_lo, -W2, W2 - 1), np.clip(w_hi, -W2, W2 - 1),
                        np.clip(h_lo, -H2, H2 - 1), np.clip(h_hi, -H2, H2 - 1), clipped)


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

    # Body frame: d_body = M^T d_obs, and with d_obs = (cb sa, sb, cb ca) that is
    # cb (sa M[0] + ca M[2]) + sb M[1] (rows of M).
    direction = np.empty((len(rs), 3))
    for i in range(3):
        direction[:, i] = cb * (sa * m[rs, 0, i] + ca * m[rs, 2, i]) + sb * m[rs, 1, i]

    margin = start_margin_m(radius)
    t_start = table[:, 1] - radius - margin
    # The origin is the point at range t_start along the ray: M^T (t_start d_obs - C). Both terms
    # are ~r0 long; float64 keeps their small difference exact to picometres.
    lidar_body = np.einsum("nji,nj->ni", m, c)  # M^T C
    origin = t_start[rs, None] * direction - lidar_body[rs]
    return RayBatch(sample=sample, w=w.astype(np.int32), h=h.astype(np.int32), origin=origin,
                    direction=direction, t_start=t_start,
                    t_max=2.0 * (radius + 2.0 * margin), k=kk)
