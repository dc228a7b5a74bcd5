"""The photon stage (SPEC section 8): from the geometry the simulator found (every sub-ray's
range and incidence) to what a single-photon lidar records. One function, :func:`photon_cloud`,
that simulate, the dataset builder and the add-on call the same way; numpy only.

Randomness: each sample draws from its own generator, ``numpy.random.default_rng([seed,
sample_id])``, so a sample's photons do not depend on which batch, worker or engine made it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError, check_int
from ..frames import spherical_to_cartesian
from ..lidar import LidarParams
from . import kernels
from .detector import SignalBins, detect, detect_points, signal_work, work_per_window
from .link import (
    LIGHT_M_S,
    bin_seconds,
    noise_per_bin,
    normal_cdf,
    range_sigma_m,
    signal_photoelectrons,
)
from .params import SensorParams, check_gate
from .points import batch_points

# A return's Gaussian is cut this many sigmas either side (the mass beyond is ~1e-7, the
# accuracy of the table below).
SIGMA_CUT = 5.3
# Rows of the spread table: the fraction of a bin at which a return's window starts, in steps
# of 1 / SPREAD_ROWS.
SPREAD_ROWS = 4096


# The most range bins one return's Gaussian may reach at once (the spread table is
# (SPREAD_ROWS + 1) x that many float64: 134 MB, and a few times that while it is made).
MAX_SPREAD_BINS = 4096
# The most detector arrivals one cloud's draws may follow (the detector's own cost model:
# detector.work_per_window for the noise of the window, detector.signal_work for the signal
# and its (sub-ray, bin) terms): about 60 bytes each at the peak, so about 1.2 GB. The
# presets at the paper's lidar need 5e3 to 1.2e6 for the noise, 1.5e5 to 4.5e5 for the signal.
MAX_WORK_PER_CLOUD = 2e7
# The sensor values a cloud's cost follows, named wherever too much is refused (and what a
# MemoryError's advice should name).
COST_SETTINGS = ("pulses, dead_time_ns, pulse_energy_j (the signal), gate_m, background_hz, "
                 "dark_count_hz")


def check_work(sensor: SensorParams, lidar: LidarParams, n_bins: int,
               signal: np.ndarray | None = None) -> None:
    """The one check of a cloud's draws against MAX_WORK_PER_CLOUD: the noise of the W x H
    window (``detector.work_per_window``) plus, once the rays are cast and before anything is
    drawn, ``signal``: each sample's signal work (``detector.signal_work``). A named error,
    not a MemoryError after minutes."""
    dead_bins = sensor.dead_time_ns * 1e-9 / bin_seconds(lidar.r_r)
    noise = work_per_window(lidar.width * lidar.height, n_bins,
                            noise_per_bin(sensor, lidar.r_r), dead_bins, sensor.pulses,
                            sensor.threshold, sensor.output == "points")
    sig = float(np.max(signal)) if signal is not None and len(signal) else 0.0
    if noise + sig <= MAX_WORK_PER_CLOUD:
        return
    raise InputError(
        f"sensor {sensor.name!r} at the lidar ({lidar.describe()}): one cloud would draw "
        f"about {noise + sig:.3g} detector arrivals (noise {noise:.3g}: the window's "
        f"{lidar.width} x {lidar.height} cells x pulses = {sensor.pulses} x the noise in a "
        f"gate of {n_bins} bins, gate_m = {sensor.gate_m!r}, background_hz + dark_count_hz = "
        f"{sensor.noise_hz:.4g}; signal {sig:.3g}: the cells the target lights x pulses x "
        f"the events a pulse, pulse_energy_j = {sensor.pulse_energy_j!r}, cells_per_pulse = "
        f"{sensor.cells_per_pulse}; dead_time_ns = {sensor.dead_time_ns!r}, output = "
        f"{sensor.output}); accepted: at most {MAX_WORK_PER_CLOUD:.3g}. Lower one of "
        f"{COST_SETTINGS}, make dead_time_ns at least the gate (one event a pulse), or use a "
        "smaller window")


@lru_cache(maxsize=64)  # every batch of a build asks again; the answer is the pair's
def check_sensor_at(sensor: SensorParams, lidar: LidarParams) -> int:
    """The range gate's bins of ``sensor`` at ``lidar``, once their pairing is checked: a gate
    of at least one bin, a threshold the pulses can reach, a return's spread, and a cloud's
    noise draws that fit in memory (``check_work``: a named error before anything is drawn,
    not a MemoryError after minutes; its signal part follows in ``photon_cloud`` once the
    rays are cast, before any draw)."""
    n_bins = check_gate(sensor, lidar.r_r)
    dead_bins = sensor.dead_time_ns * 1e-9 / bin_seconds(lidar.r_r)
    where = f"sensor {sensor.name!r} at the lidar ({lidar.describe()})"
    if sensor.output == "points" and dead_bins >= 1.0 and sensor.threshold > sensor.pulses:
        raise InputError(
            f"{where}: threshold = {sensor.threshold} is more than pulses = {sensor.pulses}: "
            f"with a dead time of at least one range bin (dead_time_ns = "
            f"{sensor.dead_time_ns!r}) a pulse counts at most once in a bin, so no bin could "
            f"ever reach the threshold; accepted: threshold <= pulses")
    sigma_bins = range_sigma_m(sensor) / lidar.r_r
    spread = int(np.ceil(2.0 * SIGMA_CUT * sigma_bins)) + 1
    if spread > MAX_SPREAD_BINS:
        raise InputError(
            f"{where}: a return's timing spread (pulse_fwhm_ps = {sensor.pulse_fwhm_ps!r}, "
            f"jitter_ps = {sensor.jitter_ps!r}: sigma {range_sigma_m(sensor):.4g} m) reaches "
            f"{spread} range bins of r_r_m = {lidar.r_r!r} at once; accepted: at most "
            f"{MAX_SPREAD_BINS} (less spread, or a coarser r_r_m)")
    check_work(sensor, lidar, n_bins)  # the noise now; the signal once the rays are cast
    return n_bins


@lru_cache(maxsize=16)
def spread_table(sigma_bins: float) -> tuple[float, np.ndarray]:
    """How a return of sigma ``sigma_bins`` (bins) spreads over the bins its Gaussian reaches:
    ``half`` = SIGMA_CUT sigma, and weights[r, j] = the mass in bin lo + j of a return at
    u = lo + half + r / SPREAD_ROWS. Weights below the error function's accuracy (~1e-7) are 0."""
    half = SIGMA_CUT * sigma_bins
    nb = int(np.ceil(2.0 * half)) + 1
    f = np.arange(SPREAD_ROWS + 1) / SPREAD_ROWS
    edges = np.arange(nb + 1)[None, :] - f[:, None] - half  # bin edges - u, in bins
    w = np.diff(normal_cdf(edges / sigma_bins), axis=1)
    return half, np.where(w > 1e-7, w, 0.0)

