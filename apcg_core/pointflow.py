"""PointFlow-protocol set metrics over the Chamfer distance: MMD-CD, COV-CD, 1-NNA-CD.

Named apart from :mod:`apcg_core.metrics` on purpose: there "MMD" is the paper's maximum mean
discrepancy between two clouds; here MMD-CD is the *minimum matching distance* between two
sets of clouds (Achlioptas et al. 2018; Yang et al. 2019). Clouds are (N, 3) arrays in metres;
empty clouds cannot be matched and are counted, not scored.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .metrics import CHUNK_ELEMENTS, _centred_pair, _sq_dist_chunks, as_cloud


def _nn_sq(a: np.ndarray, b: np.ndarray, chunk: int) -> np.ndarray:
    """Squared distance from each point of a to its nearest point of b."""
    return np.concatenate([d2.min(axis=1) for d2 in _sq_dist_chunks(a, b, chunk)])


def chamfer_distance(a, b, max_points: int | None = None, seed: int = 0,
                     chunk: int = CHUNK_ELEMENTS) -> float | None:
    """Chamfer distance: mean squared NN distance a->b plus b->a (m^2). None if a cloud is empty."""
    a, b = _centred_pair(a, b, max_points, seed)
    if len(a) == 0 or len(b) == 0:
        return None
    return float(_nn_sq(a, b, chunk).mean() + _nn_sq(b, a, chunk).mean())


def chamfer_matrix(xs: Sequence, ys: Sequence, **kwargs) -> np.ndarray:
    """Chamfer distance between every cloud of xs and every cloud of ys (NaN where empty)."""
    out = np.full((len(xs), len(ys)), np.nan)
    for i, x in enumerate(xs):
        for j, y in enumerate(ys):
            v = chamfer_distance(x, y, **kwargs)
            if v is not None:
                out[i, j] = v
    return out


@dataclass
class PointFlowScores:
    mmd_cd: float  # minimum matching distance (m^2): mean over references of the closest sample
    cov_cd: float  # coverage: fraction of references that are some sample's nearest reference
    nna_cd: float  # 1-NN accuracy of telling samples from references (0.5 is ideal)
    n_generated: int
    n_reference: int
    n_empty_generated: int
    n_empty_reference: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def pointflow_scores(generated: Sequence, reference: Sequence, **kwargs) -> PointFlowScores:
    """MMD-CD, COV-CD and 1-NNA-CD of a generated set against a reference set."""
    gen = [as_cloud(g) for g in generated]
    ref = [as_cloud(r) for r in reference]
    g_ok = [g for g in gen if len(g)]
    r_ok = [r for r in ref if len(r)]
    if len(g_ok) < 1 or len(r_ok) < 1 or len(g_ok) + len(r_ok) < 3:
        raise InputError(f"PointFlow metrics need non-empty clouds in both sets (got "
                         f"{len(g_ok)} generated, {len(r_ok)} reference)")
    gr = chamfer_matrix(g_ok, r_ok, **kwargs)
    mmd_cd = float(gr.min(axis=0).mean())
    cov_cd = len(set(gr.argmin(axis=1).tolist())) / len(r_ok)
    gg = chamfer_matrix(g_ok, g_ok, **kwargs)
    rr = chamfer_matrix(r_ok, r_ok, **kwargs)
    full = np.block([[gg, gr], [gr.T, rr]])
    np.fill_diagonal(full, np.inf)  # leave-one-out
    labels = np.r_[np.zeros(len(g_ok)), np.ones(len(r_ok))]
    nna = float((labels[full.argmin(axis=1)] == labels).mean())
    return PointFlowScores(mmd_cd, cov_cd, nna, len(gen), len(ref),
                           len(gen) - len(g_ok), len(ref) - len(r_ok))
