"""Compiled loops for the photon stage (numba), beside the numpy code they replace.

The batched points path (``stage.signal_bins``, ``points._loud_peaks``) spends its time in a
few loops that numpy runs as many passes over large arrays: spreading every sub-ray's return
over the bins its Gaussian reaches and adding them up per (cell, bin), the sums of a cell's
earlier pieces, the walk of the binomial sampler's inverse CDF and the bisection that places
each fired pulse in its cell's pieces. Here each is one pass. Every float64 operation is the
numpy code's, operand for operand and in the same order: products, quotients and sums of two
operands only, each rounded (numba contracts nothing into a fused multiply-add without
``fastmath``, which is never set here), and every exp, log, expm1 or log1p stays in numpy,
computed before or between the loops on the same values (a compiled ``exp`` need not be the
one numpy calls). ``tests/test_photon_kernels.py`` checks that both paths give the same bytes.

The core imports with numpy alone (the add-on runs in Blender's Python, which has no numba):
numba is imported only inside :func:`_load`, when it is installed and allowed, and the numpy
code runs otherwise, same bytes, slower. ``APCG_KERNELS`` in the environment is read as for
the build's ray kernels (``dataset_builder/kernels.py``): ``numpy`` never loads them,
``compiled`` loads them at the first call; otherwise a process starts on numpy and loads them
once it has put :data:`SWITCH_HITS` sub-ray hits through the stage. Compiled code is cached
beside this file (``__pycache__``; numba's per-user cache where that is read-only).
"""

from __future__ import annotations

import importlib.util
import os

import numpy as np

ENV = "APCG_KERNELS"  # "numpy": never use the compiled kernels; "compiled": from the start
# Sub-ray hits a process puts through the stage on the numpy path before it loads the
# kernels: loading numba and reading the cache costs about 0.5 s (dataset_builder/kernels.py),
# and the numpy path's extra cost over the kernels is about 2.5 us a hit (bench/photons.py,
# docs/SCALE.md "The photon stage"), so after ~200 000 hits the numpy path has spent what
# loading costs (rent, then buy). One `apcg simulate` of a few conditions never loads them.
SWITCH_HITS = 200_000

_kernels = None  # the compiled functions, once loaded; False when numba is missing
_numpy_hits = 0  # hits this process put through the numpy path while the kernels were not loaded


def _mode() -> str:
    return os.environ.get(ENV, "").strip().lower()


def enabled() -> bool:
    """Whether this process may use the compiled kernels (numba installed, not turned off)."""
    if _mode() == "numpy":
        return False
    if _kernels is None:
        return importlib.util.find_spec("numba") is not None
    return _kernels is not False


def loaded() -> bool:
    return _kernels is not None and _kernels is not False


def use_for(n_hits: int) -> bool:
    """Whether a stage call on ``n_hits`` sub-ray hits should take the compiled path (loading
    the kernels if it is time to); counts the hits toward :data:`SWITCH_HITS` when not."""
    global _numpy_hits
    if not enabled():
        return False
    if loaded():
        return True
    if _mode() == "compiled" or _numpy_hits + n_hits >= SWITCH_HITS:
        return _load() is not False
    _numpy_hits += n_hits
    return False


def _load():
    global _kernels
    if _kernels is None:
        try:
            import numba  # noqa: F401
        except ImportError:
            _kernels = False
        else:
            _kernels = _compile()
    return _kernels


def require():
    """The compiled kernels, loaded (numba must be importable)."""
    k = _load()
    if k is False:
        raise ImportError("the photon stage's compiled kernels need numba: "
                          "pip install 'apcg[sim]'")
    return k


class _Kernels:
    def __init__(self, **fns) -> None:
        self.__dict__.update(fns)