@dataclass
class SubRayHits:
    """What the ray caster found for the K x K sub-rays of N samples' cells: one entry per
    sub-ray that hit (sample, cell, unquantized float64 range, cosine of incidence), grouped
    by sample. ``photon_cloud`` checks them against its lidar (``check_hits``) before use."""

    sample: np.ndarray  # int64
    w: np.ndarray  # int32, centred cell indices
    h: np.ndarray
    range_m: np.ndarray  # float64
    cos: np.ndarray  # float64 in [0, 1]
    n_samples: int
    sub_rays: int  # K^2


@dataclass
class PhotonCells:
    """A photon cloud of N samples as the lidar records it: cell and bin-centre range per point,
    ``label`` 1 signal / 0 noise, ``count`` the events in the point's bin (1 per event in events
    output), ``pulse`` the event's pulse (events output; -1 in points output). Grouped by
    sample. ``target_*`` give, per cell that any sub-ray hit, the expected signal
    photo-electrons per pulse (what a learner needs to redo the stage)."""

    sample: np.ndarray
    w: np.ndarray
    h: np.ndarray
    range_m: np.ndarray
    label: np.ndarray  # uint8
    count: np.ndarray  # int32
    pulse: np.ndarray  # int32
    n_samples: int
    target_sample: np.ndarray
    target_w: np.ndarray
    target_h: np.ndarray
    target_signal_pe: np.ndarray
    events: bool = False  # the sensor's output was events (then ``pulse`` is meaningful)

    @classmethod
    def concatenate(cls, parts: list, n_samples: int) -> PhotonCells:
        """Parts of one batch, their ``sample`` already in the batch's numbering."""
        fields = [f for f in cls.__dataclass_fields__ if f not in ("n_samples", "events")]
        return cls(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in fields},
                   n_samples=n_samples, events=bool(parts) and parts[0].events)


