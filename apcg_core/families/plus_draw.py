"""How an APCG+ model draws its returns from the hit logits it reads per box cell (SPEC 7a,
"Drawing"): one rule per model, named in its model.json (``"draw"``), registered here.

* ``threshold``: a cell is a return where its hit logit exceeds tau (the rule of every model
  exported before stop 49, and of a model.json without ``"draw"``).
* ``diffuse-rows``: error diffusion along each box row. The model's hit probabilities are
  calibrated (the share of cells that are returns where the condition cannot tell them apart),
  so a thin wing seen edge-on reads p ~ 0.4-0.7 along a row: thresholded, the whole row is
  drawn, where the simulator's cell-centre rays meet the wing in a share of its cells. Here a
  row (w ascending, from the box's first cell) keeps a cell when the rounded running sum of
  its p steps up: after cell i the row has kept round(p_1 + ... + p_i) cells (half up), so a
  row keeps its summed p, rounded, spread evenly, with no randomness (the standard data have
  none given the condition). p = logistic(logit - tau), 0 where logit - tau <= ``span``.
  Measured on the shipped default (bench/plus_draw.py, 2,001 test-half pairs): 339 / 342
  faithful at 3-6 km against the threshold's 338, mean MMD 0.00455 against 0.00476.

Every reader (numpy, the compiled kernels, the device reader of bench/gpu_generate.py) draws
the same cells, whatever superset of a row's cells it reads: p is looked up in one table of
whole quanta (:data:`ONE` to a certain return) by the logit's step (:data:`STEPS_PER_LOGIT`),
indexed by a floor of a float64 difference that every reader computes alike, and the running
sums are integers, exact in any order (no exp, no float sum, whose rounding could differ
between numpy, numba and torch).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import InputError

ONE = 1 << 24  # quanta of a certain return: p is resolved to 6e-8, far below any fit's error
HALF = ONE >> 1
STEPS_PER_LOGIT = 1024  # p's table steps a logit (a power of two: z * 1024 is exact)
TOP_LOGIT = 20.0  # above span + this, p rounds to ONE (logistic(17) > 1 - 2^-25)
# p = 0.0025 below it. Scored on the shipped default (2,001 test-half pairs, the decoys
# prepared once, as `bench/plus_draw.py --draw diffuse-rows --span S` does; stop 49): span -3
# (p 0.047) left one 3-6 km pair unfaithful that -6 and -9 keep (339 / 342; every band alike
# at -6 and -9: the draw has converged); the compiled reader cost 0.0158, 0.0167, 0.0183 ms
# a cloud at -3, -6, -9 (threshold 0.0115; 4,096 random conditions, one process)
DEFAULT_SPAN = -6.0
# the candidate rows and columns are those above span less this: a bilinear read of values
# at most span may round a few ulp above it, and such a cell must still be read
ROW_SLACK = 1e-6


@dataclass(frozen=True)
class Draw:
    """One drawing rule: ``name`` (its model.json spelling) and, for the diffused draw, the
    logit ``span`` (relative to tau) below which a cell's p is 0."""

    name: str
    span: float | None = None

    @property
    def diffused(self) -> bool:
        return self.span is not None

    def record(self) -> dict:
        """What model.json holds for this rule."""
        return {"rule": self.name} if not self.diffused else {"rule": self.name,
                                                               "span": self.span}

    def at_sub_rays(self) -> Draw:
        """The rule for the K x K sub-rays the photon stage reads at a finer lidar
        (sensor/generated.py): the threshold, whatever the model's own. A cell's photons
        depend on which cells any sub-ray reaches, and the true sub-ray hits are compact; the
        diffused draw keeps a halo's share of p as hits spread evenly along its rows, which
        reach more cells. Cells with a target return at 1550nm-night, simulated (embree, 4 x 4
        sub-rays) against the shipped default's sub-rays thresholded / diffused (the cases of
        tests/test_lidar_any.py and three more, stop 49): A320neo at 4 km 647 against 603 /
        725, at 5.5 km 380 / 340 / 403, G650ER at 3.5 km 529 / 521 / 661, Matrice 300 RTK at
        200 m 629 / 606 / 706, Mavic 3 at 300 m 63 / 61 / 64."""
        return THRESHOLD

    def row_floor(self, tau: float) -> float:
        """The hit logit a sheet column must exceed for its row's cells to be read."""
        return tau if not self.diffused else tau + self.span - ROW_SLACK

    @cached_property
    def quanta(self) -> np.ndarray:
        """p in quanta for each logit step above span: entry k holds round(ONE logistic(span +
        (k + 1/2) / STEPS_PER_LOGIT)); empty for the threshold rule."""
        if not self.diffused:
            return np.zeros(0, np.int64)
        k = np.arange(int((TOP_LOGIT - self.span) * STEPS_PER_LOGIT) + 1)
        z = self.span + (k + 0.5) / STEPS_PER_LOGIT
        q = np.floor(ONE / (1.0 + np.exp(-z)) + 0.5).astype(np.int64)
        q[-1] = ONE
        q.flags.writeable = False
        return q

    def cell_quanta(self, hit: np.ndarray, tau: float) -> np.ndarray:
        """Each cell's p in quanta from its hit logit (float64): the table's entry at
        floor((logit - tau - span) STEPS_PER_LOGIT), 0 where logit - tau <= span (and NaN)."""
        z = np.asarray(hit, np.float64) - tau
        live = z > self.span
        out = np.zeros(len(z), np.int64)
        k = np.floor((z[live] - self.span) * STEPS_PER_LOGIT)
        out[live] = self.quanta[np.minimum(k, len(self.quanta) - 1).astype(np.int64)]
        return out

    def keep(self, sample: np.ndarray, h: np.ndarray, hit: np.ndarray, tau: float):
        """Which of the cells (in order (sample, h, w ascending): a row is a run of equal
        (sample, h)) are returns, from their hit logits."""
        hit = np.asarray(hit)
        if not self.diffused:
            return hit > tau
        q = self.cell_quanta(hit, tau)
        sample, h = np.asarray(sample), np.asarray(h)
        starts = np.ones(len(q), bool)
        starts[1:] = (sample[1:] != sample[:-1]) | (h[1:] != h[:-1])
        return stepped_up(q, np.flatnonzero(starts)[np.cumsum(starts) - 1])


