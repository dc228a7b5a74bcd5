"""The APCG+ network (apcg_core/families/apcg_plus.py): condition -> sheet (hit logit,
range offset).

The condition enters every block, not only the input: a learned embedding of the type (its code
in the model's own type table) and Fourier features of the scaled pose (range, elevation, pitch,
yaw, roll: nu without its type column) make one condition vector c; each upsampling block is
modulated by c (FiLM: x * (1 + gamma(c)) + beta(c), gamma and beta zero at the start, as
adaLN-Zero starts a block as the identity). Deliberately small: it runs on a CPU per condition.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
from torch import nn

from ..errors import InputError
from ..families.plus_heads import HEADS

POSE_DIM = 5  # nu without its type column
BASE_CHANNELS = (512, 256, 128, 64, 32, 16, 8)


@dataclass(frozen=True)
class PlusConfig:
    """Architecture of one APCG+ network. ``width`` scales every channel count; ``sheet`` is
    the side of the square sheet (4 x 2^k); ``film`` False feeds c to the first layer only
    (the ablation of per-block conditioning). ``head`` is how the sheet is drawn from the last
    features: ``conv``, a 3 x 3 convolution over features at the sheet's own resolution (the
    trained default); ``upconv``, the last upsampling step draws the sheet itself, so no
    features are ever held at full resolution (about 0.6 times the cost a condition on a CPU,
    docs/SCALE.md; what ``apcg distill`` makes). ``outputs`` is the sheet's channels: 2 for a
    model's network (hit logit, range offset), 1 for its incidence network (the logit of the
    cosine of incidence, training/families/plus_incidence.py)."""

    n_types: int
    width: float = 1.0
    sheet: int = 64
    embed: int = 32
    fourier: int = 6
    hidden: int = 256
    film: bool = True
    head: str = "conv"
    family: str = "apcg-plus"
    outputs: int = 2

    def __post_init__(self) -> None:
        if not isinstance(self.n_types, int) or self.n_types < 1:
            raise InputError(f"n_types must be an integer >= 1, got {self.n_types!r}")
        if not 0 < self.width <= 4:
            raise InputError(f"width must be in (0, 4], got {self.width}")
        k = math.log2(self.sheet / 4) if self.sheet >= 8 else -1
        if k != int(k) or not 1 <= k <= len(BASE_CHANNELS) - 1:
            top = 4 * 2 ** (len(BASE_CHANNELS) - 1)
            raise InputError(f"sheet must be 4 x 2^k with 1 <= k <= {len(BASE_CHANNELS) - 1} "
                             f"(8, 16, ... {top}), got {self.sheet}")
        if self.outputs not in (1, 2):
            raise InputError(f"outputs (the sheet's channels) must be 1 or 2, got "
                             f"{self.outputs!r}")
        if self.head not in HEADS:
            raise InputError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")

    @property
    def stages(self) -> int:
        return int(math.log2(self.sheet // 4))

    def channels(self) -> list[int]:
        """Feature channels from the 4 x 4 stem up to the last features (the sheet's
        resolution with the ``conv`` head, half of it with ``upconv``)."""
        base = BASE_CHANNELS[len(BASE_CHANNELS) - 1 - self.stages:]
        if self.head == "upconv":
            base = base[:-1]
        return [max(4, int(round(c * self.width))) for c in base]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PlusConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"an APCG+ network configuration has unknown settings {unknown}")
        return cls(**d)


def fourier_features(x: torch.Tensor, n: int) -> torch.Tensor:
    """x and sin / cos of 2^k pi x for k < n (x in [-1, 1])."""
    freqs = (2.0 ** torch.arange(n, dtype=x.dtype, device=x.device)) * math.pi
    ang = x[..., None] * freqs
    return torch.cat([x, torch.sin(ang).flatten(1), torch.cos(ang).flatten(1)], dim=1)


class PlusNet(nn.Module):
    def __init__(self, cfg: PlusConfig) -> None:
        super().__init__()
        self.cfg = cfg
        ch = cfg.channels()
        self.type_embedding = nn.Embedding(cfg.n_types, cfg.embed)
        # a free offset of the condition vector per type (zero at the start): what `apcg teach`
        # fits, with the type's embedding, to add a type to a trained network
        self.type_offset = nn.Embedding(cfg.n_types, cfg.hidden)
        nn.init.zeros_(self.type_offset.weight)
        cond_in = cfg.embed + POSE_DIM * (1 + 2 * cfg.fourier)
        self.cond = nn.Sequential(nn.Linear(cond_in, cfg.hidden), nn.SiLU(),
                                  nn.Linear(cfg.hidden, cfg.hidden), nn.SiLU())
        self.stem = nn.Linear(cfg.hidden, ch[0] * 16)
        self.ups = nn.ModuleList(nn.ConvTranspose2d(a, b, 4, 2, 1)
                                 for a, b in zip(ch[:-1], ch[1:], strict=True))
        self.films = nn.ModuleList(nn.Linear(cfg.hidden, 2 * b) for b in ch[1:]) \
            if cfg.film else None
        if self.films is not None:
            for f in self.films:  # every block starts as the identity modulation
                nn.init.zeros_(f.weight)
                nn.init.zeros_(f.bias)
        self.act = nn.SiLU()
        self.head = (nn.Conv2d(ch[-1], cfg.outputs, 3, padding=1) if cfg.head == "conv"
                     else nn.ConvTranspose2d(ch[-1], cfg.outputs, 4, 2, 1))

    def forward(self, type_code: torch.Tensor, pose: torch.Tensor,
                embedding: torch.Tensor | None = None,
                offset: torch.Tensor | None = None) -> torch.Tensor:
        """(N,) int64 type codes and (N, 5) scaled pose -> (N, outputs, S, S) sheets. ``embedding``
        and ``offset`` replace the weights of the type embedding and the type offset (``apcg
        teach`` fits one row of each)."""
        emb = (self.type_embedding(type_code) if embedding is None
               else nn.functional.embedding(type_code, embedding))
        off = (self.type_offset(type_code) if offset is None
               else nn.functional.embedding(type_code, offset))
        c = self.cond(torch.cat([emb, fourier_features(pose, self.cfg.fourier)], dim=1)) + off
        x = self.act(self.stem(c)).view(-1, self.stem.out_features // 16, 4, 4)
        for i, up in enumerate(self.ups):
            x = up(x)
            if self.films is not None:
                gamma, beta = self.films[i](c).chunk(2, dim=1)
                x = x * (1.0 + gamma[:, :, None, None]) + beta[:, :, None, None]
            x = self.act(x)
        return self.head(x)


# --- reading clouds off the sheets where the sheets are (a GPU): every box cell ----------------
def _diffused_keep(z: torch.Tensor, row_start: torch.Tensor, draw) -> torch.Tensor:
    """plus_draw.Draw.keep on the device: each cell's quanta (z: logit - tau) from the draw's
    table, the running sums of each row (beginning at index ``row_start``) in int64."""
    from apcg_core.families.plus_draw import STEPS_PER_LOGIT, stepped_up
    quanta = torch.tensor(draw.quanta, device=z.device)  # a copy: the table is read-only
    live = z > draw.span
    k = torch.where(live, torch.floor((z - draw.span) * STEPS_PER_LOGIT), torch.zeros_like(z))
    q = torch.where(live, quanta[k.clamp(0, len(quanta) - 1).long()], torch.zeros_like(k.long()))
    return stepped_up(q, row_start)


READ_CELLS = 2**25  # box cells read at once: bounds the reader's memory (~0.6 GB of float64)


def read_clouds(sheets: torch.Tensor, range_m, elevation, radius_m, box, lidar, tau: float,
                quantize: bool = True, draw=None):
    """The clouds of conditions (``range_m``, ``elevation``, ``radius_m``: numpy (N,); ``box``:
    their box_half_cells) read off their ``sheets`` (N, 2, S, S) on the sheets' device, as
    torch tensors (xyz (P, 3) and range (P,) float64; cell w, h and sample (P,) int64), in
    PlusModel.clouds_of's order.

    Every box cell (box_cells) is read as sample_sheets reads it (float64 bilinear, rows
    then columns): the same returns as the numpy reader, which reads fewer cells but is bound
    to the CPU; here the cells are read in place, so nothing but the points leaves the
    device. The box and the cells' angles are the numpy reader's own (box_half_cells, the
    lidar's cell centres), computed on the device in float64. ``draw``: the model's
    (apcg_core.families.plus_draw; None: the threshold), its quanta summed along each box row
    as integers, as the package's readers sum them."""
    dev = sheets.device
    f64 = torch.float64
    r0 = np.asarray(range_m, np.float64)
    b0 = np.asarray(elevation, np.float64)
    rad = np.asarray(radius_m, np.float64)
    w_half, h_half = box
    w_lo, w_hi, h_lo, h_hi = lidar.clip_box(w_half, h_half)
    nw, nh = w_hi - w_lo + 1, h_hi - h_lo + 1
    cells = nw * nh
    s = sheets.shape[-1]
    flat = sheets.reshape(sheets.shape[0], sheets.shape[1], s * s)
    out = []
    ends = np.cumsum(cells)
    start = 0
    while start < len(cells):  # conditions in groups of at most READ_CELLS box cells
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + READ_CELLS, side="right")))
        idx = slice(start, stop)
        n = torch.as_tensor(cells[idx], device=dev)
        first = torch.cumsum(n, 0) - n
        sample = torch.repeat_interleave(torch.arange(start, stop, device=dev), n)
        k = torch.arange(int(n.sum()), device=dev) - torch.repeat_interleave(first, n)
        t = {name: torch.as_tensor(a, device=dev)
             for name, a in (("r0", r0), ("b0", b0), ("rad", rad), ("w_lo", w_lo),
                             ("h_lo", h_lo), ("nw", nw))}
        nw_j = t["nw"][sample]
        w = t["w_lo"][sample] + k % nw_j
        h = t["h_lo"][sample] + torch.div(k, nw_j, rounding_mode="floor")
        r0_j, b0_j, rad_j = t["r0"][sample], t["b0"][sample], t["rad"][sample]
        u = r0_j * torch.cos(b0_j) * torch.tan(w.to(f64) * lidar.r_alpha) / rad_j
        v = r0_j * torch.tan(h.to(f64) * lidar.r_beta) / rad_j
        x = torch.clamp(((u + 1.0) * s - 1.0) / 2.0, 0.0, s - 1.0)
        y = torch.clamp(((1.0 - v) * s - 1.0) / 2.0, 0.0, s - 1.0)
        x0 = torch.clamp(torch.floor(x).long(), max=s - 2)
        y0 = torch.clamp(torch.floor(y).long(), max=s - 2)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]

        def at(yy, xx, sample=sample):
            return flat[sample, :, yy * s + xx].to(f64)

        read = ((at(y0, x0) * (1 - fy) + at(y0 + 1, x0) * fy) * (1 - fx)
                + (at(y0, x0 + 1) * (1 - fy) + at(y0 + 1, x0 + 1) * fy) * fx)
        if draw is None or not draw.diffused:
            keep = read[:, 0] > tau
        else:  # plus_draw.Draw.keep; a box row is nw consecutive cells here
            rel = sample - start
            row_start = first[rel] + (h - t["h_lo"][sample]) * nw_j
            keep = _diffused_keep(read[:, 0] - tau, row_start, draw)
        sample, w, h = sample[keep], w[keep], h[keep]
        r = r0_j[keep] + read[keep, 1] * rad_j[keep]
        if quantize:
            r = (torch.floor(r / lidar.r_r) + 0.5) * lidar.r_r
        alpha = w.to(f64) * lidar.r_alpha
        beta = h.to(f64) * lidar.r_beta + b0_j[keep]
        cb = torch.cos(beta)
        xyz = torch.stack([r * cb * torch.sin(alpha), r * torch.sin(beta),
                           r * cb * torch.cos(alpha)], dim=-1)
        out.append((xyz, r, w, h, sample))
        start = stop
    if not out:
        z = torch.zeros(0, dtype=torch.long, device=dev)
        return torch.zeros((0, 3), dtype=f64, device=dev), z.to(f64), z, z, z
    return tuple(torch.cat([o[i] for o in out]) for i in range(5))


__all__ = ["HEADS", "POSE_DIM", "PlusConfig", "PlusNet", "fourier_features", "read_clouds"]