def to_cloud(cells: PhotonCells, beta0: np.ndarray, lidar: LidarParams) -> PointCloud:
    """The photon cloud in the observation frame: each point on its cell's centre ray at its
    bin's centre range, as the ideal cloud places a quantized range (``beta0`` per sample)."""
    alpha, beta = lidar.cell_centre_angles(cells.w, cells.h,
                                           np.asarray(beta0, np.float64)[cells.sample])
    pulse = cells.pulse if cells.events else None
    return PointCloud(spherical_to_cartesian(alpha, beta, cells.range_m), cells.range_m,
                      cells.w, cells.h, cells.sample, cells.label, cells.count, pulse)


# The photon draws' own stream beside the dataset's other uses of its seed ("PHOT").
PHOTON_STREAM = 0x50484F54


def sample_rng(seed: int, sample_id: int) -> np.random.Generator:
    """The generator of one sample's photons: the same for a sample however it is batched."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFFFFFFFFFF, PHOTON_STREAM,
                                  int(sample_id)])


def gate_first_bin(r0: np.ndarray, sensor: SensorParams, lidar: LidarParams) -> np.ndarray:
    """Global index (floor(r / R_r), the ideal quantizer's bins) of each gate's first bin: the
    gate of ``gate_m`` metres is centred on the target's range r0, but opens no earlier than
    the pulse leaves (bin 0): a gate longer than 2 r0 runs from range 0, its length kept."""
    first = np.floor((np.asarray(r0, np.float64) - sensor.gate_m / 2.0) / lidar.r_r)
    return np.maximum(first, 0.0).astype(np.int64)


def signal_bins(cell: np.ndarray, range_m: np.ndarray, mean: np.ndarray, first_bin,
                n_bins: int, sigma_bins: float, r_r: float,
                compiled: bool = False) -> SignalBins:
    """Spread each return's mean counts over the bins its Gaussian reaches (its range in bins,
    sigma in bins) and add them up per (cell, bin); bins outside the gate are lost.
    ``first_bin``: the gate's first bin, one for all or one per return. ``compiled``: the
    spread and the sums in one compiled loop (``kernels.spread_sum``, the same bytes)."""
    if sigma_bins > 0 and compiled:
        k_ = kernels.require()
        half, weights = spread_table(sigma_bins)
        cell = np.asarray(cell, np.int64)
        first_bin = np.broadcast_to(np.asarray(first_bin, np.int64), cell.shape)
        range_m = np.asarray(range_m, np.float64)
        if not k_.ascending(cell):  # as below: a stable order by cell
            order = np.argsort(cell, kind="stable")
            cell, range_m, first_bin, mean = cell[order], range_m[order], first_bin[order], \
                mean[order]
        lo, row = k_.spread_start(range_m, np.ascontiguousarray(first_bin), float(r_r),
                                  float(half), float(len(weights) - 1))
        nb = weights.shape[1]
        heads = np.flatnonzero(np.concatenate([[True], cell[1:] != cell[:-1]])) \
            if len(cell) else np.zeros(0, np.int64)
        runs = int((np.maximum.reduceat(lo, heads) - np.minimum.reduceat(lo, heads)
                    + nb).sum()) if len(cell) else 0
        if _dense_fits(runs, len(cell) * nb):  # the kernel's slots: each cell's run
            c, b, total = k_.spread_sum(cell, lo, row, np.ascontiguousarray(mean, np.float64),
                                        weights, int(n_bins))
            return SignalBins(c, b, total)
        # wide runs: the numpy terms, added up by sorting (the same bytes)
        return _spread_terms(cell, lo, row, mean, weights, n_bins)
    u = range_m / r_r - first_bin  # position in the gate, in bins
    if sigma_bins > 0:
        half, weights = spread_table(sigma_bins)
        # Bins lo .. lo + nb - 1 with lo = floor(u - half): their weights depend only on the
        # fraction f = (u - half) - lo, tabulated; the nearest row moves a return by at most
        # half a row (1 / 8192 of a bin: 18 um at 0.15 m bins), far below sigma.
        start = u - half
        lo = np.floor(start)
        row = np.rint((start - lo) * (len(weights) - 1)).astype(np.int64)
        return _spread_terms(cell, lo.astype(np.int64), row, mean, weights, n_bins)
    return _gated_sum(np.floor(u).astype(np.int64), mean, cell, n_bins)


def _spread_terms(cell, lo, row, mean, weights, n_bins) -> SignalBins:
    """Hit i's mean times weights[row[i], j] in bin lo[i] + j, added up per (cell, bin)."""
    m = mean[:, None] * weights[row]
    b = lo[:, None] + np.arange(weights.shape[1])[None, :]
    c = np.broadcast_to(cell[:, None], b.shape)
    return _gated_sum(b.ravel(), m.ravel(), c.ravel(), n_bins)


