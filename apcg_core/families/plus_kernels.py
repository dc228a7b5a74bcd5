"""Compiled loops for the APCG+ reader (numba), beside the numpy code they replace.

``PlusModel.clouds_of`` reads a chunk's clouds off the network's sheets in ~40 numpy passes
over arrays of box rows, read cells and points, most of them fancy-indexed copies (the
interpolated rows alone are 2 x S float64 per box row). Here the work between the
transcendental functions is two passes: ``row_spans`` interpolates each box row's hit
channel between its two sheet rows and finds the sheet columns above tau, and
``read_rows`` reads the cells of each live row's interval, keeps those above tau, and
writes their quantised ranges and points. Every float64 operation is the numpy code's, operand
for operand and in the same order: float32 sheet values widened to float64 before they are
multiplied (numpy's float32 * float64 -> float64), products, quotients and sums of two
operands only, each rounded (numba contracts nothing into a fused multiply-add without
``fastmath``, which is never set here), floor exact. Every tan, arctan, sin and cos
stays in numpy on the same float64 arguments (a compiled ``tan`` need not be the one numpy
calls): the tangents, sines and cosines of the cells' angles come from tables of the lidar's
window computed by numpy (:func:`angle_tables`), the arctan of each live row's interval and
the sine and cosine of its elevation between the two passes, each on a contiguous array as
the numpy reader's are (numpy may take another routine for a strided one).
``tests/test_plus_kernels.py`` checks that both paths give the same bytes.

The core imports with numpy alone (the add-on runs in Blender's Python, which has no numba):
numba is imported only when the kernels load (``apcg_core/kernel_loader.py``, the loader the
photon stage's kernels use), and the numpy code runs otherwise, same bytes, slower.
``APCG_KERNELS`` in the environment is read as there: ``numpy`` never loads them,
``compiled`` loads them at the first call; otherwise a process starts on numpy and loads them
once it has read :data:`SWITCH_CLOUDS` clouds. Compiled code is cached beside this file
(``__pycache__``; numba's per-user cache where that is read-only).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..kernel_loader import ENV, KernelSet, Loader
from .plus_draw import HALF, ONE, STEPS_PER_LOGIT

__all__ = ["ENV", "SWITCH_CLOUDS", "angle_tables", "enabled", "expect", "loaded", "require",
           "use_for"]
# Clouds a process reads on the numpy path before it loads the kernels. Measured here (2 CPUs,
# bench/generate_profile.py --conditions data/cpu/conditions.csv --n 8192 --chunks 1024, the
# shipped model, one thread, APCG_KERNELS=numpy then =compiled in one session): the numpy
# reader 0.058-0.065 ms of CPU a cloud, the compiled one 0.011-0.012 ms, ~0.048 ms saved a
# cloud; loading in a fresh process (numba's import, 0.35 s, and the cached kernels) 0.44 s
# of CPU, what the numpy path spends over the kernels in ~9 000 clouds (rent, then buy).
# 8 192 is 32 of the reader's CHUNK-cloud calls: `apcg generate` of a few thousand conditions
# never loads numba; a larger request says so up front (expect, through Model.expect_clouds)
# and loads it on its own thread beside its first chunks. (Without the cache,
# the first process after this file changes compiles them, ~1.8 s once.)
SWITCH_CLOUDS = 8_192


# the one loader of this set (apcg_core/kernel_loader.py); _compile is defined below
_loader = Loader(lambda: _compile(), "the APCG+ reader's compiled kernels", SWITCH_CLOUDS)
enabled, loaded, use_for, require, expect = (_loader.enabled, _loader.loaded,
                                             _loader.use_for, _loader.require, _loader.expect)


@lru_cache(maxsize=16)
def angle_tables(lidar):
    """numpy's tan(w r_alpha), sin(w r_alpha), cos(w r_alpha) for every w of ``lidar``'s
    window (index w - w_min) and tan(h r_beta) for every h (index h - h_min): the values
    ``sheet_coords`` and ``spherical_to_cartesian`` compute per cell, from the same float64
    arguments (w and h as float64 times the resolution)."""
    alpha = np.arange(lidar.w_min, lidar.width // 2, dtype=np.int64).astype(np.float64) \
        * lidar.r_alpha
    beta = np.arange(lidar.h_min, lidar.height // 2, dtype=np.int64).astype(np.float64) \
        * lidar.r_beta
    out = np.tan(alpha), np.sin(alpha), np.cos(alpha), np.tan(beta)
    for a in out:
        a.flags.writeable = False
    return out


def _compile() -> KernelSet:
    from numba import njit

    jit = njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)

    # Each kernel is whole: one that called another compiled function through the closure
    # would miss numba's cache in every new process (its key pickles the closure's cells,
    # which differ from process to process) and compile again (~1.5 s).

    @jit
    def row_spans(sheets, h_lo, nh, r0, rad, tan_b, h_min, tau):
        """Each box row's place on its sheet and the sheet columns of its hit channel above
        ``tau``: for cloud n and rows h = h_lo[n] .. h_lo[n] + nh[n] - 1, v = r0 tan(h r_beta)
        / R, the sheet row pair y0 = min(floor(y), s - 2) and weight fy = y - y0 of
        y = clip(((1 - v) s - 1) / 2, 0, s - 1), and the row read between them,
        sheet[y0] (1 - fy) + sheet[y0 + 1] fy (float32 widened to float64 first, as numpy's
        float32 * float64); of the rows with a column above tau, in order (cloud, h): cloud,
        h, y0, fy, and the first and last such column."""
        s = sheets.shape[3]
        top = np.float64(s) - 1.0
        cap = 0
        for n in range(nh.shape[0]):
            if nh[n] > 0:
                cap += nh[n]
        o_n = np.empty(cap, np.int64)
        o_h = np.empty(cap, np.int64)
        o_y0 = np.empty(cap, np.int64)
        o_fy = np.empty(cap)
        o_first = np.empty(cap, np.int64)
        o_last = np.empty(cap, np.int64)
        row = np.empty(s)
        m = 0
        for n in range(nh.shape[0]):
            for k in range(nh[n]):
                h = h_lo[n] + k
                v = r0[n] * tan_b[h - h_min] / rad[n]
                y = ((1.0 - v) * np.float64(s) - 1.0) / 2.0
                if y < 0.0:
                    y = 0.0
                if y > top:
                    y = top
                y0 = np.int64(np.floor(y))
                if y0 > s - 2:
                    y0 = s - 2
                fy = y - np.float64(y0)
                gy = 1.0 - fy
                for x in range(s):
                    row[x] = (np.float64(sheets[n, 0, y0, x]) * gy
                              + np.float64(sheets[n, 0, y0 + 1, x]) * fy)
                first = 0
                while first < s and not (row[first] > tau):
                    first += 1
                if first == s:
                    continue
                last = s - 1
                while not (row[last] > tau):
                    last -= 1
                o_n[m] = n
                o_h[m] = h
                o_y0[m] = y0
                o_fy[m] = fy
                o_first[m] = first
                o_last[m] = last
                m += 1
        return o_n[:m], o_h[:m], o_y0[:m], o_fy[:m], o_first[:m], o_last[:m]

    @jit
    def read_rows(sheets, row_n, row_h, row_y0, row_fy, start, stop, cos_beta, sin_beta,
                  r0, rad, r0cb, tan_a, sin_a, cos_a, w_min, tau, quantize, r_r, quanta, span):
        """The cells w = start .. stop of each live row (``row_spans``' rows, intervals from
        numpy's arctan): u = r0 cos(b0) tan(w r_alpha) / R, the sheet column pair
        x0 = min(floor(x), s - 2) and weight fx = x - x0 of x = clip(((u + 1) s - 1) / 2, 0,
        s - 1), and each channel read as row[x0] (1 - fx) + row[x0 + 1] fx of the row's
        values (as row_spans interpolates them); a cell is kept where its hit read is above
        ``tau`` (``quanta`` empty: the threshold draw) or, for the diffused draw
        (plus_draw.Draw.keep), where the row's running sum of the cells' ``quanta`` entries,
        rounded, steps up (entry floor((read - tau - span) STEPS_PER_LOGIT), none where
        read - tau <= span; integer sums, the numpy draw's to the quantum). Its range
        r0 + offset R (quantised to the bin centres when ``quantize``) and its point
        (r cos(beta) sin(alpha), r sin(beta), r cos(beta) cos(alpha)), cos(beta) and
        sin(beta) the row's. Returns xyz, range, w, h, sample, in the numpy reader's order."""
        s = sheets.shape[3]
        top = np.float64(s) - 1.0
        cap = 0
        for i in range(start.shape[0]):
            if stop[i] >= start[i]:
                cap += stop[i] - start[i] + 1
        xyz = np.empty((cap, 3))
        rr = np.empty(cap)
        ow = np.empty(cap, np.int32)
        oh = np.empty(cap, np.int32)
        osample = np.empty(cap, np.int64)
        hit = np.empty(s)
        off = np.empty(s)
        diffused = quanta.shape[0] > 0
        top_k = quanta.shape[0] - 1
        steps = np.float64(STEPS_PER_LOGIT)
        # a cell's sheet column pair and weight depend on its cloud and w only: computed once
        # a cloud for the union of its rows' intervals (rows of a cloud are consecutive)
        col_x0 = np.empty(tan_a.shape[0], np.int64)
        col_fx = np.empty(tan_a.shape[0])
        m = 0
        cloud = -1
        for i in range(start.shape[0]):
            total = 0  # the row's running sum of quanta, and the returns it has kept
            kept = 0
            n = row_n[i]
            if n != cloud:
                cloud = n
                lo = start[i]
                hi = stop[i]
                j = i + 1
                while j < start.shape[0] and row_n[j] == n:
                    if start[j] < lo:
                        lo = start[j]
                    if stop[j] > hi:
                        hi = stop[j]
                    j += 1
                for w in range(lo, hi + 1):
                    u = r0cb[n] * tan_a[w - w_min] / rad[n]
                    x = ((u + 1.0) * np.float64(s) - 1.0) / 2.0
                    if x < 0.0:
                        x = 0.0
                    if x > top:
                        x = top
                    x0 = np.int64(np.floor(x))
                    if x0 > s - 2:
                        x0 = s - 2
                    col_x0[w - w_min] = x0
                    col_fx[w - w_min] = x - np.float64(x0)
            y0 = row_y0[i]
            fy = row_fy[i]
            gy = 1.0 - fy
            for x in range(s):
                hit[x] = (np.float64(sheets[n, 0, y0, x]) * gy
                          + np.float64(sheets[n, 0, y0 + 1, x]) * fy)
                off[x] = (np.float64(sheets[n, 1, y0, x]) * gy
                          + np.float64(sheets[n, 1, y0 + 1, x]) * fy)
            for w in range(start[i], stop[i] + 1):
                x0 = col_x0[w - w_min]
                fx = col_fx[w - w_min]
                gx = 1.0 - fx
                read = hit[x0] * gx + hit[x0 + 1] * fx
                if diffused:
                    z = read - tau
                    if not (z > span):
                        continue
                    kf = np.floor((z - span) * steps)
                    total += quanta[top_k if kf > top_k else np.int64(kf)]
                    now = (total + HALF) // ONE
                    if now <= kept:
                        continue
                    kept = now
                elif not (read > tau):
                    continue
                r = r0[n] + (off[x0] * gx + off[x0 + 1] * fx) * rad[n]
                if quantize:
                    r = (np.floor(r / r_r) + 0.5) * r_r
                rcb = r * cos_beta[i]
                xyz[m, 0] = rcb * sin_a[w - w_min]
                xyz[m, 1] = r * sin_beta[i]
                xyz[m, 2] = rcb * cos_a[w - w_min]
                rr[m] = r
                ow[m] = w
                oh[m] = row_h[i]
                osample[m] = n
                m += 1
        return xyz[:m], rr[:m], ow[:m], oh[:m], osample[:m]

    return KernelSet(row_spans=row_spans, read_rows=read_rows)

