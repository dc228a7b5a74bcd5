"""Compiled loops for the photon stage (numba), beside the numpy code they replace.

The batched points path (``stage.signal_bins``, ``points._loud_peaks``) spends its time in a
few loops that numpy runs as many passes over large arrays: spreading every sub-ray's return
over the bins its Gaussian reaches and adding them up per (cell, bin), the sums of a cell's
earlier pieces, the walk of the binomial sampler's inverse CDF and the bisection that places
each fired pulse in its cell's pieces, the placing of a stretch's events in its bins, and the
histograms and peaks of a cell's bins. Here each is one pass. Every float64 operation is the
numpy code's, operand for operand and in the same order: products, quotients and sums of two
operands only, each rounded (numba contracts nothing
into a fused multiply-add without ``fastmath``, which is never set here), and every exp, log,
expm1 or log1p stays in numpy, computed before or between the loops on the same values (a
compiled ``exp`` need not be the one numpy calls). ``tests/test_photon_kernels.py`` checks that
both paths give the same bytes.

The core imports with numpy alone (the add-on runs in Blender's Python, which has no numba):
numba is imported only when the kernels load (``apcg_core/kernel_loader.py``, the one loader
of the core's compiled loops), when it is installed and allowed, and the numpy code runs
otherwise, same bytes, slower. ``APCG_KERNELS`` in the environment is read as for the build's
ray kernels (``dataset_builder/kernels.py``): ``numpy`` never loads them, ``compiled`` loads
them at the first call; otherwise a process starts on numpy and loads them once it has put
:data:`SWITCH_HITS` sub-ray hits through the stage. Compiled code is cached
beside this file (``__pycache__``; numba's per-user cache where that is read-only).
"""

from __future__ import annotations

import numpy as np

from ..kernel_loader import ENV, KernelSet, Loader

__all__ = ["ENV", "SWITCH_HITS", "enabled", "expect", "loaded", "require",
           "use_for"]
# Sub-ray hits a process puts through the stage on the numpy path before it loads the
# kernels: loading numba and reading the cache costs about 0.5 s (dataset_builder/kernels.py),
# and the numpy path's extra cost over the kernels is about 2.5 us a hit (bench/photons.py,
# docs/SCALE.md "The photon stage"), so after ~200 000 hits the numpy path has spent what
# loading costs (rent, then buy). One `apcg simulate` of a few conditions never loads them.
SWITCH_HITS = 200_000


# the one loader of this set (apcg_core/kernel_loader.py); _compile is defined below
_loader = Loader(lambda: _compile(), "the photon stage's compiled kernels", SWITCH_HITS)
enabled, loaded, use_for, require, expect = (_loader.enabled, _loader.loaded,
                                             _loader.use_for, _loader.require, _loader.expect)


