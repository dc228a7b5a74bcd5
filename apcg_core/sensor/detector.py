"""The Geiger-mode detector (SPEC section 8): events of many pulses in a range gate, their
histogram per cell, and the cloud a single-photon lidar reports.

Time inside the gate is measured in range bins, t in [0, n_bins). Each cell sees a
piecewise-constant count intensity: ``noise`` per bin everywhere, plus the signal's mean in the
few bins its returns reach. A pulse's first event is where the cumulative intensity C(t) first
exceeds an Exp(1) draw (a Poisson process's first arrival), so

    P(first event in bin i) = (1 - exp(-mu_i)) exp(-sum_{k<i} mu_k)

holds exactly. After an event at t the detector is blind until t + dead time; the next event is
the next arrival after that.

Cost follows the events, not the window. In the cells the signal reaches ("loud" cells) the
number of pulses that fire is Binomial(pulses, 1 - exp(-C(n_bins))) per cell and only those are
followed. The rest of the window ("quiet" cells) has noise alone, the same law everywhere:
its fired (cell, pulse) pairs are found by geometric skipping. For the ``points`` output with a
dead time at least the gate (one event per pulse), quiet cells cost even less: a bin can only
hold ``threshold`` first events if at least ``threshold`` pulses had an arrival in it, and
those arrival counts are independent Binomial(pulses, 1 - exp(-noise)) per (cell, bin); only
the few cells with such a bin are then followed, arrival by arrival, exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SignalBins:
    """The signal's mean counts per pulse in the bins it reaches, flat and sorted by (cell, bin):
    cell ``cell[i]`` (an index into the window's cells) has ``mean[i]`` in gate bin ``bin[i]``."""

    cell: np.ndarray  # int64
    bin: np.ndarray  # int64, 0 <= bin < n_bins
    mean: np.ndarray  # float64 > 0


@dataclass
class Events:
    """Every detector event of one window: its cell, gate bin, whether it was signal, and (when
    asked for) the pulse it belongs to."""

    cell: np.ndarray  # int64
    bin: np.ndarray  # int64
    signal: np.ndarray  # bool
    pulse: np.ndarray | None = None  # int32, events output only


def _bisect(keys: np.ndarray, lo: np.ndarray, hi: np.ndarray, x: np.ndarray,
            right: bool) -> np.ndarray:
    """Per query, ``numpy.searchsorted(keys[lo:hi], x, side)`` + lo, all queries at once (each
    cell's keys are its own sorted run of the flat array)."""
    lo = lo.copy()
    hi = hi.copy()
    while True:
        active = lo < hi
        if not active.any():
            return lo
        mid = (lo + hi) // 2
        k = keys[np.minimum(mid, len(keys) - 1)] if len(keys) else np.zeros(len(mid))
        go_right = (k <= x) if right else (k < x)
        go_right &= active
        lo = np.where(go_right, mid + 1, lo)
        hi = np.where(active & ~go_right, mid, hi)


class Intensity:
    """C(t) of every cell of a window and its inverse: noise per bin everywhere plus the signal
    bins. Cells without signal have C(t) = noise t."""

    def __init__(self, signal: SignalBins, n_cells: int, n_bins: int, noise: float) -> None:
        self.noise = float(noise)
        self.n_bins = int(n_bins)
        self.bin = signal.bin
        self.mean = signal.mean
        self.start = np.searchsorted(signal.cell, np.arange(n_cells + 1)).astype(np.int64)
        before = np.concatenate([[0.0], np.cumsum(signal.mean)])  # signal before flat index i
        self.before = before[:-1] - before[self.start[signal.cell]]  # ... within the cell
        self.total_signal = before[self.start[1:]] - before[self.start[:-1]]
        # C at the end of each signal bin, a sorted run per cell
        self.end_c = self.noise * (self.bin + 1) + self.before + self.mean

    def total(self) -> np.ndarray:
        """C(n_bins) per cell: the mean counts of a whole gate."""
        return self.noise * self.n_bins + self.total_signal

    def inverse(self, cell: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The time t (bins) where C of ``cell`` reaches ``e`` (e < the cell's total), and the
        flat index of the signal bin holding it (-1 in a stretch of noise alone)."""
        lo, hi = self.start[cell], self.start[cell + 1]
        k = _bisect(self.end_c, lo, hi, e, right=True)  # first signal bin ending above e
        inside = k < hi
        kk = np.where(inside, k, 0)
        if len(self.bin) == 0:
            kk = np.zeros(len(e), np.int64)
            inside = np.zeros(len(e), bool)
            b = np.zeros(len(e))
            c_start = np.zeros(len(e))
            before = np.zeros(len(e))
        else:
            b = self.bin[kk].astype(np.float64)
            before = self.before[kk]
            c_start = self.noise * b + before
        before_all = np.where(inside, before, self.total_signal[cell])
        in_bin = inside & (e >= c_start)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_noise = (e - before_all) / self.noise if self.noise > 0 else np.full(len(e), np.inf)
            t_bin = b + (e - c_start) / (self.noise + (self.mean[kk] if len(self.mean) else 0.0))
        t = np.where(in_bin, t_bin, t_noise)
        return t, np.where(in_bin, kk, -1)

    def at(self, cell: np.ndarray, t: np.ndarray) -> np.ndarray:
        """C(t) of ``cell`` at times t (bins)."""
        lo, hi = self.start[cell], self.start[cell + 1]
        j = _bisect(self.bin.astype(np.float64), lo, hi, t, right=True)  # bins starting <= t
        c = self.noise * t
        has = j > lo
        if has.any():
            k = j[has] - 1
            part = np.clip(t[has] - self.bin[k], 0.0, 1.0)
            c[has] += self.before[k] + self.mean[k] * part
        return c


def _skip(rng: np.random.Generator, n: int, p: float) -> np.ndarray:
    """Indices of the successes among ``n`` independent trials of chance ``p`` each: the gaps
    between successes are geometric, so the cost is the number of successes, not of trials."""
    if n == 0 or p <= 0.0:
        return np.zeros(0, np.int64)
    if p >= 1.0:
        return np.arange(n, dtype=np.int64)
    parts = []
    last = -1
    log_q = np.log1p(-p)
    while last < n - 1:
        need = (n - 1 - last) * p
        u = rng.random(int(need + 6.0 * np.sqrt(need) + 16))
        # geometric gaps by inversion (numpy's own sampler is several times slower)
        more = last + np.cumsum(np.floor(np.log1p(-u) / log_q).astype(np.int64) + 1)
        parts.append(more)
        last = int(more[-1])
    pos = np.concatenate(parts)
    return pos[pos < n]


def _loud_events(rng: np.random.Generator, inten: Intensity, pulses: int, dead_bins: float):
    """(cell, bin, time, signal-bin index or -1, fired-pulse index) of every event of the loud
    cells (``inten``'s own cell numbers), and the fired pulses per cell."""
    n_bins = inten.n_bins
    total = inten.total()
    p_fire = -np.expm1(-total)
    fired = rng.binomial(pulses, p_fire)
    cell = np.repeat(np.arange(len(total), dtype=np.int64), fired)
    u = rng.random(len(cell))
    # the first event: an Exp(1) draw conditioned on falling inside the gate
    e = np.minimum(-np.log1p(-u * p_fire[cell]), np.nextafter(total[cell], 0))
    t, k = inten.inverse(cell, e)
    owner = np.arange(len(cell), dtype=np.int64)
    if dead_bins < n_bins:  # the detector re-arms inside the gate: later events of a pulse
        cells, ts, ks, owners = [cell], [t], [k], [owner]
        cur_cell, cur_t, cur_owner = cell, t, owner
        while len(cur_cell):
            start = cur_t + dead_bins
            go = start < n_bins
            cur_cell, start, cur_owner = cur_cell[go], start[go], cur_owner[go]
            e = inten.at(cur_cell, start) + rng.standard_exponential(len(cur_cell))
            go = e < total[cur_cell]
            cur_cell, e, cur_owner = cur_cell[go], e[go], cur_owner[go]
            cur_t, cur_k = inten.inverse(cur_cell, e)
            cells.append(cur_cell)
            ts.append(cur_t)
            ks.append(cur_k)
            owners.append(cur_owner)
        cell, t, k, owner = (np.concatenate(x) for x in (cells, ts, ks, owners))
    b = np.minimum(np.floor(t).astype(np.int64), n_bins - 1)
    return cell, b, t, k, owner, fired


def _quiet_events(rng: np.random.Generator, n_quiet: int, n_bins: int, noise: float,
                  pulses: int, dead_bins: float):
    """(quiet cell, bin, time, pulse) of every event of ``n_quiet`` cells of noise alone."""
    p = float(-np.expm1(-noise * n_bins))
    pos = _skip(rng, n_quiet * pulses, p)  # fired (cell, pulse) pairs
    cell, pulse = pos // pulses, pos % pulses
    u = rng.random(len(pos))
    t = np.minimum(-np.log1p(-u * p) / noise if len(u) else u, np.nextafter(float(n_bins), 0))
    if dead_bins < n_bins:
        cells, ts, ps = [cell], [t], [pulse]
        cur_cell, cur_t, cur_pulse = cell, t, pulse
        while len(cur_cell):
            nxt = cur_t + dead_bins + rng.standard_exponential(len(cur_cell)) / noise
            go = nxt < n_bins
            cur_cell, cur_t, cur_pulse = cur_cell[go], nxt[go], cur_pulse[go]
            cells.append(cur_cell)
            ts.append(cur_t)
            ps.append(cur_pulse)
        cell, t, pulse = (np.concatenate(x) for x in (cells, ts, ps))
    return cell, np.floor(t).astype(np.int64), t, pulse


def _binomial_pmf(n: int, p: float) -> np.ndarray:
    """P(Binomial(n, p) = z) for z = 0..n, in logs (no overflow for large n)."""
    if p <= 0.0 or p >= 1.0:
        pmf = np.zeros(n + 1)
        pmf[0 if p <= 0.0 else n] = 1.0
        return pmf
    z = np.arange(n + 1, dtype=np.float64)
    log_choose = np.concatenate([[0.0], np.cumsum(np.log((n - z[1:] + 1) / z[1:]))])
    with np.errstate(divide="ignore"):
        return np.exp(log_choose + z * np.log(p) + (n - z) * np.log1p(-p))


def _quiet_cost(n_quiet: int, n_bins: int, pmf: np.ndarray, pulses: int, threshold: int,
                noise: float) -> tuple[float, float]:
    """Expected work (arrivals handled) of the quiet cells' heavy-bin route
    (``points._quiet_peaks``) and of following every pulse that fires."""
    z = np.arange(len(pmf))
    heavy = float(pmf[threshold:].sum())
    cells = min(float(n_quiet), n_quiet * n_bins * heavy)
    light_z = float((pmf[1:threshold] * z[1:threshold]).sum())
    fast = n_quiet * n_bins * heavy * pulses / 2 + cells * n_bins * light_z
    full = n_quiet * pulses * float(-np.expm1(-noise * n_bins))
    return fast, full


def work_per_window(n_cells: int, n_bins: int, noise: float, dead_bins: float, pulses: int,
                    threshold: int, points: bool) -> float:
    """Expected arrivals the draws of one window's noise follow, by the route they take: the
    cheaper of the heavy-bin route and every pulse (``_quiet_cost``, as ``points.batch_points``
    chooses) for the points output with a dead time of at least the gate; otherwise every
    event of every pulse: a pulse's first event (1 - exp(-noise n_bins)), or where the
    detector re-arms many times in the gate, the dead-time-limited rate's noise n_bins /
    (1 + noise dead_bins), whichever is more."""
    if points and dead_bins >= n_bins:
        pmf = _binomial_pmf(pulses, float(-np.expm1(-noise)))
        return min(_quiet_cost(n_cells, n_bins, pmf, pulses, threshold, noise))
    first = float(-np.expm1(-noise * n_bins))
    per_pulse = max(first, noise * n_bins / (1.0 + noise * dead_bins)) \
        if dead_bins < n_bins else first
    return float(n_cells) * pulses * per_pulse


def signal_work(loud_total: np.ndarray, loud_sample: np.ndarray, contributions: np.ndarray,
                n_bins: int, noise: float, dead_bins: float, pulses: int, points: bool,
                events: bool) -> np.ndarray:
    """Expected work of each sample's signal, an upper bound, beside ``work_per_window``'s
    noise. ``loud_total``: the mean signal counts per pulse of each cell the signal reaches
    (an upper bound does), ``loud_sample`` its sample; ``contributions`` per sample: the
    (sub-ray, bin) terms its spread makes (``stage.signal_bins`` holds each; one work each).
    Following every event (``events``, or ``points`` with a dead time shorter than the gate),
    a pulse of a loud cell gives at least its first event, 1 - exp(-C), and at most
    min(C, 1 + n_bins / dead_bins) (C = the gate's signal + noise): at most 1 - exp(-C) once
    the dead time holds the gate. The events output also draws one uniform per (loud cell,
    pulse) for the pulse numbers (``_pulse_numbers``). ``points`` with a dead time of at
    least the gate (``points.batch_points``): a loud cell costs its pieces (at most two per
    signal bin) and the events of its stretches, whose faint bins expect under
    ``BRIGHT_COUNTS`` (3) counts each and whose noise gives at most a first event a pulse:
    5 per term more, plus pulses (1 - exp(-noise n_bins)) a loud cell."""
    loud_total = np.asarray(loud_total, np.float64)
    contributions = np.asarray(contributions, np.float64)
    n = len(contributions)
    if points and dead_bins >= n_bins:
        per_cell = np.full(len(loud_total), pulses * float(-np.expm1(-noise * n_bins)))
        return contributions * 6.0 + np.bincount(loud_sample, per_cell, minlength=n)
    c = loud_total + noise * n_bins
    first = -np.expm1(-c)
    if dead_bins >= n_bins:
        per_pulse = first
    else:
        cap = 1.0 + n_bins / dead_bins if dead_bins > 0 else np.inf
        per_pulse = np.maximum(first, np.minimum(c, cap))
    per_cell = pulses * (per_pulse + (1.0 if events else 0.0))
    return contributions + np.bincount(loud_sample, per_cell, minlength=n)


def _signal_share(signal: SignalBins, k: np.ndarray, noise: float) -> np.ndarray:
    """The chance that an event is signal: the signal's part of its bin's mean (0 in a bin the
    signal does not reach)."""
    share = np.zeros(len(k))
    sig = k >= 0
    if sig.any():
        share[sig] = signal.mean[k[sig]] / (signal.mean[k[sig]] + noise)
    return share


class Window:
    """The loud cells (those the signal reaches) and the quiet rest of a window of ``n_cells``,
    with the loud cells' intensity in their own numbering."""

    def __init__(self, signal: SignalBins, n_cells: int, n_bins: int, noise: float) -> None:
        self.loud = np.unique(signal.cell)
        local = SignalBins(np.searchsorted(self.loud, signal.cell), signal.bin, signal.mean)
        self.signal = local
        self.inten = Intensity(local, len(self.loud), n_bins, noise)
        self.n_quiet = n_cells - len(self.loud)
        # the j-th quiet cell is j plus the loud cells at or below it
        self._gaps = self.loud - np.arange(len(self.loud))

    def quiet_cell(self, j: np.ndarray) -> np.ndarray:
        return j + np.searchsorted(self._gaps, j, side="right")


def detect(rng: np.random.Generator, signal: SignalBins, n_cells: int, n_bins: int,
           noise_per_bin: float, dead_bins: float, pulses: int, with_pulse: bool) -> Events:
    """Every event of ``pulses`` pulses in each of ``n_cells`` cells (SPEC section 8), labelled
    signal or noise, with its pulse number when ``with_pulse``; ordered by cell, pulse, time."""
    win = Window(signal, n_cells, n_bins, noise_per_bin)
    cell, b, t, k, owner, fired = _loud_events(rng, win.inten, pulses, dead_bins)
    is_signal = rng.random(len(cell)) < _signal_share(win.signal, k, noise_per_bin)
    pulse = _pulse_numbers(rng, fired, pulses)[owner] if with_pulse else owner
    q_cell, q_b, q_t, q_pulse = _quiet_events(rng, win.n_quiet, n_bins, noise_per_bin, pulses,
                                              dead_bins)
    cell = np.concatenate([win.loud[cell], win.quiet_cell(q_cell)])
    b = np.concatenate([b, q_b])
    t = np.concatenate([t, q_t])
    pulse = np.concatenate([pulse, q_pulse])
    is_signal = np.concatenate([is_signal, np.zeros(len(q_cell), bool)])
    order = np.lexsort((t, pulse, cell))
    ev = Events(cell[order], b[order], is_signal[order])
    if with_pulse:
        ev.pulse = pulse[order].astype(np.int32)
    return ev


def detect_points(rng: np.random.Generator, signal: SignalBins, n_cells: int, n_bins: int,
                  noise_per_bin: float, dead_bins: float, pulses: int,
                  threshold: int) -> Histogram:
    """The peak bin (nearest of equal peaks) of each cell whose histogram reaches ``threshold``
    counts there, and how many of its counts were signal, from every event (for a dead time
    shorter than the gate; ``points.batch_points`` draws the usual case without them)."""
    win = Window(signal, n_cells, n_bins, noise_per_bin)
    cell, b, _, k, _, _ = _loud_events(rng, win.inten, pulses, dead_bins)
    is_signal = rng.random(len(cell)) < _signal_share(win.signal, k, noise_per_bin)
    loud = peaks(Events(win.loud[cell], b, is_signal), n_bins)
    q_cell, q_b, _, _ = _quiet_events(rng, win.n_quiet, n_bins, noise_per_bin, pulses,
                                      dead_bins)
    quiet = peaks(Events(q_cell, q_b, np.zeros(len(q_cell), bool)), n_bins)
    quiet.cell = win.quiet_cell(quiet.cell)
    cat = [np.concatenate([getattr(h, f) for h in (loud, quiet)]) for f in
           ("cell", "bin", "count", "signal_count")]
    keep = cat[2] >= threshold
    order = np.argsort(cat[0][keep], kind="stable")
    return Histogram(*(c[keep][order] for c in cat))


# The most uniforms ``_pulse_numbers`` holds at once (rows of ``pulses``): about 25 bytes each
# with their two argsorts, so about 50 MB whatever the loud cells and pulses.
PULSE_NUMBER_CHUNK = 1 << 21


def _pulse_numbers(rng: np.random.Generator, fired: np.ndarray, pulses: int) -> np.ndarray:
    """For each fired pulse of the loud cells (grouped by cell), its number among the cell's
    ``pulses``: a uniformly random subset of that size (pulses of a static scene are
    exchangeable). Drawn a block of cells at a time (the generator's stream read in the same
    order, so the same numbers as one (cells, pulses) draw), in bounded memory; its time is
    one uniform per (loud cell, pulse), which ``signal_work`` counts."""
    rows = max(1, PULSE_NUMBER_CHUNK // max(int(pulses), 1))
    out = []
    for lo in range(0, len(fired), rows):
        f = fired[lo:lo + rows]
        ranks = np.argsort(np.argsort(rng.random((len(f), pulses)), axis=1), axis=1)
        chosen = ranks < f[:, None]  # row-major: each cell's subset in pulse order
        out.append(np.nonzero(chosen)[1].astype(np.int64))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


@dataclass
class Histogram:
    """Per cell with any event: its peak bin (the nearest of equal peaks), the counts there, and
    how many of them were signal."""

    cell: np.ndarray
    bin: np.ndarray
    count: np.ndarray
    signal_count: np.ndarray


def peaks(events: Events, n_bins: int) -> Histogram:
    """The histogram of every cell's events, reduced to its peak bin."""
    key = events.cell * n_bins + events.bin
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    sig = np.bincount(inv, weights=events.signal, minlength=len(uniq)).astype(np.int64)
    cell = uniq // n_bins
    b = uniq % n_bins
    order = np.lexsort((b, -counts, cell))  # per cell: most counts first, then nearest
    first = np.ones(len(order), bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    pick = order[first]
    return Histogram(cell[pick], b[pick], counts[pick].astype(np.int64), sig[pick])