def _compile() -> _Kernels:
    from numba import njit

    jit = njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)

    @jit
    def spread_sum(cell, lo, row, mean, weights, n_bins):
        """stage.signal_bins' spread and sum: hit i's mean times weights[row[i], j] in bin
        lo[i] + j, kept when the bin is in the gate and the product is > 0, then added up
        per (cell, bin) in the order of the hits and of j (as numpy's bincount adds its
        entries). ``cell`` sorted. Returns (cell, bin, total) of the slots with total > 0,
        by cell then bin."""
        n = cell.shape[0]
        nb = weights.shape[1]
        cap = 0
        # the widest run of bins one cell reaches, for the scratch buffer
        i = 0
        while i < n:
            j = i
            b_lo = lo[i]
            b_hi = lo[i]
            while j < n and cell[j] == cell[i]:
                if lo[j] < b_lo:
                    b_lo = lo[j]
                if lo[j] > b_hi:
                    b_hi = lo[j]
                j += 1
            if b_hi - b_lo + nb > cap:
                cap = b_hi - b_lo + nb
            i = j
        buf = np.zeros(cap)
        used = np.zeros(cap, np.bool_)
        out_cell = np.empty(n * nb, np.int64)
        out_bin = np.empty(n * nb, np.int64)
        out_total = np.empty(n * nb)
        m_out = 0
        i = 0
        while i < n:
            c = cell[i]
            j = i
            while j < n and cell[j] == c:
                j += 1
            # the cell's kept entries: their lowest and highest bin
            first = n_bins
            last = -1
            for h in range(i, j):
                for t in range(nb):
                    b = lo[h] + t
                    if b >= 0 and b < n_bins and mean[h] * weights[row[h], t] > 0:
                        if b < first:
                            first = b
                        if b > last:
                            last = b
            if last >= 0:
                for h in range(i, j):
                    for t in range(nb):
                        b = lo[h] + t
                        m = mean[h] * weights[row[h], t]
                        if b >= 0 and b < n_bins and m > 0:
                            buf[b - first] += m
                            used[b - first] = True
                for s in range(last - first + 1):
                    if used[s]:
                        if buf[s] > 0:
                            out_cell[m_out] = c
                            out_bin[m_out] = first + s
                            out_total[m_out] = buf[s]
                            m_out += 1
                        buf[s] = 0.0
                        used[s] = False
            i = j
        return out_cell[:m_out], out_bin[:m_out], out_total[:m_out]

    @jit
    def sum_before(values, heads, counts):
        """points._sum_before: per piece, the sum of its cell's earlier pieces' values, added
        in their order (cells are runs heads[c] .. heads[c] + counts[c] - 1)."""
        out = np.zeros(values.shape[0])
        for c in range(heads.shape[0]):
            h = heads[c]
            for i in range(h + 1, h + counts[c]):
                out[i] = out[i - 1] + values[i - 1]
        return out

    @jit
    def binomial_walk(nn, ratio, uu, pk, cdf, k):
        """draws.binomial_inverse's walk up the CDF, element by element, in place: while the
        uniform is above the CDF and k < n, k += 1 and pk *= (n - k + 1) / k * ratio."""
        for i in range(nn.shape[0]):
            n = nn[i]
            kk = k[i]
            p = pk[i]
            c = cdf[i]
            r = ratio[i]
            u = uu[i]
            while u > c and kk < n:
                kk += 1
                p *= np.float64(n - kk + 1) / np.float64(kk) * r
                c += p
            k[i] = kk
            pk[i] = p
            cdf[i] = c

    @jit
    def bisect_right(keys, lo, hi, x):
        """detector._bisect(right=True): per query, searchsorted(keys[lo:hi], x, 'right') + lo."""
        out = np.empty(lo.shape[0], np.int64)
        for q in range(lo.shape[0]):
            a = lo[q]
            b = hi[q]
            v = x[q]
            while a < b:
                mid = (a + b) // 2
                if keys[mid] <= v:
                    a = mid + 1
                else:
                    b = mid
            out[q] = a
        return out

    return _Kernels(spread_sum=spread_sum, sum_before=sum_before, binomial_walk=binomial_walk,
                    bisect_right=bisect_right)
