"""Random draws of the photon stage that do not depend on how samples are batched.

Every uniform is a hash of (seed, sample id, stream, index): a counter-based generator (the
SplitMix64 output function, Steele, Lea & Flood, OOPSLA 2014, applied twice to the packed
counter). A sample's draws are then the same whether it is simulated alone, in a batch, in
another worker or on another machine, and a whole batch draws in a few numpy calls instead of
a generator per sample. Each use of randomness has its own stream number.
"""

from __future__ import annotations

import math

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_TO_UNIT = 2.0**-53

# stream numbers: one per kind of draw (a new kind takes a new number)
PIECES, LABELS, STRETCH, QUIET_COUNT, QUIET_SLOT, QUIET_Z, LIGHT_COUNT, LIGHT_SLOT, LIGHT_Z, \
    PULSE, FIRED, FIRST_PIECE, FAINT_LABEL = range(1, 14)


def _mix(x: np.ndarray) -> np.ndarray:
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


def stream_key(seed: int, stream: int) -> np.uint64:
    """The mix of the seed and the stream that every uniform of the stream starts from."""
    with np.errstate(over="ignore"):
        return _mix(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) * _GOLDEN + np.uint64(stream))


def uniforms(seed: int, sample_id: np.ndarray, stream: int, index: np.ndarray) -> np.ndarray:
    """One uniform in (0, 1) per (sample id, index) of ``stream``, float64."""
    with np.errstate(over="ignore"):
        key = stream_key(seed, stream)
        a = _mix(key ^ (np.asarray(sample_id).astype(np.uint64) * _GOLDEN))
        x = _mix(a + (np.asarray(index).astype(np.uint64) + np.uint64(1)) * _GOLDEN)
    return ((x >> np.uint64(11)).astype(np.float64) + 0.5) * _TO_UNIT


_lgamma = np.frompyfunc(math.lgamma, 1, 1)


def binomial_inverse(n: np.ndarray, p: np.ndarray, u: np.ndarray,
                     compiled: bool = False) -> np.ndarray:
    """Binomial(n, p) by inverting its CDF at the uniforms ``u`` (one each), elementwise and
    exact to double precision. Counted from 0, or for a large mean from 12 standard
    deviations below it (the mass below, < 1e-32, is not drawn). ``compiled``: the walk up
    the CDF in the compiled loop (``kernels.binomial_walk``, the same bytes)."""
    n = np.asarray(n, np.int64)
    p = np.clip(np.asarray(p, np.float64), 0.0, 1.0)
    u = np.asarray(u, np.float64)
    flip = p > 0.5
    q = np.where(flip, 1.0 - p, p)
    x = np.zeros(len(n), np.int64)
    live = np.flatnonzero((n > 0) & (q > 0))
    if len(live) == 0:
        return np.where(flip, n - x, x)
    nn, qq, uu = n[live], q[live], u[live]
    mean = nn * qq
    start = np.maximum(0, np.floor(mean - 12.0 * np.sqrt(mean * (1.0 - qq)))).astype(np.int64)
    start[mean < 16.0] = 0
    # log P(X = start) = start log q + (n - start) log(1 - q) (+ the log of the binomial
    # coefficient): with start 0 the first term is -0.0 (0 times a log q < 0), which adds
    # nothing to the second, bit for bit, so log q is taken only where start > 0
    log_pk = (nn - start) * np.log1p(-qq)
    big = start > 0
    if big.any():
        s, m = start[big], nn[big]
        log_pk[big] = s * np.log(qq[big]) + log_pk[big]
        log_pk[big] += (_lgamma(m + 1) - _lgamma(s + 1) - _lgamma(m - s + 1)).astype(float)
    pk = np.exp(log_pk)
    cdf = pk.copy()
    k = start.copy()
    ratio = qq / (1.0 - qq)
    if compiled:
        from .kernels import require

        require().binomial_walk(nn, ratio, uu, pk, cdf, k)
        x[live] = k
        return np.where(flip, n - x, x)
    act = np.flatnonzero((uu > cdf) & (k < nn))
    while len(act):
        k[act] += 1
        pk[act] *= (nn[act] - k[act] + 1) / k[act] * ratio[act]
        cdf[act] += pk[act]
        act = act[(uu[act] > cdf[act]) & (k[act] < nn[act])]
    x[live] = k
    return np.where(flip, n - x, x)


def index_within(group: np.ndarray) -> np.ndarray:
    """For a sorted group label per element, each element's index within its group."""
    n = len(group)
    if n == 0:
        return np.zeros(0, np.int64)
    first = np.empty(n, bool)
    first[0] = True
    first[1:] = group[1:] != group[:-1]
    starts = np.flatnonzero(first)
    return np.arange(n) - np.repeat(starts, np.diff(np.append(starts, n)))