def _gated_sum(b, m, c, n_bins) -> SignalBins:
    """The terms in the gate (and > 0) added up per (cell, bin)."""
    keep = (b >= 0) & (b < n_bins) & (m > 0)
    b, m, c = b[keep], m[keep], c[keep]
    if len(c) == 0:
        return SignalBins(c.astype(np.int64), b, m)
    if (np.diff(c) < 0).any():  # the simulator gives hits cell by cell; others may not
        order = np.argsort(c, kind="stable")
        b, m, c = b[order], m[order], c[order]
    return _sum_cell_bins(c, b, m)


# signal_bins adds up per (cell, bin) through one dense slot per bin of each cell's run of
# bins while the runs hold at most this many slots per (sub-ray, bin) term (plus
# DENSE_SLOTS_FREE); past that (fine bins under a sharp pulse: a cell's sub-rays a metre
# apart are 1e6 bins of 1 um) it sorts the terms instead: memory follows the terms.
DENSE_SLOTS_PER_TERM = 4
DENSE_SLOTS_FREE = 1 << 16


def _dense_fits(runs: int, terms: int) -> bool:
    return runs <= DENSE_SLOTS_PER_TERM * terms + DENSE_SLOTS_FREE


def _sum_cell_bins(c: np.ndarray, b: np.ndarray, m: np.ndarray) -> SignalBins:
    """The terms ``m`` (> 0) added up per (cell ``c``, bin ``b``), ``c`` sorted, each sum
    taken in the terms' order (as bincount adds): by (cell, bin). The dense slots and the
    sort give the same bytes."""
    first = np.flatnonzero(np.concatenate([[True], c[1:] != c[:-1]]))
    lo = np.minimum.reduceat(b, first)
    width = np.maximum.reduceat(b, first) - lo + 1
    if not _dense_fits(int(width.sum()), len(c)):
        # a stable sort by (cell, bin): a sum's terms keep their order
        order = np.lexsort((b, c))
        cs, bs = c[order], b[order]
        new = np.empty(len(cs), bool)
        new[0] = True
        new[1:] = (cs[1:] != cs[:-1]) | (bs[1:] != bs[:-1])
        total = np.bincount(np.cumsum(new) - 1, weights=m[order])
        slot = np.flatnonzero(total > 0)
        head = np.flatnonzero(new)[slot]
        return SignalBins(cs[head].astype(np.int64), bs[head].astype(np.int64), total[slot])
    # each cell's bins lie in a short run [lo, hi]; one dense slot per bin of those runs,
    # filled by bincount, without sorting the terms
    start = np.concatenate([[0], np.cumsum(width)])
    group = np.repeat(np.arange(len(first)), np.diff(np.append(first, len(c))))
    total = np.bincount(start[group] + b - lo[group], weights=m, minlength=int(start[-1]))
    slot = np.flatnonzero(total > 0)
    g = np.searchsorted(start, slot, side="right") - 1
    return SignalBins(c[first][g].astype(np.int64), lo[g] + slot - start[g], total[slot])