def _compile() -> KernelSet:
    from numba import njit

    jit = njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)

    @jit
    def ascending(a):
        """Whether ``a`` never decreases (numpy: not (diff(a) < 0).any())."""
        for i in range(1, a.shape[0]):
            if a[i] < a[i - 1]:
                return False
        return True

    @jit
    def spread_start(range_m, first_bin, r_r, half, rows):
        """stage.signal_bins' place of each return's window: lo = floor(u - half) and the
        table row rint((u - half - lo) rows), u = range / r_r - first bin, as numpy rounds
        them."""
        n = range_m.shape[0]
        lo = np.empty(n, np.int64)
        row = np.empty(n, np.int64)
        for i in range(n):
            start = (range_m[i] / r_r - np.float64(first_bin[i])) - half
            f = np.floor(start)
            row[i] = np.int64(np.rint((start - f) * rows))
            lo[i] = np.int64(f)
        return lo, row

    @jit
    def spread_sum(cell, lo, row, mean, weights, n_bins):
        """stage.signal_bins' spread and sum: hit i's mean times weights[row[i], j] in bin
        lo[i] + j, kept when the bin is in the gate and the product is > 0, then added up
        per (cell, bin) in the order of the hits (as numpy's bincount adds its entries).
        ``cell`` sorted. Returns (cell, bin, total) of the slots with total > 0 (every kept
        slot: a sum of positive terms), by cell then bin."""
        n = cell.shape[0]
        nb = weights.shape[1]
        cap = 0  # per cell, the gate's bins its hits' windows span: the output's bound
        i = 0
        while i < n:
            base = lo[i]
            top = lo[i]
            j = i
            while j < n and cell[j] == cell[i]:
                base = min(base, lo[j])
                top = max(top, lo[j])
                j += 1
            span = min(top + nb, n_bins) - max(base, 0)
            cap += max(span, 0)
            i = j
        out_cell = np.empty(cap, np.int64)
        out_bin = np.empty(cap, np.int64)
        out_total = np.empty(cap)
        buf = np.zeros(64)
        m_out = 0
        i = 0
        while i < n:
            c = cell[i]
            base = lo[i]
            top = lo[i]
            j = i
            while j < n and cell[j] == c:
                if lo[j] < base:
                    base = lo[j]
                if lo[j] > top:
                    top = lo[j]
                j += 1
            width = top - base + nb
            if width > buf.shape[0]:
                buf = np.zeros(2 * width)
            first = width
            last = -1
            for h in range(i, j):
                off = lo[h] - base
                mh = mean[h]
                r = row[h]
                for t in range(nb):
                    b = lo[h] + t
                    if b < 0 or b >= n_bins:
                        continue
                    m = mh * weights[r, t]
                    if m > 0:
                        buf[off + t] += m
                        if off + t < first:
                            first = off + t
                        if off + t > last:
                            last = off + t
            for k in range(first, last + 1):
                if buf[k] > 0:
                    out_cell[m_out] = c
                    out_bin[m_out] = base + k
                    out_total[m_out] = buf[k]
                    m_out += 1
                    buf[k] = 0.0
            i = j
        return out_cell[:m_out], out_bin[:m_out], out_total[:m_out]

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
    def chain_prepare(j, active, heads, counts, remaining, q, log1pq):
        """Position j of points._loud_peaks' chain, up to the exp: for each active cell with
        pulses left and a piece at position j, the piece, the sampler's start and (n - start)
        log(1 - q) as draws.binomial_inverse makes them (n the pulses left, q = min(p, 1 - p);
        start -1 where q is not > 0: no walk). With start > 0 the caller adds start log q and
        the lgamma terms, in numpy; with start 0 that term is -0.0 and adds nothing."""
        n = active.shape[0]
        idx = np.empty(n, np.int64)
        start = np.empty(n, np.int64)
        log_pk = np.zeros(n)
        m = 0
        for a in range(n):
            c = active[a]
            left = remaining[c]
            if left <= 0 or j >= counts[c]:
                continue
            piece = heads[c] + j
            idx[m] = piece
            qq = q[piece]
            if qq > 0:
                mean = np.float64(left) * qq
                st = 0
                if not (mean < 16.0):
                    v = np.floor(mean - 12.0 * np.sqrt(mean * (1.0 - qq)))
                    if v > 0:
                        st = np.int64(v)
                start[m] = st
                log_pk[m] = np.float64(left - st) * log1pq[piece]
            else:
                start[m] = -1
            m += 1
        return idx[:m], start[:m], log_pk[:m]

    @jit
    def chain_finish(idx, start, pk, cell_of_piece, remaining, q, flip, u, fired):
        """The rest of position j: each piece's binomial walk (draws.binomial_inverse's, its
        ratio q / (1 - q) one rounded quotient as there), its count of fired pulses, and its
        cell's pulses left."""
        for a in range(idx.shape[0]):
            piece = idx[a]
            c = cell_of_piece[piece]
            left = remaining[c]
            x = 0
            if start[a] >= 0:
                kk = start[a]
                p = pk[a]
                cdf = p
                r = q[piece] / (1.0 - q[piece])
                uu = u[piece]
                while uu > cdf and kk < left:
                    kk += 1
                    p *= np.float64(left - kk + 1) / np.float64(kk) * r
                    cdf += p
                x = kk
            if flip[piece]:
                x = left - x
            fired[piece] = x
            remaining[c] = left - x

    @jit
    def pieces(cell, b, mean, n_bins, noise, n_cells, bright_min):
        """points._pieces in one pass: per cell (``cell`` sorted, its signal bins ``b``
        ascending) each bright signal bin (mean >= ``bright_min``) a piece, and each run of
        bins between them (before the first, after the last; the whole gate where there is
        none) one piece of noise and faint bins. Per piece: start, length, bright bin index
        (-1 for the others), faint bins [flo, fhi), mean, sample, number within the sample,
        loud cell index, and the sum of the cell's earlier pieces' means; per loud cell:
        first piece, pieces, and the whole gate's mean."""
        n = cell.shape[0]
        cap = 0  # the pieces and the cells, counted first: no array longer than it must be
        n_loud = 0
        i = 0
        while i < n:
            x = 0
            j = i
            while j < n and cell[j] == cell[i]:
                if mean[j] >= bright_min:
                    cap += 1 + (b[j] > x)
                    x = b[j] + 1
                j += 1
            cap += x < n_bins
            n_loud += 1
            i = j
        p_start = np.empty(cap, np.int64)
        p_len = np.empty(cap, np.int64)
        p_sig = np.empty(cap, np.int64)
        p_flo = np.empty(cap, np.int64)
        p_fhi = np.empty(cap, np.int64)
        p_mean = np.empty(cap)
        sample = np.empty(cap, np.int64)
        p_index = np.empty(cap, np.int64)
        cell_of_piece = np.empty(cap, np.int64)
        before = np.empty(cap)
        heads = np.empty(n_loud, np.int64)
        counts = np.empty(n_loud, np.int64)
        total = np.empty(n_loud)
        m = 0
        nc = 0
        prev_sample = -1
        within = 0
        i = 0
        while i < n:
            j = i
            while j < n and cell[j] == cell[i]:
                j += 1
            s = cell[i] // n_cells
            if s != prev_sample:
                within = 0
                prev_sample = s
            h = m
            x = 0  # the first bin not yet in a piece
            flo = i  # the first faint bin not yet in a piece
            for k in range(i, j + 1):
                if k < j and not (mean[k] >= bright_min):
                    continue
                stop = b[k] if k < j else n_bins
                if stop > x:  # the run [x, stop): noise and the faint bins flo .. k - 1
                    acc = 0.0
                    for f in range(flo, k):
                        acc = acc + mean[f]
                    p_start[m] = x
                    p_len[m] = stop - x
                    p_sig[m] = -1
                    p_flo[m] = flo
                    p_fhi[m] = k
                    p_mean[m] = noise * np.float64(stop - x) + acc
                    m += 1
                if k < j:
                    p_start[m] = b[k]
                    p_len[m] = 1
                    p_sig[m] = k
                    p_flo[m] = k
                    p_fhi[m] = k
                    p_mean[m] = noise * np.float64(1) + mean[k]
                    m += 1
                    x = b[k] + 1
                    flo = k + 1
            heads[nc] = h
            counts[nc] = m - h
            for q in range(h, m):
                sample[q] = s
                p_index[q] = within
                within += 1
                cell_of_piece[q] = nc
                if q == h:
                    before[q] = 0.0
                else:
                    before[q] = before[q - 1] + p_mean[q - 1]
            total[nc] = before[m - 1] + p_mean[m - 1]
            nc += 1
            i = j
        return (p_start[:m], p_len[:m], p_sig[:m], p_flo[:m], p_fhi[:m], p_mean[:m],
                sample[:m], p_index[:m], cell_of_piece[:m], before[:m], heads[:nc],
                counts[:nc], total[:nc])

    @jit
    def mix(x):
        """draws._mix: SplitMix64's finaliser on uint64, wrapping as numpy's does."""
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))

    @jit
    def uniform(sample_key, index):
        """The uniform of draw ``index`` from a sample's key (``mix(key ^ id * golden)``)."""
        x = mix(sample_key + (np.uint64(index) + np.uint64(1)) * np.uint64(0x9E3779B97F4A7C15))
        return (np.float64(x >> np.uint64(11)) + 0.5) * 1.1102230246251565e-16

    @jit
    def sample_key(key, sample_id):
        return mix(key ^ (np.uint64(sample_id) * np.uint64(0x9E3779B97F4A7C15)))

    @jit
    def uniforms(key, ids, sample, index):
        """draws.uniforms(seed, ids[sample], stream, index) with ``key`` the seed's and the
        stream's mix: the same SplitMix64 steps on uint64, wrapping as numpy's do."""
        out = np.empty(sample.shape[0])
        for i in range(sample.shape[0]):
            out[i] = uniform(sample_key(key, ids[sample[i]]), index[i])
        return out

    @jit
    def masked_uniforms(key, ids, sample, mask):
        """Where ``mask``: uniforms(key, ids, sample[mask], index_within(sample[mask])) (sample
        sorted), 0.0 elsewhere: the masked elements numbered within their sample in order."""
        n = sample.shape[0]
        out = np.zeros(n)
        at = 0
        last = -1
        a = np.uint64(0)
        for i in range(n):
            if not mask[i]:
                continue
            if sample[i] != last:
                last, at = sample[i], 0
                a = sample_key(key, ids[last])
            out[i] = uniform(a, at)
            at += 1
        return out

    @jit
    def place_fired(p_first, cells, heads, counts, n_events, target, fired):
        """points._loud_peaks' "by draws" route for the cells ``cells`` (ascending): their
        pieces' P(first event) ``p_first`` (the cells' runs, in order), summed up within each
        cell as points._sum_before(p_first) + p_first sums them (each sum the previous sum plus one
        term), and each of the cell's ``n_events[c]`` targets (in that order) placed at
        min(searchsorted(upto, target, 'right'), pieces - 1), counted into ``fired``."""
        upto = np.empty(p_first.shape[0])
        at = 0
        e = 0
        for i in range(cells.shape[0]):
            c = cells[i]
            m = counts[c]
            run = 0.0
            for _ in range(m):
                run = run + p_first[at]
                upto[at] = run
                at += 1
            first = at - m
            for _ in range(n_events[c]):
                v = target[e]
                e += 1
                a = first
                b = at
                while a < b:
                    mid = (a + b) // 2
                    if upto[mid] <= v:
                        a = mid + 1
                    else:
                        b = mid
                if a > at - 1:
                    a = at - 1
                fired[heads[c] + a - first] += 1

    @jit
    def score(count, b, n_bins):
        """points._top's order of a cell's bins: the most counts, then the nearest bin."""
        return np.int64(count) * (n_bins + 1) + (n_bins - b)

    @jit
    def peak_arrays(n):
        """Room for n peaks: cell, bin, count, signal count."""
        return (np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64),
                np.empty(n, np.int64))

    @jit
    def top(cell, b, count, sig, n_bins):
        """points._top: per run of equal ``cell`` (sorted; a (cell, bin) at most once), the
        entry of the highest count * (n_bins + 1) + n_bins - bin: the most counts, then the
        nearest bin. Returns the chosen entries' (cell, bin, count, signal count)."""
        n = cell.shape[0]
        oc, ob, on, os_ = peak_arrays(n)
        m = 0
        i = 0
        while i < n:
            best = i
            best_score = score(count[i], b[i], n_bins)
            j = i + 1
            while j < n and cell[j] == cell[i]:
                s_j = score(count[j], b[j], n_bins)
                if s_j > best_score:
                    best, best_score = j, s_j
                j += 1
            oc[m], ob[m], on[m], os_[m] = cell[best], b[best], count[best], sig[best]
            m += 1
            i = j
        return oc[:m], ob[:m], on[:m], os_[:m]

    @jit
    def histogram_top(cell, b, label, n_bins):
        """points._histogram: the counts of events (and of the signal ones, ``label`` 1) per
        (cell, bin) (``cell`` sorted, bins in any order), reduced to each cell's peak as
        points._top reduces them (the most counts, then the nearest bin)."""
        n = cell.shape[0]
        oc, ob, on, os_ = peak_arrays(n)
        hist = np.zeros(n_bins, np.int64)
        hsig = np.zeros(n_bins, np.int64)
        m = 0
        i = 0
        while i < n:
            j = i
            while j < n and cell[j] == cell[i]:
                hist[b[j]] += 1
                hsig[b[j]] += label[j]
                j += 1
            best_b = -1
            best_n = 0
            for k in range(i, j):  # each bin's count is final: the peak, then clear
                bk = b[k]
                h = hist[bk]
                if h > best_n or (h == best_n and h > 0 and bk < best_b):
                    best_n, best_b = h, bk
            oc[m], ob[m], on[m], os_[m] = cell[i], best_b, best_n, hsig[best_b]
            for k in range(i, j):
                hist[b[k]] = 0
                hsig[b[k]] = 0
            m += 1
            i = j
        return oc[:m], ob[:m], on[:m], os_[:m]

    @jit
    def stretch_events(pieces, reps, base, sample, key, ids, em):
        """points._loud_peaks' events of the stretches ``pieces`` (``reps`` each, numbered
        from ``base`` within their sample): each one's piece, number, and -u em (u its
        uniform of ``key``'s stream, em its piece's 1 - exp(-M)), the log1p's argument of
        its first-arrival mean."""
        n = 0
        for g in range(pieces.shape[0]):
            n += reps[g]
        e_piece = np.empty(n, np.int64)
        e_index = np.empty(n, np.int64)
        arg = np.empty(n)
        e = 0
        for g in range(pieces.shape[0]):
            piece = pieces[g]
            a = sample_key(key, ids[sample[piece]])
            for r in range(reps[g]):
                e_piece[e] = piece
                e_index[e] = base[g] + r
                arg[e] = -uniform(a, base[g] + r) * em[piece]
                e += 1
        return e_piece, e_index, arg

    @jit
    def stretch_peaks(t, e_piece, e_index, p_start, p_len, p_flo, p_fhi, cell_of_piece, sample,
                      b, mean, noise, key, ids, n_bins):
        """points._loud_peaks' stretch events from their first-arrival means ``t`` (events
        grouped by piece) to each cell's peak: each event walked to its bin as
        points._stretch_bins walks it, an event in a faint bin labelled signal when its
        uniform of ``key``'s stream is below the bin's signal share, and the histogram's
        peak per cell as histogram_top finds it. A piece's events are walked in order of
        ``t`` in one pass: the sums along the walk are the same floats for every event."""
        n = t.shape[0]
        gap_cell = np.empty(n, np.int64)
        gap_bin = np.empty(n, np.int64)
        label = np.zeros(n, np.int64)
        order = np.empty(n, np.int64)
        i = 0
        while i < n:
            piece = e_piece[i]
            j = i
            while j < n and e_piece[j] == piece:
                # insertion sort of the piece's events by t (a few each)
                k = j
                while k > i and t[order[k - 1]] > t[j]:
                    order[k] = order[k - 1]
                    k -= 1
                order[k] = j
                j += 1
            x = p_start[piece]
            end = x + p_len[piece]
            flo = p_flo[piece]
            fhi = p_fhi[piece]
            f = flo
            cum = 0.0
            c = cell_of_piece[piece]
            a_key = sample_key(key, ids[sample[piece]])
            for q in range(i, j):
                e = order[q]
                te = t[e]
                gap_cell[e] = c
                while True:
                    if f < fhi:
                        a = cum + noise * np.float64(b[f] - x)
                        if a > te:  # in the run of noise before faint bin f
                            off = np.floor((te - cum) / noise)
                            lim = np.float64(b[f] - 1 - x)
                            if off > lim:
                                off = lim
                            gap_bin[e] = x + np.int64(off)
                            break
                        after = a + (noise + mean[f])
                        if after > te:  # in faint bin f
                            gap_bin[e] = b[f]
                            if uniform(a_key, e_index[e]) < mean[f] / (mean[f] + noise):
                                label[e] = 1
                            break
                        cum = after
                        x = b[f] + 1
                        f += 1
                    elif fhi > flo and (x >= end or not (noise > 0)):
                        gap_bin[e] = b[fhi - 1]  # no run after the last faint bin
                        if uniform(a_key, e_index[e]) < mean[fhi - 1] / (mean[fhi - 1] + noise):
                            label[e] = 1
                        break
                    else:
                        off = np.floor((te - cum) / noise)
                        lim = np.float64(end - 1 - x)
                        if off > lim:
                            off = lim
                        gap_bin[e] = x + np.int64(off)
                        break
            i = j
        return histogram_top(gap_cell, gap_bin, label, n_bins)

    @jit
    def merge_top(c1, b1, n1, s1, c2, b2, n2, s2, n_bins):
        """points._top of two peak lists (each sorted by cell, one entry a cell, no bin in
        both) concatenated and stably sorted by cell: per cell, the better of its entries."""
        n = c1.shape[0] + c2.shape[0]
        oc, ob, on, os_ = peak_arrays(n)
        i = 0
        j = 0
        m = 0
        while i < c1.shape[0] or j < c2.shape[0]:
            both = i < c1.shape[0] and j < c2.shape[0] and c1[i] == c2[j]
            second = (i >= c1.shape[0] or (j < c2.shape[0] and c2[j] < c1[i])
                      or (both and score(n2[j], b2[j], n_bins) > score(n1[i], b1[i], n_bins)))
            if second:
                oc[m], ob[m], on[m], os_[m] = c2[j], b2[j], n2[j], s2[j]
            else:
                oc[m], ob[m], on[m], os_[m] = c1[i], b1[i], n1[i], s1[i]
            i += 1 if both or not second else 0
            j += 1 if both or second else 0
            m += 1
        return oc[:m], ob[:m], on[:m], os_[:m]

    return KernelSet(place_fired=place_fired, masked_uniforms=masked_uniforms, top=top,
                     histogram_top=histogram_top, merge_top=merge_top, pieces=pieces,
                     stretch_events=stretch_events,
                     stretch_peaks=stretch_peaks,
                     uniforms=uniforms, spread_sum=spread_sum, ascending=ascending,
                     spread_start=spread_start,
                     binomial_walk=binomial_walk,
                     chain_prepare=chain_prepare, chain_finish=chain_finish)

