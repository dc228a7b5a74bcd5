"""APCG+ ("apcg-plus"): a generator that follows its condition, queried only where the lidar looks.

The paper's cGAN draws a whole 64 x 256 normalised image from noise and the condition, then
DeNorm and Im2PC (SPEC sections 5-6) turn it into a cloud. APCG+ keeps the condition -> image
idea and changes three things, each measured (docs/evaluation/plus/):

* **A sheet, not a window.** The network draws the target on a square *sheet* in the target's
  own scale: sheet coordinates (u, v) are the lateral and vertical offsets from the centre of
  mass divided by the type's bounding radius R, so every type at every range fills the sheet
  alike (Norm's purpose, without its block copies).
* **Only the box, at the lidar's own cells.** A cloud is read off the sheet at the centres of
  the cells that can see the target (those within R of the centre: the simulator's box),
  at their exact sheet coordinates (bilinear), not through DeNorm's nearest pixel. Far targets
  cost few reads.
* **Two outputs.** Channel 0 is the logit of "this cell has a return", channel 1 the range
  offset (r - r0) / R of that return. The returns are drawn from the logits by the model's
  ``draw`` (:mod:`apcg_core.families.plus_draw`): error diffusion of the calibrated
  probabilities logistic(logit - tau) along each box row (the default), or, for a model.json
  without one, where the logit is above ``tau``, the model's output threshold as Im2PC's tau is
  the cGAN's (0: probability one half; chosen on the validation half by `apcg choose-tau`);
  its range is quantised to the lidar's time bins as the standard data are.

This module is numpy (and onnxruntime to run the exported network), like the rest of the core;
the network itself is :mod:`apcg_core.nn.apcg_plus` (torch), used for training and for the torch
runtime; its training is ``training/families/apcg_plus.py``.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError, check_int
from ..frames import spherical_to_cartesian
from ..lidar import LidarParams
from . import plus_kernels
from .base import RUNTIMES, ModelTypes, onnx_session, onnx_weights, onnxruntime
from .plus_draw import draw_of

FAMILY = "apcg-plus"
CHUNK = 256  # conditions read at a time (a block of `apcg generate`): bounds memory (a sheet
# is 2 x S x S floats); blocks of 1024 made the 102,400-cloud generate slower (paired 1.05,
# docs/SCALE.md)
NET_ROWS = 32  # conditions per network call: the activations (~32 KB a condition) stay in a
# core's cache; the same network time as 256 a call within the runs' spread here
# (bench/generate_profile.py --chunks 32,256), 30 MiB less peak memory in a 2-lane generate,
# and the same sheets byte for byte at any count (tests/test_plus.py)


# --- sheet geometry (shared by training and generation: one definition) -------------------------
def box_half_cells(range_m, elevation, radius_m, lidar: LidarParams):
    """Half-extent (cells) of the box of cells that can see a sphere of radius R about the
    target's centre, in azimuth and elevation, +1 cell of margin (a cell sees the sphere when
    its centre ray passes within R of the centre)."""
    r0 = np.asarray(range_m, np.float64)
    rad = np.minimum(np.asarray(radius_m, np.float64), 0.999 * r0)
    ang = np.arcsin(rad / r0)
    cb = np.cos(np.asarray(elevation, np.float64))
    w_half = np.floor(ang / (lidar.r_alpha * cb) + 1.0).astype(np.int64)
    h_half = np.floor(ang / lidar.r_beta + 1.0).astype(np.int64)
    return w_half, h_half


def box_cells(range_m, elevation, radius_m, lidar: LidarParams):
    """Every box cell of each condition, clipped to the lidar's window: (sample, w, h) arrays."""
    w_half, h_half = box_half_cells(range_m, elevation, radius_m, lidar)
    w_lo, w_hi, h_lo, h_hi = lidar.clip_box(w_half, h_half)
    nw, nh = w_hi - w_lo + 1, h_hi - h_lo + 1
    n = nw * nh
    sample = np.repeat(np.arange(len(n)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)  # index within its box
    w = w_lo[sample] + k % nw[sample]
    h = h_lo[sample] + k // nw[sample]
    return sample, w, h


def sheet_coords(w, h, range_m, elevation, radius_m, lidar: LidarParams):
    """Sheet coordinates (u, v) of cells (w, h): lateral and vertical offsets of the cell's
    centre ray from the target's centre, at the target's range, in units of R."""
    r0 = np.asarray(range_m, np.float64)
    rad = np.asarray(radius_m, np.float64)
    u = r0 * np.cos(elevation) * np.tan(np.asarray(w, np.float64) * lidar.r_alpha) / rad
    v = r0 * np.tan(np.asarray(h, np.float64) * lidar.r_beta) / rad
    return u, v


def sample_sheets(sheets: np.ndarray, sample, u, v) -> np.ndarray:
    """Bilinear reads of ``sheets`` (N, C, S, S) at (u, v) for rows ``sample``: (len(u), C).

    The same sampling as torch's ``grid_sample(mode='bilinear', padding_mode='border',
    align_corners=False)`` with x = u and y = -v (row 0 is the top of the sheet, v = +1)."""
    s = sheets.shape[-1]
    x = np.clip(((np.asarray(u) + 1.0) * s - 1.0) / 2.0, 0.0, s - 1.0)
    y = np.clip(((1.0 - np.asarray(v)) * s - 1.0) / 2.0, 0.0, s - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), s - 2)
    y0 = np.minimum(np.floor(y).astype(np.int64), s - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    flat = sheets.reshape(sheets.shape[0], sheets.shape[1], s * s)

    def at(yy, xx):
        return flat[sample, :, yy * s + xx]

    # rows first, then columns: the order PlusModel's reader uses, so both round alike
    return ((at(y0, x0) * (1 - fy) + at(y0 + 1, x0) * fy) * (1 - fx)
            + (at(y0, x0 + 1) * (1 - fy) + at(y0 + 1, x0 + 1) * fy) * fx)


def _row_interval(r0, b0, radius_m, n, first, last, w_lo, w_hi, s, lidar: LidarParams):
    """The cells [start, stop] of box rows of conditions ``n`` whose interpolated hit channel
    is above tau in sheet columns first .. last only: the cells whose sheet x lies within one
    column of them, plus one cell each side (one definition for both readers)."""
    # sheet x of cell w is ((a tan(w Ra) + 1) s - 1) / 2, a = r0 cos(b0) / R: invert it
    a = r0[n] * np.cos(b0[n]) / radius_m[n]

    def w_at(x):
        return np.arctan(((2.0 * x + 1.0) / s - 1.0) / a) / lidar.r_alpha

    start = np.maximum(np.ceil(w_at(first - 1.0)).astype(np.int64) - 1, w_lo[n])
    stop = np.minimum(np.floor(w_at(last + 1.0)).astype(np.int64) + 1, w_hi[n])
    return start, stop


# --- the model ---------------------------------------------------------------------------------
@dataclass
class _Runtime:
    name: str
    session: object = None
    net: object = None


class PlusModel(ModelTypes):
    """An exported APCG+ model: model.json + sheets.onnx (inputs ``type_code`` (N,) int64 and
    ``pose`` (N, 5) float32, nu without its type column; output ``sheet`` (N, 2, S, S))."""

    TAUS = (-1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0)  # hit-logit thresholds choose-tau sweeps
    DEFAULT_TAU = 0.0
    ANY_LIDAR = True  # the sheet is drawn in the target's own scale, read at any lidar's cells
    SEEDED = False  # the standard data are a function of the condition, and so is this model

    @staticmethod
    def check_tau(tau) -> float:
        if not (isinstance(tau, (int, float, np.floating)) and np.isfinite(tau)):
            raise InputError(f"tau (the hit-logit threshold) must be a finite number, got "
                             f"{tau!r}")
        return float(tau)

    def __init__(self, directory, runtime: str = "auto") -> None:
        self._read_model_json(directory)
        self.onnx_path = self.directory / "sheets.onnx"
        if not self.onnx_path.is_file():
            raise InputError(f"{self.directory} is not an {FAMILY} model (no sheets.onnx; "
                             "`apcg export` makes one from a training run)")
        if runtime not in RUNTIMES:
            raise InputError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
        radius = [r.get("bounding_radius_m") for r in self.types.records]
        if any(r is None or not np.isfinite(r) or r <= 0 for r in radius):
            raise InputError(f"{self.directory / 'model.json'}: every type needs a "
                             "bounding_radius_m > 0 (an APCG+ model reads its box from it)")
        self.radius = np.asarray(radius, np.float64)
        self.tau = self.meta_tau()
        # how returns are drawn from the hit logits (plus_draw.py; none: the threshold)
        self.draw = draw_of(self.meta.get("draw"), f"{self.directory / 'model.json'}")
        self.quantize = self.meta_flag("quantize", True)
        # chunks generated side by side, each network call on one thread: measured fastest
        # here (bench/plus_speed.py); APCG_THREADS sets the count (1: one chunk at a time)
        self.workers = check_int("APCG_THREADS", int(os.environ.get(
            "APCG_THREADS", os.cpu_count() or 1)), 1)
        self.runtime = "onnx" if runtime == "auto" else runtime
        self._rt: _Runtime | None = None
        self._opening = threading.Lock()
        # the incidence output (training/families/plus_incidence.py): a second network the
        # photon stage reads each sub-ray's cosine of incidence from (SPEC section 8)
        self.incidence_path = self.directory / "incidence.onnx"
        has_file, has_record = self.incidence_path.is_file(), "incidence" in self.meta
        if has_file != has_record:
            raise InputError(f"{self.directory}: " + (
                "incidence.onnx is there but model.json does not say what it is (its "
                "'incidence' record); export it again with `apcg export`" if has_file else
                "model.json records an incidence network but incidence.onnx is missing"))
        self.draws_incidence = has_file
        self._incidence = {}  # its onnxruntime session, once opened (shared by shallow copies)

    # How `apcg generate` feeds this model (apcg_core/generation_cli.py): its clouds depend on
    # neither the seed nor how the conditions are cut into blocks, so a block is one network
    # call, and `workers` blocks are generated side by side while the previous ones are
    # written (bench/generate_profile.py measures the split).
    block_clouds = CHUNK

    @property
    def lanes(self) -> int:
        return self.workers

    def expect_clouds(self, n: int) -> None:
        # enough clouds to switch: the reader loads beside the first blocks, and makes its
        # first call there, on a probe with the argument types the blocks' calls will have
        plus_kernels.expect(n, warm=self._warm_reader)

    def _warm_reader(self, kernels) -> None:
        """The compiled reader on one probe condition (the middle of the condition space, type
        0) and a 4 x 4 sheet whose hit logits are all above the draw's floor: every kernel
        called once with the types of a real block's call (float32 sheets, as the network's)."""
        lo, hi = self.space.bounds(np.zeros((1, 6)))
        table = (lo + hi) / 2.0
        table[:, 0] = 0.0
        sheets = np.full((1, 2, 4, 4), self.tau + 1.0, np.float32)
        sheets[:, 1] = 0.0
        self._clouds_compiled(table, sheets, kernels)

    def _run(self, codes: np.ndarray, pose: np.ndarray) -> np.ndarray:
        if self._rt is None:
            with self._opening:  # blocks run in threads: one session, opened once
                if self._rt is None:
                    self._rt = self._open(self.runtime)
        if self._rt.name == "onnx":
            return self._rt.session.run(None, {"type_code": codes, "pose": pose})[0]
        import torch
        with torch.no_grad():
            return self._rt.net(torch.from_numpy(codes), torch.from_numpy(pose)).numpy()

    def _even_run(self, codes: np.ndarray, pose: np.ndarray, run=None) -> np.ndarray:
        """The network on an even number of rows (an odd batch gets a copy of its last row,
        whose sheet is dropped): onnxruntime's matrix products take a lone last row another
        way, so an odd batch's sheets differ in the last bits from the same conditions' in an
        even one; even, a condition's sheet is the same bytes in any batch (one condition
        alone, a block, a CSV of 10^6), so its cloud is too (tests/test_plus.py). ``run``: the
        network to run (default the model's own, :meth:`_run`)."""
        n = len(codes)
        if n % 2:
            codes, pose = np.append(codes, codes[-1:]), np.concatenate([pose, pose[-1:]])
        return (run or self._run)(codes, np.ascontiguousarray(pose))[:n]

    def _open(self, runtime: str) -> _Runtime:
        if runtime == "onnx":
            return _Runtime("onnx", session=self._onnx_session(self.onnx_path))
        return _Runtime("torch", net=self.torch_net().eval())

    def _onnx_session(self, path):
        ort = onnxruntime("generation needs onnxruntime: pip install onnxruntime "
                          "(or --runtime torch)")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1 if self.workers > 1 else 0  # 0: onnxruntime's own
        return onnx_session(path, opts)

    def torch_net(self):
        """A fresh torch network (apcg_core.nn.apcg_plus.PlusNet) holding this model's
        weights: what the torch runtime runs, distillation's teacher, fine-tuning's start."""
        import torch

        from ..nn.apcg_plus import PlusConfig, PlusNet
        net = PlusNet(PlusConfig.from_dict(self.meta["net"]))
        state = onnx_weights(self.onnx_path)
        own = net.state_dict()
        missing = [k for k in own if k not in state]
        if missing:
            raise InputError(f"{self.onnx_path} lacks weights {missing[:5]}")
        net.load_state_dict({k: torch.from_numpy(state[k]) for k in own})
        return net

    def sheets(self, table: np.ndarray, rows: int = NET_ROWS, run=None) -> np.ndarray:
        """The network's sheets (N, 2, S, S) for condition rows in this model's types,
        ``rows`` conditions a network call (the same sheets at any count); ``run``: another
        network on the same inputs (:meth:`_even_run`)."""
        nu = self.space.encode(table).astype(np.float32)
        codes = table[:, 0].astype(np.int64)
        out = [self._even_run(codes[s:s + rows], nu[s:s + rows, 1:], run)
               for s in range(0, len(table), rows)]
        return np.concatenate(out) if out else np.zeros((0, 2, 1, 1), np.float32)

    def incidence_of(self, table: np.ndarray, cloud: PointCloud) -> np.ndarray:
        """Each point's cosine of incidence (``cloud.sample`` indexing condition rows
        ``table``, its cells at this model's lidar): the logistic of the incidence network's
        sheet read at the cell's centre as the model's own sheet is (bilinear). The network
        runs on onnxruntime whatever this model's runtime, CHUNK conditions at a time (memory
        flat in the number of conditions), through :meth:`sheets` as the model's own does."""
        if not self.draws_incidence:
            raise InputError(f"{self.directory} has no incidence output (incidence.onnx); "
                             "`apcg train --family apcg-plus-incidence --init MODEL` makes one")
        with self._opening:
            if "session" not in self._incidence:
                self._incidence["session"] = self._onnx_session(self.incidence_path)
        session = self._incidence["session"]

        def run(codes, pose):
            return session.run(None, {"type_code": codes, "pose": pose})[0]

        out = np.zeros(len(cloud))
        if not len(cloud):
            return out
        sample = (np.zeros(len(cloud), np.int64) if cloud.sample is None
                  else np.asarray(cloud.sample, np.int64))
        order = np.argsort(sample, kind="stable")
        codes = table[:, 0].astype(np.int64)
        for lo in range(0, len(table), CHUNK):
            hi = min(lo + CHUNK, len(table))
            a, b = np.searchsorted(sample[order], [lo, hi])
            if a == b:
                continue
            pts = order[a:b]
            sm = sample[pts]
            u, v = sheet_coords(cloud.cell_w[pts], cloud.cell_h[pts], table[sm, 1],
                                table[sm, 2], self.radius[codes[sm]], self.lidar)
            sheets = self.sheets(table[lo:hi], run=run).astype(np.float64)
            out[pts] = 1.0 / (1.0 + np.exp(-sample_sheets(sheets, sm - lo, u, v)[:, 0]))
        return out

    def clouds_of(self, table: np.ndarray, sheets: np.ndarray,
                  compiled: bool | None = None) -> PointCloud:
        """Read the clouds of conditions ``table`` off their ``sheets`` (one stacked cloud):
        the same returns as reading every box cell with :func:`sample_sheets`, found faster.

        The bilinear read is separable (u depends on w alone, v on h alone), so each box row
        h is first interpolated between two sheet rows; a cell can then exceed the draw's row
        floor (tau, or tau + span) only where one of the two sheet columns it lies between
        does, which bounds each row's cells to one interval of w. Only those cells are read
        (a few more than the returns); the draw counts every cell outside them as p = 0.

        ``compiled`` (default: :func:`plus_kernels.use_for` these clouds) reads them in the
        compiled loops of :mod:`apcg_core.families.plus_kernels`, the same bytes; float32 or
        float64 sheets and a float64 table (the others: numpy)."""
        if compiled is None:
            compiled = plus_kernels.use_for(len(table))
        if (compiled and table.dtype == np.float64
                and sheets.dtype in (np.float32, np.float64)):
            return self._clouds_compiled(table, sheets)
        sample, w, h, read = self.box_reads(table, sheets, self.draw.row_floor(self.tau))
        keep = self.draw.keep(sample, h, read[:, 0], self.tau)
        return self.cloud_of_cells(table, sample[keep], w[keep], h[keep], read[keep, 1])

    def box_reads(self, table: np.ndarray, sheets: np.ndarray, span_tau: float):
        """Every box cell of each live row (a row with a sheet column whose hit read exceeds
        ``span_tau``) within the interval those columns bound, as (sample, w, h, the cell's
        (hit logit, range offset) read off the sheet): the numpy reader's cells, which it
        draws from (the model's ``draw``: plus_draw.py)."""
        lidar = self.lidar
        codes = table[:, 0].astype(np.int64)
        r0, b0, rad = table[:, 1], table[:, 2], self.radius[codes]
        s = sheets.shape[-1]
        w_half, h_half = box_half_cells(r0, b0, rad, lidar)
        w_lo, w_hi, h_lo, h_hi = lidar.clip_box(w_half, h_half)
        nh = h_hi - h_lo + 1
        row_n = np.repeat(np.arange(len(table)), nh)
        h = h_lo[row_n] + np.arange(nh.sum()) - np.repeat(np.cumsum(nh) - nh, nh)
        _, v = sheet_coords(0, h, r0[row_n], b0[row_n], rad[row_n], lidar)
        y = np.clip(((1.0 - v) * s - 1.0) / 2.0, 0.0, s - 1.0)
        y0 = np.minimum(np.floor(y).astype(np.int64), s - 2)
        fy = (y - y0)[:, None, None]
        rows = sheets[row_n, :, y0, :] * (1 - fy) + sheets[row_n, :, y0 + 1, :] * fy  # (R,C,S)
        active = rows[:, 0, :] > span_tau
        live = np.flatnonzero(active.any(axis=1))
        first = np.argmax(active[live], axis=1)
        last = s - 1 - np.argmax(active[live, ::-1], axis=1)
        n = row_n[live]
        start, stop = _row_interval(r0, b0, rad, n, first, last, w_lo, w_hi, s, lidar)
        count = np.maximum(stop - start + 1, 0)
        cell_row = np.repeat(live, count)
        w = np.repeat(start, count) + np.arange(count.sum()) - np.repeat(
            np.cumsum(count) - count, count)
        sample = row_n[cell_row]
        u, _ = sheet_coords(w, 0, r0[sample], b0[sample], rad[sample], lidar)
        x = np.clip(((u + 1.0) * s - 1.0) / 2.0, 0.0, s - 1.0)
        x0 = np.minimum(np.floor(x).astype(np.int64), s - 2)
        fx = (x - x0)[:, None]
        read = rows[cell_row, :, x0] * (1 - fx) + rows[cell_row, :, x0 + 1] * fx
        return sample, w, h[cell_row], read

    def cloud_of_cells(self, table: np.ndarray, sample, w, h, offset) -> PointCloud:
        """The points of the kept cells (sample, w, h) at their range offsets (read off the
        sheet, in units of the type's radius)."""
        codes = table[:, 0].astype(np.int64)
        r0, b0, rad = table[:, 1], table[:, 2], self.radius[codes]
        r = r0[sample] + offset.astype(np.float64) * rad[sample]
        if self.quantize:
            r = self.lidar.quantize_range(r)
        alpha, beta = self.lidar.cell_centre_angles(w, h, b0[sample])
        return PointCloud(spherical_to_cartesian(alpha, beta, r), r, w, h, sample)

    def _clouds_compiled(self, table: np.ndarray, sheets: np.ndarray,
                         kernels=None) -> PointCloud:
        """:meth:`clouds_of` in two compiled passes (plus_kernels.row_spans: the box rows'
        places and the columns above tau; plus_kernels.read_rows: the cells, ranges and
        points), every tan, arctan, sin and cos in numpy on the numpy reader's arguments
        (tables of the window's angles; the live rows' intervals and elevations).
        ``kernels``: the compiled set (default: loaded now)."""
        k = kernels or plus_kernels.require()
        lidar = self.lidar
        codes = table[:, 0].astype(np.int64)
        rad = self.radius[codes]
        w_half, h_half = box_half_cells(table[:, 1], table[:, 2], rad, lidar)  # as numpy's
        w_lo, w_hi, h_lo, h_hi = lidar.clip_box(w_half, h_half)
        r0 = np.ascontiguousarray(table[:, 1])
        b0 = np.ascontiguousarray(table[:, 2])
        sheets = np.ascontiguousarray(sheets)
        s = sheets.shape[-1]
        tan_a, sin_a, cos_a, tan_b = plus_kernels.angle_tables(lidar)
        n, h, y0, fy, first, last = k.row_spans(sheets, h_lo, h_hi - h_lo + 1, r0, rad, tan_b,
                                                lidar.h_min, self.draw.row_floor(self.tau))
        start, stop = _row_interval(r0, b0, rad, n, first, last, w_lo, w_hi, s, lidar)
        beta = h.astype(np.float64) * lidar.r_beta + b0[n]  # cell_centre_angles' beta
        xyz, r, w, h, sample = k.read_rows(
            sheets, n, h, y0, fy, start, stop, np.cos(beta), np.sin(beta), r0, rad,
            r0 * np.cos(b0), tan_a, sin_a, cos_a, lidar.w_min, self.tau, self.quantize,
            lidar.r_r, self.draw.quanta, float(self.draw.span or 0.0))
        return PointCloud(xyz, r, w, h, sample)

    def generate(self, conditions, count: int = 1, seed: int = 0):
        """Point clouds for ``conditions`` (mapped by type name into this model's types),
        ``count`` per condition. The standard data are a function of the condition, and so is
        this model: ``seed`` is accepted for the common interface and changes nothing."""
        table = self.repeated_conditions(conditions, count)

        def chunk(s):
            part = table[s:s + CHUNK]
            c = self.clouds_of(part, self.sheets(part))
            if s:
                c.sample += s  # the reader's own array
            return c

        starts = range(0, len(table), CHUNK)
        if self.workers > 1 and len(starts) > 1:
            # onnxruntime gains little from a second thread on this small network, and the
            # reader is numpy or plus_kernels: chunks side by side keep every core busy (all
            # release the GIL)
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(self.workers) as pool:
                clouds = list(pool.map(chunk, starts))
        else:
            clouds = [chunk(s) for s in starts]
        if len(clouds) == 1:  # a block of one chunk (how `apcg generate` asks): no copy
            cloud = clouds[0]
        else:
            cloud = (PointCloud(*(np.concatenate([getattr(c, k) for c in clouds])
                                  for k in ("xyz", "range_m", "cell_w", "cell_h", "sample")))
                     if clouds else PointCloud(np.zeros((0, 3)), [], [], [],
                                               np.zeros(0, np.int64)))
        return self.result(cloud, np.zeros((0, self.lidar.height, self.lidar.width),
                                           np.float32), table)


class _PlusLoader:
    """APCG+ as the core knows it: its loader (training adds the rest:
    training/families/apcg_plus.py)."""

    name = FAMILY

    @staticmethod
    def load(directory, runtime: str = "auto"):
        return PlusModel(Path(directory), runtime=runtime)


LOADER = _PlusLoader()

__all__ = ["FAMILY", "LOADER", "PlusModel", "box_cells", "box_half_cells", "sample_sheets",
           "sheet_coords"]