def _per_sample(hits, cell_all, pe, first, n_bins, sigma_bins, noise, dead_bins, sensor,
                lidar, seed, ids, n_cells, compiled=False) -> list:
    """Events (or points with a dead time shorter than the gate), sample by sample, pulse by
    pulse: each sample's own generator (``sample_rng``); ``compiled``: the signal's spread
    compiled (the same bytes)."""
    bounds = np.searchsorted(hits.sample, np.arange(hits.n_samples + 1))
    parts = []
    for i in range(hits.n_samples):
        sl = slice(bounds[i], bounds[i + 1])
        sig = signal_bins(cell_all[sl], hits.range_m[sl], pe[sl], int(first[i]), n_bins,
                          sigma_bins, lidar.r_r, compiled)
        rng = sample_rng(seed, ids[i])
        if sensor.output == "events":
            ev = detect(rng, sig, n_cells, n_bins, noise, dead_bins, sensor.pulses, True)
            m = len(ev.cell)
            parts.append((np.full(m, i, np.int64), ev.cell, ev.bin, ev.signal.astype(np.uint8),
                          np.ones(m, np.int32), ev.pulse))
        else:
            hist = detect_points(rng, sig, n_cells, n_bins, noise, dead_bins, sensor.pulses,
                                 sensor.threshold)
            m = len(hist.cell)
            label = (2 * hist.signal_count >= hist.count).astype(np.uint8)
            parts.append((np.full(m, i, np.int64), hist.cell, hist.bin, label,
                          hist.count.astype(np.int32), np.full(m, -1, np.int32)))
    return parts


# The farthest range the stage takes, in range bins: a gate's bins are counted in int64 and a
# bin's range computed in float64, exact below 2**53 (a gate of up to 2**52 bins beyond).
MAX_RANGE_BINS = 2**52
# A photon seed: what --seed and a dataset config's seed accept (apcg_core/options.py SEED).
MAX_SEED = 2**32 - 1


def _ranges(name: str, values: np.ndarray, lidar: LidarParams) -> None:
    """Refuse ``values`` (metres) that are not all finite, > 0 and within MAX_RANGE_BINS
    bins: a NaN or huge range would be cast to a garbage bin, a range <= 0 lies behind the
    lidar. Two reductions: NaN propagates through both and fails the comparison."""
    if not len(values):
        return
    lo, hi = values.min(), values.max()
    limit = MAX_RANGE_BINS * lidar.r_r
    if lo > 0 and hi <= limit:
        return
    bad = values[~(np.isfinite(values) & (values > 0) & (values <= limit))][0]
    raise InputError(f"photon stage: {name} = {bad!r} m not accepted; accepted: finite, "
                     f"> 0 and <= {limit:.6g} m (2**52 range bins of r_r_m = "
                     f"{lidar.r_r!r})")


def _hit_array(hits: SubRayHits, name: str, m: int, integer: bool) -> np.ndarray:
    """One of ``hits``' per-hit columns as a 1-D array of ``m`` entries, integer where it
    indexes (a float index would be truncated into another cell or sample)."""
    a = np.asarray(getattr(hits, name))
    kinds = "iu" if integer else "iuf"
    if a.ndim != 1 or len(a) != m or a.dtype.kind not in kinds:
        raise InputError(
            f"photon stage: SubRayHits {name} must be a 1-D array of {m} "
            f"{'integers' if integer else 'numbers'} (one per hit, as range_m), got "
            f"{a.dtype} of shape {a.shape}")
    return a


def _in(name: str, a: np.ndarray, lo: int, hi: int, what: str) -> None:
    """Refuse an index of ``a`` outside ``lo``..``hi``: never folded into another cell."""
    if len(a) and not (lo <= a.min() and a.max() <= hi):
        bad = a[(a < lo) | (a > hi)][0]
        raise InputError(f"photon stage: a hit's {name} = {int(bad)} lies outside {what}; "
                         f"accepted: {name} in {lo}..{hi}")


