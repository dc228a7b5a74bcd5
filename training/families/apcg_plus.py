"""Training APCG+ (apcg_core/families/apcg_plus.py): the family object the trainer, export and
evaluation use.

The standard data are (almost) a function of the condition: one first-surface return per cell.
So the network is fitted to them directly, cell by cell, as pix2pix pairs an L1 loss with its
adversary (here the reconstruction loss alone: see docs/evaluation/plus for what an adversary
added). Each step draws, for every sample of the batch, ``QUERIES`` cells of its box:

* a quarter uniformly over the box (what generation reads),
* a quarter among the sample's returns (the ``returns`` mix, the default; none in the
  ``silhouette`` mix),
* the rest near its returns (a return's cell moved by up to ``EDGE_CELLS`` cells: the
  silhouette, where the errors are),

reads the sheets there (bilinear, as generation does) and takes binary cross-entropy on "has a
return" plus ``DEPTH_WEIGHT`` x L1 on the range offset of the cells that have one. Log columns:
``loss_d`` is the cross-entropy, ``loss_g`` the L1, ``wasserstein`` the share of cells classified
right (there is no critic).
"""

from __future__ import annotations

import json
import sys
import weakref
from pathlib import Path

import numpy as np

from apcg_core.errors import InputError
from apcg_core.families.apcg_plus import FAMILY, box_half_cells, sheet_coords
from apcg_core.io.dataset import write_atomic

from .base import Family

QUERIES = 1024
EDGE_CELLS = 3
# How each step's query cells are drawn (`apcg train --queries`): the shares of the box
# (uniform) and of the sample's returns; the rest lie near the returns. Drawing cells *because*
# they are returns weights a return above a cell without one at the same place, so the fitted
# hit probability is too high wherever the standard data cannot be told from the condition
# (a wingtip thinner than a cell: 0.82 fitted against 0.39 seen, stop 45,
# docs/evaluation/recognize); "silhouette" draws places, not labels.
QUERY_MIXES = {"returns": (0.25, 0.25), "silhouette": (0.25, 0.0)}
DEPTH_WEIGHT = 4.0
# Distillation (`apcg distill`). The hit logit matters to generation only near tau, where a
# cell is kept or dropped; 8 leaves the tanh within 1 % of linear for |logit| < 1.4. The range
# offset is in bounding radii: an aircraft's 20-40 m radius puts the 0.15 m range bin at
# 0.004-0.008, so its error is weighted 10 against the logit's (a 0.04 offset error costs what
# 0.4 of logit does); a cell is a possible return when the teacher's logit is above tau - 3.
LOGIT_CLIP = 8.0
DISTILL_DEPTH_WEIGHT = 10.0
DEPTH_MARGIN = 3.0


class HitLookup:
    """Which cells of which training sample hold a return, and its range offset: one sorted
    key per return (sample x H x W + pixel) for vectorised lookups."""

    def __init__(self, ds) -> None:
        n_px = ds.height * ds.width
        counts = np.diff(ds.offsets)
        self.sample_of = np.repeat(np.arange(len(ds)), counts)
        keys = self.sample_of * n_px + ds.pixel
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.delta = ds.delta_range_m[order].astype(np.float64)
        cos = getattr(ds, "cos_incidence", None)  # an incidence dataset's (plus_incidence.py)
        self.cos = None if cos is None else cos[order].astype(np.float32)
        self.offsets = ds.offsets
        self.pixel = ds.pixel
        self.n_px = n_px

    def find(self, sample, pixel, cosine: bool = False):
        """(is a return, its range offset in metres or 0) for cells ``pixel`` of ``sample``;
        with ``cosine``, also its cosine of incidence or 0."""
        key = sample * self.n_px + pixel
        pos = np.minimum(np.searchsorted(self.keys, key), len(self.keys) - 1)
        hit = self.keys[pos] == key
        found = hit, np.where(hit, self.delta[pos], 0.0)
        return (*found, np.where(hit, self.cos[pos], 0.0)) if cosine else found