def stepped_up(q, row_first):
    """The diffused draw's keep over cells of quanta ``q`` (int64), each in the row whose
    first cell is at index ``row_first``: round(running sum) steps up (integers: exact, in any
    order of summation). numpy arrays or torch tensors alike (the device reader's)."""
    total = q.cumsum(0)
    before = total - q
    base = before[row_first]
    return (total - base + HALF) // ONE > (before - base + HALF) // ONE


THRESHOLD = Draw("threshold")
DIFFUSE_ROWS = Draw("diffuse-rows", DEFAULT_SPAN)
DRAWS = {d.name: d for d in (THRESHOLD, DIFFUSE_ROWS)}
DEFAULT = DIFFUSE_ROWS  # what `apcg export` writes for a new APCG+ model


def draw_of(record, where: str = "model.json") -> Draw:
    """The rule a model.json's ``"draw"`` names (None: ``threshold``, every older model's)."""
    if record is None:
        return THRESHOLD
    accepted = ", ".join(DRAWS)
    if not isinstance(record, dict) or not isinstance(record.get("rule"), str):
        raise InputError(f"{where}: 'draw' must be a table with a 'rule' (one of {accepted}), "
                         f"got {record!r}")
    rule = record["rule"]
    if rule not in DRAWS:
        raise InputError(f"{where}: draw rule {rule!r} is not one of {accepted}")
    unknown = sorted(set(record) - {"rule", "span"})
    if unknown:
        raise InputError(f"{where}: draw has unknown keys {unknown} (accepted: rule, span)")
    if not DRAWS[rule].diffused:
        if "span" in record:
            raise InputError(f"{where}: the {rule} draw takes no span")
        return DRAWS[rule]
    span = record.get("span", DEFAULT_SPAN)
    if not (isinstance(span, (int, float)) and not isinstance(span, bool)
            and np.isfinite(span) and -12.0 <= span <= 0.0):
        raise InputError(f"{where}: draw span must be a logit in -12 .. 0 (below tau; "
                         f"default {DEFAULT_SPAN}), got {span!r}")
    return Draw(rule, float(span))


__all__ = ["DEFAULT", "DRAWS", "Draw", "HALF", "ONE", "STEPS_PER_LOGIT", "THRESHOLD",
           "draw_of", "stepped_up"]
