"""The ``points`` output of a batch of samples at once (SPEC section 8), for a dead time at
least the gate (one event per pulse, Geiger mode): the same law as following every pulse
(``detector.detect`` then ``detector.peaks``), at a cost that follows the signal's bins and
the rare noise peaks instead of the pulses.

Cells are numbered across the batch (sample * W * H + cell). Every draw is a counter-based
uniform of (seed, sample id, stream, index within the sample) (``draws``), so a sample's
points do not depend on its batch.

* Loud cells (those the signal reaches): the gate is cut into pieces, each bright signal bin
  (``BRIGHT_COUNTS``) and each stretch between them (noise and the faint signal bins there).
  A pulse that has not fired before a piece fires in it with chance 1 - exp(-mu) (mu the
  piece's mean), so the pulses firing in each piece are a chain of binomials in time order:
  exactly the multinomial histogram of first events. A bright bin's count is kept; its signal
  part is binomial with the signal's share of the bin. Events in a stretch are placed in it
  one by one (the first-arrival law truncated to the stretch), an event in a faint bin
  signal with that bin's share.
* Quiet cells (noise alone): arrivals of a pulse in a (cell, bin) are Poisson(noise), and a
  bin's count of first events is at most Z, the pulses with an arrival there, which is
  Binomial(pulses, 1 - exp(-noise)) independently over (cell, bin). Only (cell, bin) with
  Z >= threshold can hold a point: their number is binomial over all quiet slots and their
  places uniform; in their cells every other bin's Z is drawn given Z < threshold (most are
  0); each Z gets a uniform subset of pulses, and a pulse's event is its first arrival.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from . import draws, kernels
from .detector import SignalBins, _binomial_pmf, _bisect, _quiet_cost

# A signal bin is a piece of its own (its count kept, its binomial in the chain) when it
# expects at least this many counts over the pulses; fainter bins join the stretch of noise
# they lie in, where an event is placed only when the stretch could hold the cell's point.
# The law is the same either way (a piece is any run of bins); the split only moves work:
# the faint bins of the spread's tails (half of all signal bins expect < 0.04 counts at the
# 1550 nm day preset) stop costing a binomial each. Chosen by bench/photons.py.
BRIGHT_COUNTS = 3.0


@dataclass
class Peaks:
    """Per cell (batch numbering) with a point: its bin, count and signal count."""

    cell: np.ndarray
    bin: np.ndarray
    count: np.ndarray
    signal_count: np.ndarray


def _first_of_groups(key: np.ndarray) -> np.ndarray:
    first = np.empty(len(key), bool)
    if len(key):
        first[0] = True
        first[1:] = key[1:] != key[:-1]
    return first


def _top(cell, b, count, sig, n_bins: int) -> Peaks:
    """Per cell, the bin with the most counts (the nearest of equal ones); ``cell`` sorted, a
    (cell, bin) at most once. No sort: each cell's best of count * (n_bins + 1) + n_bins - bin
    (the count first, then the nearer bin), by ``maximum.reduceat`` over its run."""
    if len(cell) == 0:
        z = np.zeros(0, np.int64)
        return Peaks(z, z, z, z)
    score = count.astype(np.int64) * (n_bins + 1) + (n_bins - b)
    heads = np.flatnonzero(_first_of_groups(cell))
    best = np.maximum.reduceat(score, heads)
    at = np.flatnonzero(score == np.repeat(best, np.diff(np.append(heads, len(cell)))))
    return Peaks(cell[at], b[at], count[at], sig[at])


def _histogram(cell, b, n_bins: int, label=None) -> Peaks:
    """Counts per (cell, bin) of events (``label`` 1 for a signal event; none: all noise),
    reduced to each cell's peak with its signal count."""
    if len(cell) == 0:
        z = np.zeros(0, np.int64)
        return Peaks(z, z, z, z)
    key = cell * n_bins + b
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.flatnonzero(_first_of_groups(key))
    counts = np.diff(np.append(first, len(key)))
    sig = (np.add.reduceat(np.asarray(label, np.int64)[order], first) if label is not None
           else np.zeros(len(first), np.int64))
    k = key[first]
    return _top(k // n_bins, k % n_bins, counts, sig, n_bins)


def _sum_before(values: np.ndarray, steps: list) -> np.ndarray:
    """For each piece, the sum of its cell's earlier pieces' ``values`` (``steps[j]``: the
    pieces at position j of their cell, each one right after its cell's piece j - 1)."""
    out = np.zeros(len(values))
    for idx in steps[1:]:
        out[idx] = out[idx - 1] + values[idx - 1]
    return out


def _chain_compiled(k_, chain, em, rest, heads, counts, cell_of_piece, remaining, u,
                    fired) -> None:
    """The chain of _loud_peaks, position by position as there, with each position's
    binomials (draws.binomial_inverse) split at their transcendentals: p = em / (1 -
    exp(-rest)) (em = 1 - exp(-mu), every piece's), q and log(1 - q) of every chain piece in
    numpy at once, then per position the start and log P(start) compiled, the exp (and any
    log q, lgamma) in numpy, the walk compiled. The same bytes."""
    at = np.flatnonzero(chain)
    n = len(em)
    p = np.zeros(len(at))  # a piece with nothing after its start (no noise, no signal): 0
    going = rest[at] > 0
    p[going] = np.clip(np.minimum(em[at][going] / -np.expm1(-rest[at][going]), 1.0), 0.0, 1.0)
    flip = np.zeros(n, bool)
    flip[at] = p > 0.5
    qa = np.where(flip[at], 1.0 - p, p)
    q, log1pq = np.zeros(n), np.zeros(n)
    q[at] = qa
    good = qa > 0
    log1pq[at[good]] = np.log1p(-qa[good])
    active = np.flatnonzero(remaining > 0)
    j = 0
    while len(active):
        idx, start, log_pk = k_.chain_prepare(j, active, heads, counts, remaining, q, log1pq)
        big = start > 0
        if big.any():
            s, m = start[big], remaining[cell_of_piece[idx[big]]]
            log_pk[big] = s * np.log(q[idx[big]]) + log_pk[big]
            log_pk[big] += (draws._lgamma(m + 1) - draws._lgamma(s + 1)
                            - draws._lgamma(m - s + 1)).astype(float)
        k_.chain_finish(idx, start, np.exp(log_pk), cell_of_piece, remaining, q, flip, u,
                        fired)
        j += 1
        active = active[(remaining[active] > 0) & (counts[active] > j)]


def _sequential_sums(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per run [lo, hi) of ``values``, its sum added up in order from 0.0 (((0 + v0) + v1) +
    ...), as the compiled loop adds it: position by position, all runs at once."""
    acc = np.zeros(len(lo))
    size = hi - lo
    for k in range(int(size.max()) if len(size) else 0):
        at = np.flatnonzero(size > k)
        acc[at] = acc[at] + values[lo[at] + k]
    return acc


def _stretch_bins(t, e_piece, p_start, p_len, p_flo, p_fhi, b, mean, noise: float) -> tuple:
    """Where each event of a stretch lands (numpy; ``kernels.stretch_peaks`` compiled, the same
    bytes): ``t`` the mean its first arrival took from the piece's start (the first-arrival
    law: -log(1 - u (1 - exp(-M)))), walked through the piece's noise runs and faint signal
    bins in order (A_f, B_f: the mean up to faint bin f's start and end). Returns the bin
    and the faint signal bin's index (-1 in a run of noise)."""
    n = len(t)
    start, end = p_start[e_piece], p_start[e_piece] + p_len[e_piece]
    flo, fhi = p_flo[e_piece], p_fhi[e_piece]
    # A_f and B_f of the faint bins of the pieces these events are in, position by position
    pieces = np.unique(e_piece[fhi > flo])
    lo, hi = p_flo[pieces], p_fhi[pieces]
    a_f, b_f = np.zeros(len(mean)), np.zeros(len(mean))
    cum, x = np.zeros(len(pieces)), p_start[pieces].copy()
    for k in range(int((hi - lo).max()) if len(pieces) else 0):
        at = np.flatnonzero(hi - lo > k)
        f = lo[at] + k
        a_f[f] = cum[at] + noise * (b[f] - x[at])
        b_f[f] = a_f[f] + (noise + mean[f])
        cum[at], x[at] = b_f[f], b[f] + 1
    # the first of A_lo, B_lo, A_lo+1, ... above t: 2k a run of noise before faint bin k,
    # 2k + 1 faint bin k, 2 fhi the run after the last
    v = np.empty(2 * len(mean))
    v[0::2], v[1::2] = a_f, b_f
    pos = _bisect(v, 2 * flo, 2 * fhi, t, right=True)
    k = pos // 2
    in_faint = (pos % 2 == 1)
    had = k > flo  # a faint bin before: the run starts after it
    prev = np.maximum(k - 1, 0)
    x = np.where(had, b[prev] + 1, start)
    cum = np.where(had, b_f[prev], 0.0)
    run_end = np.where(k < fhi, b[np.minimum(k, len(b) - 1)], end) if len(b) else end
    bin_ = np.empty(n, np.int64)
    faint = np.full(n, -1, np.int64)
    faint[in_faint] = k[in_faint]
    bin_[in_faint] = b[k[in_faint]]
    run = np.flatnonzero(~in_faint)
    # after the last faint bin with no run left, or no noise: the last faint bin
    last = (k[run] == fhi[run]) & (fhi[run] > flo[run]) & ((x[run] >= end[run]) | (noise <= 0))
    lf = run[last]
    faint[lf] = fhi[lf] - 1
    bin_[lf] = b[fhi[lf] - 1]
    run = run[~last]
    if len(run):
        off = np.minimum(np.floor((t[run] - cum[run]) / noise),
                         (run_end[run] - 1 - x[run]).astype(np.float64))
        bin_[run] = x[run] + off.astype(np.int64)
    return bin_, faint


def _pieces(cell, b, mean, n_bins: int, noise: float, n_cells: int, bright_min: float,
            steps: list | None = None) -> tuple:
    """The loud cells' pieces (numpy; ``kernels.pieces`` compiled, the same bytes). Per cell
    (``cell`` sorted, its signal bins ``b`` ascending) each bright signal bin (mean >=
    ``bright_min``) is a piece; the bins between them, and before the first and after the
    last (the whole gate in a cell with none), are one piece each where there are any: noise
    and the faint signal bins there. Per piece: start, length, bright signal bin index (-1
    for the others), its faint signal bins [flo, fhi), mean (noise * length plus the bright
    bin's mean, or plus its faint bins' means added up in order), sample, number within the
    sample, loud cell index, and the sum of the cell's earlier pieces' means (C before it);
    per loud cell: first piece, pieces, and C of the whole gate. ``steps``, when given,
    receives the pieces by position in their cell."""
    n_sig = len(cell)
    new_cell = _first_of_groups(cell)
    cell_id = np.cumsum(new_cell) - 1
    n_loud = int(cell_id[-1]) + 1
    cs = np.flatnonzero(new_cell)
    ce = np.append(cs[1:], n_sig)
    bi = np.flatnonzero(mean >= bright_min)  # the bright signal bins
    bc = cell_id[bi]
    first_b = _first_of_groups(bc)
    last_b = np.append(bc[1:] != bc[:-1], True) if len(bi) else np.zeros(0, bool)
    prev = np.concatenate([[0], bi[:-1]]) if len(bi) else bi
    prev_end = np.where(first_b, 0, b[prev] + 1)
    gap_len = b[bi] - prev_end
    gap = gap_len > 0
    tail_len = np.where(last_b, n_bins - 1 - b[bi], 0)
    tail = tail_len > 0
    dark = np.ones(n_loud, bool)  # cells without a bright bin: the whole gate one piece
    dark[bc] = False
    dark = np.flatnonzero(dark)
    # units in cell order: each bright bin (with the piece before it and the tail), each dark
    # cell (one piece)
    unit_cell = np.concatenate([bc, dark])
    order = np.argsort(unit_cell, kind="stable")
    per = np.concatenate([gap.astype(np.int64) + 1 + tail, np.ones(len(dark), np.int64)])
    end_slot = np.empty(len(order), np.int64)
    end_slot[order] = np.cumsum(per[order])
    n_pieces = int(end_slot.max())
    nb = len(bi)
    sig_slot = end_slot[:nb] - 1 - tail
    p_start = np.empty(n_pieces, np.int64)
    p_len = np.empty(n_pieces, np.int64)
    p_sig = np.full(n_pieces, -1, np.int64)
    p_flo = np.zeros(n_pieces, np.int64)
    p_fhi = np.zeros(n_pieces, np.int64)
    p_start[sig_slot], p_len[sig_slot], p_sig[sig_slot] = b[bi], 1, bi
    p_flo[sig_slot], p_fhi[sig_slot] = bi, bi
    g = sig_slot[gap] - 1
    p_start[g], p_len[g] = prev_end[gap], gap_len[gap]
    p_flo[g], p_fhi[g] = np.where(first_b, cs[bc], prev + 1)[gap], bi[gap]
    t = sig_slot[tail] + 1
    p_start[t], p_len[t] = b[bi][tail] + 1, tail_len[tail]
    p_flo[t], p_fhi[t] = bi[tail] + 1, ce[bc[tail]]
    d = end_slot[nb:] - 1
    p_start[d], p_len[d], p_flo[d], p_fhi[d] = 0, n_bins, cs[dark], ce[dark]
    p_mean = noise * p_len
    p_mean[sig_slot] += mean[bi]
    comp = np.flatnonzero(p_sig < 0)
    p_mean[comp] = p_mean[comp] + _sequential_sums(mean, p_flo[comp], p_fhi[comp])
    cell_of_piece = np.empty(n_pieces, np.int64)  # loud cell index, ascending
    cell_of_piece[sig_slot] = bc
    cell_of_piece[g] = bc[gap]
    cell_of_piece[t] = bc[tail]
    cell_of_piece[d] = dark
    heads = np.flatnonzero(_first_of_groups(cell_of_piece))
    counts = np.diff(np.append(heads, n_pieces))
    sample = cell[cs][cell_of_piece] // n_cells
    p_index = draws.index_within(sample)  # a piece's number within its sample
    # the sums run position by position, so a cell's numbers never depend on the other cells
    pos = np.arange(n_pieces) - heads[cell_of_piece]
    pos = pos.astype(np.int16 if pos.max() < 32767 else np.int64)
    by_pos = np.argsort(pos, kind="stable")  # a radix sort on small integers
    bounds = np.searchsorted(pos[by_pos], np.arange(int(pos.max()) + 2))
    steps = [] if steps is None else steps
    steps.extend(by_pos[bounds[j]:bounds[j + 1]] for j in range(len(bounds) - 1))
    before = _sum_before(p_mean, steps)
    last = heads + counts - 1
    total = before[last] + p_mean[last]
    return (p_start, p_len, p_sig, p_flo, p_fhi, p_mean, sample, p_index, cell_of_piece,
            before, heads, counts, total)


def _loud_peaks(signal: SignalBins, n_bins: int, noise: float, pulses: int, threshold: int,
                seed: int, ids: np.ndarray, n_cells: int, compiled: bool = False) -> Peaks:
    """The peaks of the cells the signal reaches (their peak bins, not yet held to the
    threshold except where that saves work without changing them). ``compiled``: the loops
    in ``kernels`` (the same bytes)."""
    cell, b, mean = signal.cell, signal.bin, signal.mean
    n_sig = len(cell)
    if n_sig == 0:
        z = np.zeros(0, np.int64)
        return Peaks(z, z, z, z)
    k_ = kernels.require() if compiled else None
    new_cell = _first_of_groups(cell)
    steps = []
    build = k_.pieces if k_ is not None else functools.partial(_pieces, steps=steps)
    (p_start, p_len, p_sig, p_flo, p_fhi, p_mean, sample, p_index, cell_of_piece, before,
     heads, counts, total) = build(cell, b, np.ascontiguousarray(mean, np.float64),
                                   int(n_bins), float(noise), int(n_cells),
                                   float(BRIGHT_COUNTS / pulses))
    n_pieces = len(p_start)

    def by_position() -> list:  # steps[j]: the pieces at position j of their cell
        if not steps:
            pos = np.arange(n_pieces) - heads[cell_of_piece]
            pos = pos.astype(np.int16 if pos.max() < 32767 else np.int64)
            by_pos = np.argsort(pos, kind="stable")  # a radix sort on small integers
            bounds = np.searchsorted(pos[by_pos], np.arange(int(pos.max()) + 2))
            steps.extend(by_pos[bounds[j]:bounds[j + 1]] for j in range(len(bounds) - 1))
        return steps

    def uniforms(stream, of_sample, index):  # draws.uniforms(seed, ids[of_sample], ...)
        if k_ is not None:
            return k_.uniforms(draws.stream_key(seed, stream), ids, of_sample, index)
        return draws.uniforms(seed, ids[of_sample], stream, index)

    c_sample = sample[heads]
    p_fire = -np.expm1(-total)
    fired_cell = draws.binomial_inverse(
        np.full(len(heads), pulses), p_fire,
        uniforms(draws.FIRED, c_sample, draws.index_within(c_sample)), compiled)
    # Given F fired pulses, the pieces they fire in are F independent draws of that law: cheap
    # when F is below the cell's number of pieces. Otherwise the chain of binomials, piece by
    # piece; both are the multinomial histogram of first events.
    by_draws = fired_cell < counts
    fired = np.zeros(n_pieces, np.int64)
    em = -np.expm1(-p_mean)  # 1 - exp(-mu): P(a pulse has an arrival in the piece)
    # -- by draws: inverse CDF over each cell's pieces, by bisection within the cell's run
    cells_d = np.flatnonzero(by_draws & (fired_cell > 0))
    if len(cells_d) and k_ is not None:  # the same, on these cells' pieces only
        run = counts[cells_d]
        idx = np.arange(int(run.sum())) + np.repeat(heads[cells_d] - (np.cumsum(run) - run), run)
        ev_sample = np.repeat(c_sample[cells_d], fired_cell[cells_d])
        ev_u = uniforms(draws.FIRST_PIECE, ev_sample, draws.index_within(ev_sample))
        k_.place_fired(np.exp(-before[idx]) * em[idx], cells_d, heads, counts, fired_cell,
                       ev_u * np.repeat(p_fire[cells_d], fired_cell[cells_d]), fired)
    elif len(cells_d):
        # P(a pulse's first event is in the piece), and up to each piece within its cell
        p_first = np.exp(-before) * em
        upto = _sum_before(p_first, by_position()) + p_first
        ev_cell = np.repeat(cells_d, fired_cell[cells_d])
        ev_sample = c_sample[ev_cell]
        ev_u = uniforms(draws.FIRST_PIECE, ev_sample, draws.index_within(ev_sample))
        target = ev_u * p_fire[ev_cell]
        lo, hi = heads[ev_cell], heads[ev_cell] + counts[ev_cell]
        at = np.minimum(_bisect(upto, lo, hi, target, right=True), hi - 1)
        fired += np.bincount(at, minlength=n_pieces)
    # -- the chain, for the cells where most pulses fire: of the pulses that fire at all and
    # have not yet, a piece takes each with chance (1 - exp(-mu)) / (1 - exp(-C_rest)), C_rest
    # the mean from the piece's start to the gate's end
    if (~by_draws).any():
        chain = ~by_draws[cell_of_piece]
        if k_ is not None:
            u = k_.masked_uniforms(draws.stream_key(seed, draws.PIECES), ids, sample, chain)
        else:
            u = np.zeros(n_pieces)
            u[chain] = uniforms(draws.PIECES, sample[chain], draws.index_within(sample[chain]))
        remaining = np.where(by_draws, 0, fired_cell)
        rest = total[cell_of_piece] - before
        if k_ is not None:
            _chain_compiled(k_, chain, em, rest, heads, counts, cell_of_piece, remaining,
                            u, fired)
        for idx in by_position() if k_ is None else ():
            left = remaining[cell_of_piece[idx]]
            live = left > 0
            if not live.all():
                idx, left = idx[live], left[live]
                if len(idx) == 0:
                    continue
            p = -np.expm1(-p_mean[idx]) / -np.expm1(-rest[idx])
            x = draws.binomial_inverse(left, np.minimum(p, 1.0), u[idx], compiled)
            fired[idx] = x
            remaining[cell_of_piece[idx]] -= x
    # signal bins: counts kept, their signal part drawn
    in_sig = np.flatnonzero((p_sig >= 0) & (fired > 0))
    k = p_sig[in_sig]
    share = mean[k] / (mean[k] + noise)
    sig_count = draws.binomial_inverse(
        fired[in_sig], share, uniforms(draws.LABELS, sample[in_sig], p_index[in_sig]),
        compiled)
    # the signal bins' peak per cell
    top_of = _top if k_ is None else (lambda *a: Peaks(*k_.top(*a)))
    sig_top = top_of(cell_of_piece[in_sig], p_start[in_sig], fired[in_sig],
                     np.asarray(sig_count, np.int64), n_bins)
    # stretches (noise and faint signal bins): each event placed by the first-arrival law
    # truncated to its stretch, an event in a faint bin signal with the bin's signal share.
    # A stretch whose events number less than both the threshold and its cell's highest
    # bright bin cannot hold the cell's point (no bin of it can beat that bin, nor make a
    # point where the cell has none): its events are not placed. Each event keeps its number
    # among all the stretches' events of its sample, so the others draw as if it were.
    in_gap = np.flatnonzero((p_sig < 0) & (fired > 0))
    reps = fired[in_gap]
    best_sig = np.zeros(len(heads), np.int64)
    best_sig[sig_top.cell] = sig_top.count
    need = np.maximum(threshold, best_sig[cell_of_piece[in_gap]])
    g_sample = sample[in_gap]
    ends = np.cumsum(reps)
    g_first = np.flatnonzero(_first_of_groups(g_sample))
    g_base = ends - reps - np.repeat((ends - reps)[g_first], np.diff(np.append(g_first,
                                                                              len(in_gap))))
    kept = reps >= need
    in_gap, reps, g_base = in_gap[kept], reps[kept], g_base[kept]
    if k_ is not None:  # the same draws and walks, in two passes over the events
        e_piece, e_index, arg = k_.stretch_events(
            in_gap, reps, g_base, sample, draws.stream_key(seed, draws.STRETCH), ids, em)
        gaps = Peaks(*k_.stretch_peaks(-np.log1p(arg), e_piece, e_index, p_start, p_len, p_flo,
                                       p_fhi, cell_of_piece, sample, b, mean, float(noise),
                                       draws.stream_key(seed, draws.FAINT_LABEL), ids,
                                       int(n_bins)))
        top = Peaks(*k_.merge_top(sig_top.cell, sig_top.bin, sig_top.count,
                                  sig_top.signal_count, gaps.cell, gaps.bin, gaps.count,
                                  gaps.signal_count, n_bins))
        return Peaks(cell[new_cell][top.cell], top.bin, top.count, top.signal_count)
    e_piece = np.repeat(in_gap, reps)
    e_index = np.repeat(g_base, reps) + draws.index_within(np.repeat(np.arange(len(in_gap)),
                                                                      reps))
    e_sample = sample[e_piece]
    t = -np.log1p(-uniforms(draws.STRETCH, e_sample, e_index) * em[e_piece])
    gap_bin, faint = _stretch_bins(t, e_piece, p_start, p_len, p_flo, p_fhi, b, mean,
                                   float(noise))
    gap_label = np.zeros(len(t), np.int64)
    lit = np.flatnonzero(faint >= 0)
    if len(lit):
        f = faint[lit]
        gap_label[lit] = uniforms(draws.FAINT_LABEL, e_sample[lit], e_index[lit]) < (
            mean[f] / (mean[f] + noise))
    gaps = _histogram(cell_of_piece[e_piece], gap_bin, n_bins, gap_label)
    # each cell's peak: its signal bins' or its stretches' (sorted by cell, one of each)
    both = np.concatenate([sig_top.cell, gaps.cell])
    order = np.argsort(both, kind="stable")
    top = _top(both[order], np.concatenate([sig_top.bin, gaps.bin])[order],
               np.concatenate([sig_top.count, gaps.count])[order],
               np.concatenate([sig_top.signal_count, gaps.signal_count])[order], n_bins)
    return Peaks(cell[new_cell][top.cell], top.bin, top.count, top.signal_count)


def _distinct(seed, ids, stream, sample, group, limit) -> np.ndarray:
    """For each element (grouped by sample), an integer uniform in [0, limit) distinct from
    the others of its ``group`` (a sample, or a slot within one): drawn, and a repeat drawn
    again with the sample's next indices. Depends only on each sample's own elements."""
    n = len(sample)
    if n == 0:
        return np.zeros(0, np.int64)
    limit = np.broadcast_to(np.asarray(limit, np.int64), (n,))
    value = np.minimum(np.floor(draws.uniforms(seed, ids[sample], stream,
                                               draws.index_within(sample)) * limit)
                       .astype(np.int64), limit - 1)
    used = np.bincount(sample, minlength=len(ids))  # indices drawn so far, per sample
    while True:
        order = np.lexsort((np.arange(n), value, group))
        g, v = group[order], value[order]
        dup = np.sort(order[np.flatnonzero((g[1:] == g[:-1]) & (v[1:] == v[:-1])) + 1])
        if len(dup) == 0:
            return value
        ds = sample[dup]
        fresh = used[ds] + draws.index_within(ds)
        u = draws.uniforms(seed, ids[ds], stream, fresh)
        value[dup] = np.minimum(np.floor(u * limit[dup]).astype(np.int64), limit[dup] - 1)
        used += np.bincount(ds, minlength=len(ids))


def _quiet_peaks(n_quiet: np.ndarray, loud_global: np.ndarray, n_cells: int, n_bins: int,
                 noise: float, pulses: int, threshold: int, seed: int,
                 ids: np.ndarray, compiled: bool = False) -> Peaks:
    z0 = np.zeros(0, np.int64)
    n = len(n_quiet)
    alpha = float(-np.expm1(-noise))
    pmf = _binomial_pmf(pulses, alpha)
    heavy = float(pmf[threshold:].sum())
    if heavy <= 0.0:
        return Peaks(z0, z0, z0, z0)
    slots = n_quiet * n_bins
    k = draws.binomial_inverse(slots, np.full(n, heavy),
                               draws.uniforms(seed, ids, draws.QUIET_COUNT, np.zeros(n)),
                               compiled)
    sample = np.repeat(np.arange(n), k)
    if len(sample) == 0:
        return Peaks(z0, z0, z0, z0)
    slot = _distinct(seed, ids, draws.QUIET_SLOT, sample, sample, slots[sample])
    # heavy Z from its law truncated to >= threshold
    cdf = np.cumsum(pmf[threshold:])
    cdf /= cdf[-1]
    zu = draws.uniforms(seed, ids[sample], draws.QUIET_Z, draws.index_within(sample))
    z_heavy = threshold + np.minimum(np.searchsorted(cdf, zu, side="right"), len(cdf) - 1)
    # the quiet cells holding them (per sample, quiet numbering), and the light bins there
    q_cell = slot // n_bins
    key = sample * n_cells + q_cell
    cells, first = np.unique(key, return_index=True)
    c_sample = sample[first]
    light = float(pmf[1:threshold].sum()) / float(pmf[:threshold].sum())
    per_sample_cells = np.bincount(c_sample, minlength=n)
    light_slots = per_sample_cells * n_bins
    m = draws.binomial_inverse(light_slots, np.full(n, light),
                               draws.uniforms(seed, ids, draws.LIGHT_COUNT, np.zeros(n)),
                               compiled)
    l_sample = np.repeat(np.arange(n), m)
    l_pos = _distinct(seed, ids, draws.LIGHT_SLOT, l_sample, l_sample, light_slots[l_sample])
    c_offset = np.concatenate([[0], np.cumsum(per_sample_cells)])
    l_key = cells[c_offset[l_sample] + l_pos // n_bins]
    l_bin = l_pos % n_bins
    h_key, h_bin = key, slot % n_bins
    # a light slot where a heavy one already is: the heavy one's Z stands
    taken = np.isin(l_key * n_bins + l_bin, h_key * n_bins + h_bin)
    l_key, l_bin, l_sample = l_key[~taken], l_bin[~taken], l_sample[~taken]
    lcdf = np.cumsum(pmf[1:threshold])
    lcdf /= lcdf[-1] if len(lcdf) and lcdf[-1] > 0 else 1.0
    lu = draws.uniforms(seed, ids[l_sample], draws.LIGHT_Z, draws.index_within(l_sample))
    z_light = 1 + np.minimum(np.searchsorted(lcdf, lu, side="right"), max(len(lcdf) - 1, 0))
    all_key = np.concatenate([h_key, l_key])
    all_bin = np.concatenate([h_bin, l_bin])
    all_z = np.concatenate([z_heavy, z_light])
    # each Z: a uniform subset of the pulses
    arr_slot = np.repeat(np.arange(len(all_key)), all_z)
    arr_sample = all_key[arr_slot] // n_cells
    order = np.argsort(arr_sample, kind="stable")
    arr_slot, arr_sample = arr_slot[order], arr_sample[order]
    pulse = _distinct(seed, ids, draws.PULSE, arr_sample, arr_slot, pulses)
    a_key, a_bin = all_key[arr_slot], all_bin[arr_slot]
    # a pulse's event is its first arrival
    order = np.lexsort((a_bin, pulse, a_key))
    a_key, a_bin, pulse = a_key[order], a_bin[order], pulse[order]
    first = _first_of_groups(a_key * (pulses + 1) + pulse)
    hist = _histogram(a_key[first], a_bin[first], n_bins)
    keep = hist.count >= threshold
    return Peaks(_window_cells(hist.cell[keep], loud_global, n_cells), hist.bin[keep],
                 hist.count[keep], np.zeros(int(keep.sum()), np.int64))


def _window_cells(quiet_key: np.ndarray, loud_global: np.ndarray, n_cells: int) -> np.ndarray:
    """Batch cell numbers of quiet cells given as sample * n_cells + j (the sample's j-th
    quiet cell)."""
    s, j = quiet_key // n_cells, quiet_key % n_cells
    quiet_before = s * n_cells - np.searchsorted(loud_global, s * n_cells)
    gaps = loud_global - np.arange(len(loud_global))
    jj = quiet_before + j
    return jj + np.searchsorted(gaps, jj, side="right")


def _quiet_peaks_every_pulse(n_quiet: np.ndarray, loud_global: np.ndarray, n_cells: int,
                             n_bins: int, noise: float, pulses: int, threshold: int, seed: int,
                             ids: np.ndarray, compiled: bool = False) -> Peaks:
    """The quiet cells' points by following every pulse that fires (one event each): cheaper
    than the heavy-bin route when the noise is so strong that heavy bins are common."""
    p_fire = float(-np.expm1(-noise * n_bins))
    sample = np.repeat(np.arange(len(n_quiet)), n_quiet)
    j = draws.index_within(sample)
    fired = draws.binomial_inverse(np.full(len(sample), pulses), np.full(len(sample), p_fire),
                                   draws.uniforms(seed, ids[sample], draws.QUIET_COUNT, j),
                                   compiled)
    key = np.repeat(sample * n_cells + j, fired)
    ev_sample = key // n_cells
    u = draws.uniforms(seed, ids[ev_sample], draws.QUIET_SLOT, draws.index_within(ev_sample))
    b = np.minimum(np.floor(-np.log1p(-u * p_fire) / noise).astype(np.int64), n_bins - 1)
    hist = _histogram(key, b, n_bins)
    keep = hist.count >= threshold
    return Peaks(_window_cells(hist.cell[keep], loud_global, n_cells), hist.bin[keep],
                 hist.count[keep], np.zeros(int(keep.sum()), np.int64))


def batch_points(signal: SignalBins, n_samples: int, n_cells: int, n_bins: int, noise: float,
                 pulses: int, threshold: int, seed: int, ids: np.ndarray,
                 compiled: bool = False) -> Peaks:
    """Every point (peak bin reaching ``threshold``) of a batch: ``signal`` in batch cell
    numbering, sorted by cell and bin. ``compiled``: the loud cells' loops compiled
    (``kernels``; the same bytes)."""
    loud = _loud_peaks(signal, n_bins, noise, pulses, threshold, seed, ids, n_cells, compiled)
    loud_global = signal.cell[_first_of_groups(signal.cell)]
    n_quiet = n_cells - np.bincount(loud_global // n_cells, minlength=n_samples)
    # the heavy-bin route unless the noise makes heavy bins common (a choice made from the
    # sensor alone, so the same for every batch)
    pmf = _binomial_pmf(pulses, float(-np.expm1(-noise)))
    heavy_route, every_pulse = _quiet_cost(n_cells, n_bins, pmf, pulses, threshold, noise)
    route = _quiet_peaks if heavy_route <= every_pulse else _quiet_peaks_every_pulse
    quiet = route(n_quiet, loud_global, n_cells, n_bins, noise, pulses, threshold, seed, ids,
                  compiled)
    cell = np.concatenate([loud.cell, quiet.cell])
    keep = np.concatenate([loud.count, quiet.count]) >= threshold
    order = np.argsort(cell[keep], kind="stable")
    return Peaks(*(np.concatenate([getattr(loud, f), getattr(quiet, f)])[keep][order]
                   for f in ("cell", "bin", "count", "signal_count")))