def check_hits(hits: SubRayHits, lidar: LidarParams) -> SubRayHits:
    """``hits`` checked against ``lidar``, the one entry of every caller (simulate, the
    dataset builder, generated clouds, scenes, the add-on): whole counts, columns of one
    length, samples in 0..n_samples-1 grouped in order (each sample's draws take its run),
    cells inside the W x H window, finite ranges > 0, cosines in [0, 1]. Returns them as
    arrays (no copy of an array)."""
    n = check_int("photon stage: SubRayHits n_samples", hits.n_samples, 0)
    k2 = check_int("photon stage: SubRayHits sub_rays", hits.sub_rays, 1,
                   hint=" (K x K sub-rays a cell)")
    range_m = np.asarray(hits.range_m)
    if range_m.ndim != 1 or range_m.dtype.kind not in "iuf":
        raise InputError(f"photon stage: SubRayHits range_m must be a 1-D array of numbers "
                         f"(one per hit), got {range_m.dtype} of shape {range_m.shape}")
    m = len(range_m)
    sample = _hit_array(hits, "sample", m, True)
    w = _hit_array(hits, "w", m, True)
    h = _hit_array(hits, "h", m, True)
    cos = _hit_array(hits, "cos", m, False)
    _in("sample", sample, 0, n - 1, f"the {n} samples")
    if m > 1 and (sample[1:] < sample[:-1]).any():
        raise InputError("photon stage: SubRayHits sample must be in order (the hits grouped "
                         "by sample, as the simulator gives them); sort the hits by sample")
    window = f"the lidar's {lidar.width} x {lidar.height} window (centred cell indices)"
    _in("w", w, lidar.w_min, lidar.w_min + lidar.width - 1, window)
    _in("h", h, lidar.h_min, lidar.h_min + lidar.height - 1, window)
    _ranges("a hit's range_m", range_m, lidar)
    if m and not (cos.min() >= 0 and cos.max() <= 1):
        bad = cos[~((cos >= 0) & (cos <= 1))][0]
        raise InputError(f"photon stage: a hit's cos = {bad!r} not accepted; accepted: the "
                         "cosine of its incidence, in [0, 1]")
    return SubRayHits(sample, w, h, range_m, cos, n, k2)


def _per_sample_values(name: str, values, n: int) -> np.ndarray:
    """``values`` as n float64, one per sample, or a named error (not numpy's)."""
    try:
        a = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.ndim != 1 or len(a) != n:
        raise InputError(f"photon stage: {name} must hold one number per sample ({n}), got "
                         f"{values!r}")
    return a


def _reflectivity(reflectivity, n: int, m: int) -> tuple[np.ndarray, bool]:
    """``reflectivity`` per sample (one value broadcast), or per hit when it holds one value
    per hit (m of them, m != n); and whether it is per hit."""
    per_hit = np.ndim(reflectivity) == 1 and len(reflectivity) == m != n
    try:
        rho = np.asarray(reflectivity, np.float64)
        return (rho if per_hit else np.broadcast_to(rho, (n,))), per_hit
    except (TypeError, ValueError):
        raise InputError(f"photon stage: reflectivity must be one number, one per sample ({n}) "
                         f"or one per hit ({m}), got {reflectivity!r}") from None


def _sample_ids(sample_ids, n: int) -> np.ndarray:
    """One id >= 0 per sample, integers: they seed each sample's draws."""
    ids = np.asarray(sample_ids)
    if ids.ndim != 1 or len(ids) != n or ids.dtype.kind not in "iu" or (
            n and ids.min() < 0):
        raise InputError(f"photon stage: sample_ids must be {n} integers >= 0 (one per "
                         f"sample), got {sample_ids!r}")
    return ids.astype(np.int64)


