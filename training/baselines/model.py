"""A trained comparison model as a directory (model.json + weights.pt + counts.npz) and its
generation: canonical sets -> observation frame -> snapped to the lidar's cells (one return per
cell, range quantized) -> the condition's expected point count (a random subset of the cells), so
every method's clouds are what the SPC-Lidar records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from apcg_core.cloud import PointCloud
from apcg_core.condition import ConditionSpace
from apcg_core.frames import cartesian_to_spherical, spherical_to_cartesian
from apcg_core.generation import NOISE_DIM, GenerationResult, ModelTypes, load_model
from apcg_core.lidar import LidarParams

from .data import CountLookup, from_canonical, voxel_centres
from .family import FamilyConfig
from .nets import check_sampling_steps

VOXEL_SURPLUS = 4


def load_any(directory=None, runtime: str = "onnx"):
    """The model in ``directory``: the cGAN (APCGModel) or a comparison family, as
    ``apcg_core.generation.load_model`` finds it (here the cGAN runs on onnxruntime unless
    told otherwise)."""
    return load_model(directory, runtime=runtime)


def export_baseline(st: dict, head: dict, counts: CountLookup, out: Path, meta: dict) -> None:
    torch.save({"G": st["G"], "net": st["net"]}, out / "weights.pt")
    np.savez(out / "counts.npz", codes=counts.codes, nu=counts.nu, counts=counts.counts,
             k=counts.k)
    (out / "model.json").write_text(json.dumps({**meta, "family": st["net"]["family"]},
                                               indent=1) + "\n")


def untrained_baseline(model: BaselineModel, out: Path, seed: int = 0) -> BaselineModel:
    """The same network as ``model``, freshly initialised (seeded), as a model directory."""
    import shutil
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    net, _ = model.cfg.networks()
    torch.save({"G": net.state_dict(), "net": model.meta["net"]}, out / "weights.pt")
    for name in ("counts.npz", "model.json"):
        shutil.copy(model.directory / name, out / name)
    return BaselineModel(out, model.sampling_steps)


class BaselineModel(ModelTypes):
    runtime = "torch"
    norm = True
    tau = None

    def __init__(self, directory, sampling_steps: int | None = None) -> None:
        self.directory = Path(directory)
        self.meta = json.loads((self.directory / "model.json").read_text())
        self.cfg = FamilyConfig(**self.meta["net"])
        self.space = ConditionSpace.from_dict(self.meta["condition_space"])
        self.lidar = LidarParams.from_dict(self.meta["lidar"])
        self.types = self.meta["types"]
        st = torch.load(self.directory / "weights.pt", map_location="cpu", weights_only=False)
        self.net, _ = self.cfg.networks()
        self.net.load_state_dict(st["G"])
        self.net.eval()
        with np.load(self.directory / "counts.npz") as z:
            self.counts = CountLookup(z["codes"], z["nu"], z["counts"], int(z["k"]))
        if sampling_steps is None:  # the export's choice; None: every step of the schedule
            sampling_steps = self.meta.get("sampling_steps")
        if sampling_steps is not None:
            check_sampling_steps(sampling_steps, self.cfg.diffusion_steps)
        self.sampling_steps = sampling_steps

    @torch.no_grad()
    def canonical(self, nu: np.ndarray, seed: int, counts) -> list[np.ndarray]:
        """Point sets in the canonical frame; the voxel GAN gives the ``counts[i]`` most
        probable voxels of each grid (a threshold at 0.5 leaves a young network's sparse grids
        nearly empty and has no say in how many points the lidar would record)."""
        gen = torch.Generator().manual_seed(int(seed))
        nu_t = torch.from_numpy(nu.astype(np.float32))
        if self.cfg.family == "diffusion":
            pts = self.cfg.schedule.sample(self.net, nu_t, self.cfg.n_points, gen,
                                           self.sampling_steps)
            return list(pts.numpy())
        z = torch.randn(len(nu), NOISE_DIM, generator=gen)
        out = self.net(z, nu_t).numpy()
        if self.cfg.family == "point-gan":
            return list(out)
        centres = voxel_centres(self.cfg.voxel_res)
        return [centres[np.argsort(-p, kind="stable")[:n]]
                for p, n in zip(out.reshape(len(nu), -1), counts, strict=True)]

    def generate(self, table, count: int = 1, seed: int = 0) -> GenerationResult:
        table = self.repeated_conditions(table, count)
        nu = self.space.encode(table)
        counts = [self.counts(int(table[i, 0]), nu[i]) for i in range(len(table))]
        # voxels behind one another fall into one cell: offer more than the count asks for
        sets = self.canonical(nu, seed, [VOXEL_SURPLUS * n for n in counts])
        lengths = self.depth_length(table[:, 0])
        rng = np.random.default_rng(seed)
        parts = []
        for i, (pts, n) in enumerate(zip(sets, counts, strict=True)):
            if not np.isfinite(pts).all():  # never drop such points silently (they have no cell)
                raise RuntimeError(f"the {self.cfg.family} network produced "
                                   f"{int((~np.isfinite(pts)).any(-1).sum())} non-finite points "
                                   f"for condition {table[i].tolist()} (sample {i})")
            xyz = from_canonical(pts, table[i, 1], table[i, 2], lengths[i])
            cells = self._snap(xyz, table[i, 2], i)
            if len(cells[0]) > n:  # the expected count for the condition, after snapping
                keep = np.sort(rng.permutation(len(cells[0]))[:n])
                cells = tuple(c[keep] for c in cells)
            parts.append(cells)
        cloud = PointCloud(*[np.concatenate([p[k] for p in parts]) for k in range(5)])
        return GenerationResult(cloud, None, table)

    def _snap(self, xyz: np.ndarray, beta0: float, sample: int):
        """Points -> the lidar's cells: the nearest point of each cell, its range quantized."""
        lidar = self.lidar
        alpha, beta, r = cartesian_to_spherical(xyz)
        w, h = lidar.cell_of_angles(alpha, beta, beta0)
        ok = lidar.inside(w, h)
        w, h, r = w[ok], h[ok], r[ok]
        order = np.lexsort((r, h, w))
        w, h, r = w[order], h[order], r[order]
        first = np.ones(len(w), bool)
        first[1:] = (w[1:] != w[:-1]) | (h[1:] != h[:-1])
        w, h, r = w[first], h[first], lidar.quantize_range(r[first])
        a, b = lidar.cell_centre_angles(w, h, beta0)
        return (spherical_to_cartesian(a, b, r), r, w, h,
                np.full(len(r), sample, np.int64))