_LOOKUPS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def hit_lookup(ds) -> HitLookup:
    if ds not in _LOOKUPS:
        _LOOKUPS[ds] = HitLookup(ds)
    return _LOOKUPS[ds]


def radius_of(ds) -> np.ndarray:
    """Each sample's type's bounding radius (m), from the dataset's type table."""
    rad = [r.get("bounding_radius_m") for r in ds.types.records]
    if any(r is None for r in rad):
        raise InputError(f"dataset {ds.directory} does not record bounding_radius_m for its "
                         "types; rebuild it with this version of `apcg dataset build`")
    return np.asarray(rad, np.float64)[ds.conditions[:, 0].astype(np.int64)]


def draw_queries(ds, idx, rng, n: int = QUERIES, mix: str = "returns", cosine: bool = False):
    """Query cells of samples ``idx``: (B, n) arrays of u, v, hit (0/1) and range offset / R,
    drawn by ``mix`` (a name of QUERY_MIXES); with ``cosine``, also each return's cosine of
    incidence (0 where none; an incidence dataset's)."""
    lidar = ds.lidar
    look = hit_lookup(ds)
    idx = np.asarray(idx, np.int64)
    b = len(idx)
    r0, b0 = ds.conditions[idx, 1], ds.conditions[idx, 2]
    rad = radius_of(ds)[idx]
    w_half, h_half = box_half_cells(r0, b0, rad, lidar)
    w_lo = np.maximum(-w_half, lidar.w_min)
    w_hi = np.minimum(w_half, lidar.width // 2 - 1)
    h_lo = np.maximum(-h_half, lidar.h_min)
    h_hi = np.minimum(h_half, lidar.height // 2 - 1)
    box_share, hit_share = QUERY_MIXES[mix]
    n_box, n_hit = int(n * box_share), int(n * hit_share)
    n_edge = n - n_box - n_hit
    # uniform over the box
    wu = rng.integers(w_lo[:, None], w_hi[:, None] + 1, (b, n_box))
    hu = rng.integers(h_lo[:, None], h_hi[:, None] + 1, (b, n_box))
    # returns, and cells near them (a sample without returns falls back to the box)
    starts, counts = look.offsets[idx], np.diff(look.offsets)[idx]
    pick = rng.integers(0, np.maximum(counts, 1)[:, None], (b, n_hit + n_edge))
    px = look.pixel[np.minimum(starts[:, None] + pick, len(look.pixel) - 1)]
    row, col = np.divmod(px, lidar.width)
    wr, hr = lidar.w_of_col(col), lidar.h_of_row(row)
    jitter = rng.integers(-EDGE_CELLS, EDGE_CELLS + 1, (2, b, n_edge))
    wr[:, n_hit:] += jitter[0]
    hr[:, n_hit:] += jitter[1]
    none = counts == 0
    wr[none] = rng.integers(w_lo[none, None], w_hi[none, None] + 1, (none.sum(), n_hit + n_edge))
    hr[none] = rng.integers(h_lo[none, None], h_hi[none, None] + 1, (none.sum(), n_hit + n_edge))
    w = np.clip(np.concatenate([wu, wr], axis=1), w_lo[:, None], w_hi[:, None])
    h = np.clip(np.concatenate([hu, hr], axis=1), h_lo[:, None], h_hi[:, None])
    pixel = lidar.row_of_h(h) * lidar.width + lidar.col_of_w(w)
    hit, delta, *cos = look.find(np.repeat(idx[:, None], n, axis=1), pixel, cosine)
    u, v = sheet_coords(w, h, r0[:, None], b0[:, None], rad[:, None], lidar)
    return (u, v, hit.astype(np.float32), (delta / rad[:, None]),
            *(c.astype(np.float32) for c in cos))


class PlusFamily(Family):
    """APCG+: trained by regression on the standard data (no critic), exported to ONNX."""

    name = FAMILY
    sizes = ("sheet", "head", "queries")
    default_tau = 0.0  # the hit logit's threshold: probability one half
    # The regression trains with Adam's usual betas at a larger rate than a GAN can, one batch
    # per step; the average of the weights (decay 0.999) is what is exported.
    train_defaults = {"lr": 1e-3, "betas": (0.9, 0.99), "n_critic": 1, "ema": 0.999,
                      "width": 1.0}

    @staticmethod
    def load(directory, runtime: str = "auto"):
        from apcg_core.families.apcg_plus import PlusModel
        return PlusModel(directory, runtime=runtime)

    def net_config(self, cfg, dataset):
        from apcg_core.nn.apcg_plus import PlusConfig
        return PlusConfig(n_types=len(dataset.types), width=cfg.width, sheet=cfg.sheet,
                          head=cfg.head)

    def init_from(self, net, model_dir, dataset) -> None:
        """Start ``net`` from the weights of the APCG+ model in ``model_dir`` (`apcg train
        --init`): the same types in the same order as the dataset's, the same network."""
        net.load_state_dict(self.starting_model(net, model_dir, dataset).torch_net()
                            .state_dict())

    def starting_model(self, net, model_dir, dataset):
        """The APCG+ model in ``model_dir``, refused unless it can start ``net``: its types the
        dataset's, in the same order, and its network ``net``'s but for the sheet's channels
        (an incidence network's one against the model's two)."""
        from apcg_core.families import load_model
        model = load_model(model_dir)
        if model.family != FAMILY:
            raise InputError(f"--init {model_dir}: a {model.family} model; an {self.name} run "
                             f"starts only from an {FAMILY} model")
        if list(model.types.names) != list(dataset.types.names):
            raise InputError(f"--init {model_dir}: its types are not the dataset's (the same "
                             "names in the same order are needed; the dataset has "
                             f"{len(dataset.types.names)}, the model {len(model.types.names)})")
        from apcg_core.nn.apcg_plus import PlusConfig
        theirs = PlusConfig.from_dict({**model.meta["net"], "outputs": net.cfg.outputs}).to_dict()
        ours = net.cfg.to_dict()
        if theirs != ours:
            diff = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
            said = ", ".join(f"{k}={theirs.get(k)!r}" for k in diff)
            raise InputError(f"--init {model_dir}: its network differs from the run's in "
                             f"{', '.join(diff)} (the model's: {said}); give the same "
                             "--width, --sheet and --head")
        return model

    def networks(self, net):
        from apcg_core.nn.apcg_plus import PlusNet
        return PlusNet(net), None

    def prepare(self, dataset) -> None:
        hit_lookup(dataset)
        radius_of(dataset)

    def batches_per_step(self, cfg) -> int:
        return 1

    def draw(self, tr, idx, rng):
        """Query cells of samples ``idx`` and their targets: u, v, hit, range offset."""
        return draw_queries(tr.data, idx, rng, mix=tr.cfg.queries)

    def batch(self, tr, idx):
        """The batch's query cells (u, v) and targets (:meth:`draw`) as tensors, drawn with
        the batch's own seed (so a resumed run draws the same cells)."""
        import torch
        rng = np.random.default_rng([tr.cfg.seed, tr.batch_counter, tr.rank])
        u, v, *targets = self.draw(tr, idx, rng)
        grid = torch.from_numpy(np.stack([u, -v], axis=-1).astype(np.float32))[:, :, None]
        return (torch.from_numpy(np.asarray(idx, np.int64)), grid,
                *(torch.from_numpy(np.asarray(t, np.float32)) for t in targets))

    @staticmethod
    def read_queries(tr):
        """The next batch's sheets read at its query cells, (B, channels, Q), and its
        targets."""
        import torch
        import torch.nn.functional as F
        (idx, grid, *targets), nu = tr.next_batch()
        codes = torch.from_numpy(tr.data.conditions[idx.numpy(), 0].astype(np.int64))
        tr.G.train()
        with tr.autocast():
            sheets = tr.G(codes, nu[:, 1:])
        read = F.grid_sample(sheets.float(), grid, mode="bilinear", padding_mode="border",
                             align_corners=False)[..., 0]
        return read, targets

    @staticmethod
    def descend(tr, loss) -> None:
        tr.opt_g.zero_grad(set_to_none=True)
        loss.backward()
        tr.allreduce_grads(tr.G)
        tr.opt_g.step()

    def train_step(self, tr) -> dict:
        import torch
        import torch.nn.functional as F
        read, (hit, off) = self.read_queries(tr)
        logit, depth = read[:, 0], read[:, 1]
        bce = F.binary_cross_entropy_with_logits(logit, hit)
        l1 = (torch.abs(depth - off) * hit).sum() / hit.sum().clamp(min=1.0)
        self.descend(tr, bce + DEPTH_WEIGHT * l1)
        right = ((logit > 0).float() == hit).float().mean()
        return tr.finish_step(bce, l1, 0.0, right)

    def export(self, state: dict, header: dict, out_dir, meta: dict, data_dir,
               sampling_steps=None) -> Path:
        from apcg_core.nn.apcg_plus import PlusConfig, PlusNet
        self.check_sampling_steps(sampling_steps, state)
        net = PlusNet(PlusConfig.from_dict(state["net"]))
        net.load_state_dict(state["G"])
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        export_sheets_onnx(net, out / "sheets.onnx")
        from apcg_core.families.plus_draw import DEFAULT as DEFAULT_DRAW
        meta = {**meta, "family": FAMILY, "draw": DEFAULT_DRAW.record(),
                "quantize": bool(header.get("config", {}).get("quantize", True))}
        meta.pop("norm", None)
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
        return out

    def untrained(self, model, out_dir, seed: int = 0):
        """The same network freshly initialised (seeded), as a model directory."""
        import torch

        from apcg_core.families.apcg_plus import PlusModel
        from apcg_core.nn.apcg_plus import PlusConfig, PlusNet
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(seed)
        export_sheets_onnx(PlusNet(PlusConfig.from_dict(model.meta["net"])),
                           out / "sheets.onnx")
        write_atomic(out / "model.json", json.dumps(without_incidence(model.meta)).encode())
        return PlusModel(out, runtime="onnx")


    # --- distillation (training/distill.py, `apcg distill`) ------------------------------
    def distill_networks(self, model, width: float, head: str):
        """(teacher, student): the model's own network (its exported weights) and a fresh one
        of ``width`` and ``head`` for the same types and sheet, whose type embedding, type
        offset and condition MLP start as the teacher's (the same shapes: only the drawing
        is new)."""
        from apcg_core.nn.apcg_plus import PlusConfig, PlusNet
        teacher = model.torch_net()
        cfg = PlusConfig.from_dict({**model.meta["net"], "width": float(width),
                                    "head": head})
        student = PlusNet(cfg)
        own = teacher.state_dict()
        start = {k: v for k, v in own.items()
                 if k.split(".")[0] in ("type_embedding", "type_offset", "cond")}
        student.load_state_dict(start, strict=False)
        return teacher, student

    @staticmethod
    def distill_loss(out, target, tau: float):
        """(logit loss, depth loss) of a student's sheets ``out`` against the teacher's
        ``target``, every cell. The hit logit is compared through LOGIT_CLIP * tanh(. /
        LOGIT_CLIP): linear where the threshold tau is read, flat far from it, so cells
        certain either way cost nothing once the student agrees. The range offset counts
        where the teacher's cell is within DEPTH_MARGIN of tau (a cell generation may read),
        weighted DISTILL_DEPTH_WEIGHT."""
        import torch
        c = LOGIT_CLIP
        l_logit = torch.abs(c * torch.tanh(out[:, 0] / c) - c * torch.tanh(target[:, 0] / c))
        near = (target[:, 0] > tau - DEPTH_MARGIN).float()
        l_depth = (torch.abs(out[:, 1] - target[:, 1]) * near).sum() / near.sum().clamp(min=1.0)
        return l_logit.mean(), DISTILL_DEPTH_WEIGHT * l_depth

    def export_distilled(self, net, model, out_dir, extra: dict) -> Path:
        """The student as a model directory: the teacher's model.json (types, condition space,
        lidar, tau) with the student's network, and what the distillation was. The teacher's
        measurements (its held-out lidars, its tau sweep) are not the student's: dropped."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        export_sheets_onnx(net, out / "sheets.onnx")
        meta = {k: v for k, v in model.meta.items()
                if k not in ("measured_lidars", "tau_choice", "log", "train", "trained_steps",
                             "trained_epochs", "taught", *INCIDENCE_RECORD)}
        meta.update({"net": net.cfg.to_dict(), **extra,
                     "generator_weights": "moving average of the student's weights"})
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
        return out

    def teach(self, model, data_dir, out_dir, minutes: float = 10.0, steps: int | None = None,
              seed: int = 0, progress: bool = True) -> dict:
        """Fit one new row of the type embedding and of the type offset to the type of
        ``data_dir`` (a dataset of that type alone), starting from the known type it resembles
        most, every other weight frozen; write the model with the type added."""
        import time
        from dataclasses import replace

        import torch
        import torch.nn.functional as F

        from apcg_core.families.base import onnx_weights
        from apcg_core.nn.apcg_plus import PlusConfig, PlusNet

        from ..data import DepthDataset
        ds = DepthDataset(data_dir, "train")
        if len(ds.types) != 1:
            raise InputError(f"{data_dir} holds {len(ds.types)} types; teaching takes one")
        old = PlusConfig.from_dict(model.meta["net"])
        new_code = old.n_types
        net = PlusNet(replace(old, n_types=old.n_types + 1))
        state = onnx_weights(model.onnx_path)
        own = net.state_dict()
        emb, offs = state["type_embedding.weight"], state["type_offset.weight"]
        state["type_embedding.weight"] = np.concatenate([emb, emb[:1]])
        state["type_offset.weight"] = np.concatenate([offs, offs[:1]])
        net.load_state_dict({k: torch.from_numpy(np.asarray(state[k])) for k in own})
        for p in net.parameters():
            p.requires_grad_(False)
        rng = np.random.default_rng(seed)
        batch = min(32, len(ds))
        codes = torch.full((batch,), new_code, dtype=torch.int64)
        t0 = time.perf_counter()

        one = F.one_hot(torch.tensor(new_code), old.n_types + 1)[:, None].float()

        def with_row(table, row):
            return table.detach() * (1.0 - one) + one * row

        def loss_of(rows, idx, queries):
            u, v, hit, off = queries
            grid = torch.from_numpy(np.stack([u, -v], -1).astype(np.float32))[:, :, None]
            hit_t, off_t = torch.from_numpy(hit), torch.from_numpy(off.astype(np.float32))
            sheets = net(codes[:len(idx)], torch.from_numpy(ds.nu[idx, 1:]),
                         embedding=with_row(net.type_embedding.weight, rows[0]),
                         offset=with_row(net.type_offset.weight, rows[1]))
            read = F.grid_sample(sheets, grid, mode="bilinear", padding_mode="border",
                                 align_corners=False)[..., 0]
            bce = F.binary_cross_entropy_with_logits(read[:, 0], hit_t)
            l1 = (torch.abs(read[:, 1] - off_t) * hit_t).sum() / hit_t.sum().clamp(min=1.0)
            right = ((read[:, 0] > 0).float() == hit_t).float().mean()
            return bce + DEPTH_WEIGHT * l1, float(right)

        # start from the known type the new one resembles most (lowest loss on one batch)
        idx = rng.choice(len(ds), batch, replace=False)
        probe = draw_queries(ds, idx, rng)
        with torch.no_grad():
            losses = [float(loss_of((torch.from_numpy(e), torch.from_numpy(o)), idx, probe)[0])
                      for e, o in zip(emb, offs, strict=True)]
        nearest = int(np.argmin(losses))
        rows = (torch.from_numpy(emb[nearest].copy()).requires_grad_(True),
                torch.from_numpy(offs[nearest].copy()).requires_grad_(True))
        opt = torch.optim.Adam(rows, lr=1e-2)
        n_steps = steps if steps is not None else 10**9
        budget = max(minutes * 60.0 - (time.perf_counter() - t0), 5.0)
        t1, step, loss_v, right_v = time.perf_counter(), 0, float("nan"), float("nan")
        while step < n_steps and time.perf_counter() - t1 < budget:
            idx = rng.choice(len(ds), batch, replace=False)
            loss, right_v = loss_of(rows, idx, draw_queries(ds, idx, rng))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            loss_v = float(loss.detach())
            if progress and step % 100 == 0:
                print(f"teach step {step}: loss {loss_v:.4f}, cells right {right_v:.3f}",
                      file=sys.stderr, flush=True)
        with torch.no_grad():
            net.type_embedding.weight[new_code] = rows[0]
            net.type_offset.weight[new_code] = rows[1]
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        export_sheets_onnx(net, out / "sheets.onnx")
        rec = {**ds.types.records[0]}
        space = dict(model.meta["condition_space"])
        space["n_types"] = old.n_types + 1
        if rec.get("range_band") == "near":
            space["drone_types"] = sorted([*space.get("drone_types", []), new_code])
        fit = {"steps": step, "seconds": round(time.perf_counter() - t0, 2),
               "last_loss": loss_v, "cells_right": right_v,
               "trained": "the type's rows of the type embedding and offset",
               "started_from": model.types.names[nearest],
               "dataset": ds.header.get("config", {}).get("description")}
        # the incidence network (if any) knows the old types only: the taught model has none
        meta = {**without_incidence(model.meta), "net": net.cfg.to_dict(),
                "condition_space": space,
                "types": [*model.types.to_records(), {"code": new_code, **rec}],
                "taught": [*model.meta.get("taught", []), {"type": rec["name"], **fit}]}
        (out / "model.json").write_text(json.dumps(meta, indent=1) + "\n")
        for name in ("train_config.json", "log.csv"):
            src = Path(model.directory) / name
            if src.exists():
                (out / name).write_bytes(src.read_bytes())
        return fit


# What model.json records of an incidence network (training/families/plus_incidence.py): a
# model written from another one without copying incidence.onnx (a student, a taught type, an
# untrained twin) leaves them out, and its photons read the range's slope (SPEC section 8).
INCIDENCE_RECORD = ("incidence", "incidence_log")


def without_incidence(meta: dict) -> dict:
    return {k: v for k, v in meta.items() if k not in INCIDENCE_RECORD}


def export_sheets_onnx(net, path: Path, output: str = "sheet") -> None:
    """The network as ONNX: inputs type_code (N,) int64 and pose (N, 5); output ``output``
    (a model's ``sheet``, its incidence network's ``incidence``)."""
    import os
    import warnings

    import torch
    net = net.eval()
    tmp = path.with_name(path.name + ".part")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (torch.zeros(2, dtype=torch.int64), torch.zeros(2, 5)), str(tmp),
                          input_names=["type_code", "pose"], output_names=[output],
                          opset_version=17, dynamo=False, do_constant_folding=False,
                          dynamic_axes={"type_code": {0: "batch"}, "pose": {0: "batch"},
                                        output: {0: "batch"}})
    os.replace(tmp, path)


PLUS = PlusFamily()

__all__ = ["PLUS", "PlusFamily", "draw_queries", "export_sheets_onnx"]