def photon_cloud(hits: SubRayHits, r0: np.ndarray, reflectivity: np.ndarray,
                 sensor: SensorParams, lidar: LidarParams, seed: int,
                 sample_ids: np.ndarray | None = None) -> PhotonCells:
    """The photon stage for N samples: every cell of each sample's W x H window is gated around
    the sample's range r0, with noise everywhere and signal where sub-rays hit. ``reflectivity``
    per sample, or per hit (one value per sub-ray hit: a scene's window holds several targets);
    ``sample_ids`` (default 0..N-1) seed each sample's draws. Every argument is checked here,
    the stage's one entry: the hits (``check_hits``), r0 finite and > 0, a seed in
    0..2**32-1 (``--seed``'s rule), a named InputError before anything is drawn."""
    hits = check_hits(hits, lidar)
    n = hits.n_samples
    r0 = _per_sample_values("r0 (the gate's range)", r0, n)
    _ranges("r0 (the gate's range)", r0, lidar)
    rho, per_hit = _reflectivity(reflectivity, n, len(hits.range_m))
    if not (np.isfinite(rho) & (rho >= 0) & (rho <= 1)).all():
        bad = rho[~(np.isfinite(rho) & (rho >= 0) & (rho <= 1))][0]
        raise InputError(f"reflectivity must be in [0, 1], got {bad!r}")
    seed = check_int("photon stage: seed", seed, 0, MAX_SEED)
    ids = np.arange(n) if sample_ids is None else _sample_ids(sample_ids, n)
    n_bins = check_sensor_at(sensor, lidar)
    n_cells = lidar.width * lidar.height
    noise = noise_per_bin(sensor, lidar.r_r)
    dead_bins = sensor.dead_time_ns * 1e-9 / bin_seconds(lidar.r_r)
    sigma_bins = range_sigma_m(sensor) / lidar.r_r
    first = gate_first_bin(r0, sensor, lidar)

    pe = signal_photoelectrons(hits.range_m, hits.cos, rho if per_hit else rho[hits.sample],
                               sensor, hits.sub_rays)
    cell_all = ((hits.h.astype(np.int64) - lidar.h_min) * lidar.width
                + (hits.w.astype(np.int64) - lidar.w_min))
    # per target cell: the expected signal photo-electrons per pulse
    key = hits.sample.astype(np.int64) * n_cells + cell_all
    if len(key) and (np.diff(key) >= 0).all():  # the simulator's order: np.unique's, unsorted
        new = np.empty(len(key), bool)
        new[0] = True
        np.not_equal(key[1:], key[:-1], out=new[1:])
        uniq, inv = key[new], np.cumsum(new) - 1
    else:
        uniq, inv = np.unique(key, return_inverse=True)
    tpe = np.bincount(inv, weights=pe, minlength=len(uniq))
    # the draws' cost with the signal now known (an upper bound: a cell's whole signal, gated
    # or not), refused before anything is drawn (check_work, as the noise was)
    terms = np.bincount(hits.sample, minlength=n).astype(np.float64) * (
        int(np.ceil(2.0 * SIGMA_CUT * sigma_bins)) + 1 if sigma_bins > 0 else 1)
    check_work(sensor, lidar, n_bins, signal_work(
        tpe, (uniq // n_cells).astype(np.int64), terms, n_bins, noise, dead_bins,
        sensor.pulses, sensor.output == "points", sensor.output == "events"))
    # the loops compiled once the process has enough hits for them (kernels.py: the same bytes)
    compiled = kernels.use_for(len(hits.range_m))
    if sensor.output == "points" and dead_bins >= n_bins:
        # the whole batch at once, with counter-based draws (points.py)
        gcell = hits.sample.astype(np.int64) * n_cells + cell_all
        sig = signal_bins(gcell, hits.range_m, pe, first[hits.sample], n_bins, sigma_bins,
                          lidar.r_r, compiled)
        pk = batch_points(sig, n, n_cells, n_bins, noise, sensor.pulses, sensor.threshold,
                          seed, ids, compiled)
        m = len(pk.cell)
        parts = [(pk.cell // n_cells, pk.cell % n_cells, pk.bin,
                  (2 * pk.signal_count >= pk.count).astype(np.uint8),
                  pk.count.astype(np.int32), np.full(m, -1, np.int32))]
    else:
        parts = _per_sample(hits, cell_all, pe, first, n_bins, sigma_bins, noise, dead_bins,
                            sensor, lidar, seed, ids, n_cells, compiled)
    cols = [np.concatenate([p[j] for p in parts]) if parts else np.zeros(0, np.int64)
            for j in range(6)]
    s, cell, b, label, count, pulse = cols
    w = (cell % lidar.width + lidar.w_min).astype(np.int32)
    h = (cell // lidar.width + lidar.h_min).astype(np.int32)
    range_m = (first[s] + b + 0.5) * lidar.r_r if len(s) else np.zeros(0)
    tcell = uniq % n_cells
    return PhotonCells(s.astype(np.int64), w, h, range_m.astype(np.float64),
                       label.astype(np.uint8), count.astype(np.int32), pulse.astype(np.int32),
                       n, (uniq // n_cells).astype(np.int64),
                       (tcell % lidar.width + lidar.w_min).astype(np.int32),
                       (tcell // lidar.width + lidar.h_min).astype(np.int32), tpe,
                       sensor.output == "events")


__all__ = ["LIGHT_M_S", "PhotonCells", "SubRayHits", "check_hits", "check_sensor_at",
           "gate_first_bin", "photon_cloud", "sample_rng", "signal_bins", "to_cloud"]
