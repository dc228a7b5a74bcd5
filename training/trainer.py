"""Training of every model family (the improved cGAN of SPEC section 7 and the comparison
families), with exact resume and data parallelism. What a step computes belongs to the family
(``training/families/<family>.py``, found through ``apcg_core.families``); the trainer keeps the
loop, the optimisers, the checkpoints, the logs and the clock, and never asks which family it runs.

Exactness: the batch order is a pure function of (seed, batch counter) and every random draw of a
step (noise, gradient-penalty mixing) comes from a generator seeded by (seed, step, rank), so a
run resumed from a checkpoint computes the very same steps as an uninterrupted one.

Data parallel (``torchrun --nproc_per_node N``, gloo on CPU): each rank takes its own slice of
every batch; gradients are averaged across ranks by an all-reduce after each backward (this keeps
the gradient penalty's double backward simple) and BatchNorm buffers follow rank 0.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from apcg_core.errors import APCGError, InputError
from apcg_core.families import get_family
from apcg_core.io.atomic import atomic_path
from apcg_core.io.dataset import write_atomic

from .data import DepthDataset

LOG_FIELDS = ["step", "epoch", "loss_d", "loss_g", "gp", "wasserstein", "seconds"]


@dataclass
class TrainConfig:
    width: float = 1.0
    conv: bool = True
    attention: bool = True
    loss: str = "wgan-gp"
    batch_size: int = 32
    lr: float = 2e-4
    betas: tuple = (0.5, 0.9)
    n_critic: int = 5
    gp_lambda: float = 10.0
    epochs: float = 1000.0
    steps: int | None = None  # overrides epochs when given
    seed: int = 0
    bf16: bool = False
    checkpoint_every: int = 500
    norm: bool = True  # train on Norm(depth) (eq. 17); False: "APCG w/o Norm." (paper Fig. 17)
    family: str = "cgan"  # a registered model family (apcg_core.families.family_names())
    # Sizes of some families (each family's train_options() names those it takes):
    n_points: int = 256  # points per generated set
    voxel_res: int = 32  # occupancy grid resolution
    diffusion_steps: int = 200  # T of the DDPM schedule
    sheet: int = 64  # side of an APCG+ sheet (4 x 2^k)
    head: str = "conv"  # how an APCG+ network draws its sheet (apcg_core.families.plus_heads.HEADS)
    # how APCG+ draws its loss's cells (training.families.apcg_plus.QUERY_MIXES)
    queries: str = "returns"
    keep_every: int = 0  # also keep checkpoints/step-NNNNNN.pt every this many steps (0: never)
    diverge_gp: float = 50.0  # stop when the gradient penalty's mean over 50 steps exceeds it
    ema: float = 0.0  # decay of an exponential moving average of the generator (0: none)
    hours: float | None = None  # a time budget: stop once training time, summed over resumes,
    # reaches it (equal-hours comparisons of model families; steps / epochs still cap the run)
    log_every: int = 10
    threads: int | None = None
    init: str | None = None  # a model directory whose weights start the network (fine-tuning)

    @classmethod
    def from_dict(cls, saved: dict) -> TrainConfig:
        """A configuration as saved with a run (checkpoint or train_config.json ``train``)."""
        # Runs saved before these were removed carry them: "extra" (never read) and
        # "channels_last" (never set by any command). They are dropped, so old runs resume.
        removed = ("extra", "channels_last")
        known = {f.name for f in fields(cls)}
        unknown = sorted(k for k in saved if k not in known and k not in removed)
        if unknown:
            raise InputError(f"a saved training configuration has unknown settings {unknown}")
        out = {k: v for k, v in saved.items() if k in known}
        if "betas" in out:
            out["betas"] = tuple(out["betas"])
        return cls(**out)


PRESETS = {
    # The paper: full width, 1000 epochs: a GPU job.
    "paper": TrainConfig(),
    # This CPU: a quarter of the channels, bf16 autocast. (n_critic 2 diverged at step 1933 of
    # the first default-model run; 5, as in WGAN-GP, costs the same per epoch.)
    # The exported generator is the moving average of the weights (decay 0.999): an undertrained
    # GAN's raw weights jitter from step to step; at step 4000 of the default model the average
    # scored MMD 0.115 against the raw weights' 0.131 on drones (0.149 / 0.151 on aircraft).
    "cpu": TrainConfig(width=0.25, n_critic=5, bf16=True, epochs=30.0, checkpoint_every=100,
                       keep_every=500, ema=0.999),
    # Tests: tiny and fast.
    "tiny": TrainConfig(width=0.0625, n_critic=1, epochs=1.0, checkpoint_every=20,
                        log_every=1),
}


def size_defaults() -> dict:
    """The family-specific sizes (name -> default) a family's ``train_options`` draws from."""
    return {f.name: f.default for f in fields(TrainConfig)
            if f.name in ("n_points", "voxel_res", "diffusion_steps", "sheet", "head",
                          "queries")}


def gradient_penalty(d, real, fake, nu, eps) -> torch.Tensor:
    """E[(||grad_x D(x)||_2 - 1)^2] at x = eps real + (1 - eps) fake (WGAN-GP).

    The norm is sqrt(sum g^2 + 1e-12), so a zero gradient gives a penalty of ~1 with a finite
    gradient instead of NaN."""
    e = eps.view(-1, *([1] * (real.dim() - 1)))
    mix = (e * real + (1 - e) * fake).detach().requires_grad_(True)
    score = d(mix, nu)
    (grad,) = torch.autograd.grad(score.sum(), mix, create_graph=True)
    norm = torch.sqrt(grad.flatten(1).pow(2).sum(1) + 1e-12)
    return ((norm - 1.0) ** 2).mean()


@torch.no_grad()
def ema_update(avg: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    """avg <- decay avg + (1 - decay) model for every parameter; buffers (BatchNorm statistics)
    are copied, so the average runs with the statistics of the weights it follows."""
    for a, p in zip(avg.parameters(), model.parameters(), strict=True):
        a.lerp_(p.detach(), 1.0 - decay)
    for a, b in zip(avg.buffers(), model.buffers(), strict=True):
        a.copy_(b)


def step_generator(seed: int, step: int, phase: int, rank: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(int(np.random.SeedSequence([seed, step, phase, rank]).generate_state(1)[0]))
    return g


class Trainer:
    def __init__(self, data_dir, run_dir, cfg: TrainConfig, resume: bool = False,
                 progress: bool = True, preset: str | None = None) -> None:
        """``preset``: the preset ``cfg`` was made from, recorded with a new run (a resume
        that names another is refused)."""
        self.cfg = cfg
        self.run = Path(run_dir)
        self.progress = progress
        self.rank, self.world = _dist_rank_world()
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        self.data = DepthDataset(data_dir, "train")
        self.data_dir = str(data_dir)
        if resume:  # before the network is made from it: a dataset that is not the run's is
            # named as such, not as a checkpoint of another network (another lidar's window)
            rec = read_run_record(self.run)
            if rec is not None:
                check_same_dataset(rec, self.data.header, data_dir, "--resume", run=self.run)
        self.family = get_family(cfg.family, need="train_step")
        torch.manual_seed(cfg.seed)  # initial weights
        try:
            net = self.net_config = self.family.net_config(cfg, self.data)
            self.G, self.D = self.family.networks(net)  # (generator or denoiser, critic or None)
        except ValueError as exc:  # a size the family's network cannot take (its image's)
            raise InputError(f"the {cfg.family} family cannot train on the dataset {data_dir}: "
                             f"{exc} (its lidar's window is {self.data.width} x "
                             f"{self.data.height}); train another family, or on a dataset "
                             "of another lidar") from exc
        if cfg.init is not None and not resume:  # a resumed run has its own weights
            if not callable(getattr(self.family, "init_from", None)):
                raise InputError(f"--init: the {cfg.family} family cannot start from a "
                                 "model's weights; train it from scratch")
            self.family.init_from(self.G, cfg.init, self.data)
        self.family.prepare(self.data)
        if not 0.0 <= cfg.ema < 1.0:
            raise InputError(f"ema (the generator average's decay) must be in [0, 1), got "
                             f"{cfg.ema}")
        if not (isinstance(cfg.lr, (int, float)) and math.isfinite(cfg.lr) and cfg.lr > 0):
            raise InputError(f"lr (the learning rate) must be a number > 0, got {cfg.lr!r}")
        if cfg.hours is not None and not cfg.hours > 0:
            raise InputError(f"hours (the training-time budget) must be > 0, got {cfg.hours}")
        self.G_ema = copy.deepcopy(self.G).eval() if cfg.ema > 0 else None
        self.ema_since = 0  # the step the average started from (later when added on resume)
        self.opt_g = torch.optim.Adam(self.G.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
        self.opt_d = (torch.optim.Adam(self.D.parameters(), lr=cfg.lr, betas=tuple(cfg.betas))
                      if self.D is not None else None)
        self.step = 0
        self.batch_counter = 0
        self.seconds_before = 0.0  # training time of earlier runs (from the log, on resume)
        self.bpe = self.data.batches_per_epoch(cfg.batch_size, self.world)
        self.total_steps = cfg.steps if cfg.steps is not None else int(
            math.ceil(cfg.epochs * self.bpe / self.family.batches_per_step(cfg)))
        ckpt = self.run / "checkpoint.pt"
        existed = (self.run / "train_config.json").exists()
        if self.world > 1:  # every rank looks before rank 0 writes the run's files
            import torch.distributed as dist
            dist.barrier()
        if (self.run / "model.json").exists():  # export's or teach's output, not a run
            raise InputError(f"-o {self.run} is a model directory (it holds model.json), not a "
                             "training run: training would overwrite its files; choose another "
                             "-o for the run")
        if existed and not resume and ckpt.exists():
            raise InputError(f"{self.run} already holds a training run; pass --resume to "
                             "continue it or choose another -o")
        if existed and not resume and self.rank == 0:
            # it stopped before its first checkpoint: nothing of it can be kept; start over
            print(f"apcg train: {self.run} stopped before its first checkpoint; starting it "
                  "over", file=sys.stderr)
            (self.run / "log.csv").unlink(missing_ok=True)
        if resume:
            if not ckpt.exists():
                raise InputError(f"nothing to resume in {self.run}: it has no checkpoint.pt "
                                 "(it stopped before its first); start it over with the same "
                                 "command without --resume")
            self._load(ckpt)
            record = self.run / "train_config.json"
            rec = read_run_record(self.run) if self.rank == 0 else None
            if rec is not None:
                ran = rec["train"].get("family", "cgan")
                if ran != self.cfg.family:
                    raise InputError(f"{ckpt} is a checkpoint of the {self.cfg.family} family "
                                     f"but {self.run} is a {ran} run (its train_config.json): "
                                     "it is another run's checkpoint; put the run's own back, "
                                     "or train a new run with another -o")
            if rec is not None:  # show the budget in force, not the first's
                rec["train"] = asdict(cfg)
                write_atomic(record, json.dumps(rec, indent=1).encode())
        elif self.rank == 0:
            self.run.mkdir(parents=True, exist_ok=True)
            write_atomic(self.run / "train_config.json", json.dumps(
                {"train": asdict(cfg), "net": net.to_dict(),
                 "data": str(Path(self.data_dir).resolve()),
                 "dataset": self.data.header.get("name"),
                 "dataset_types": dataset_type_names(self.data.header),
                 "dataset_defines": dataset_defines(self.data.header), "world": self.world}
                | ({"preset": preset} if preset else {}),
                indent=1).encode())
        if self.world > 1:
            _broadcast(self.G)
            if self.D is not None:
                _broadcast(self.D)
        self._tb = None

    # --- checkpoints -------------------------------------------------------------------------
    def _state(self) -> dict:
        return {"step": self.step, "batch_counter": self.batch_counter,
                "G": self.G.state_dict(),
                "D": self.D.state_dict() if self.D is not None else None,
                "opt_g": self.opt_g.state_dict(),
                "opt_d": self.opt_d.state_dict() if self.opt_d is not None else None,
                "G_ema": self.G_ema.state_dict() if self.G_ema is not None else None,
                "ema_since": self.ema_since,
                "train": asdict(self.cfg), "net": self.net_config.to_dict()}

    def save(self) -> None:
        if self.rank != 0:
            return
        with atomic_path(self.run / "checkpoint.pt") as tmp:
            torch.save(self._state(), tmp)
        if self.cfg.keep_every and self.step % self.cfg.keep_every == 0:
            keep = self.run / "checkpoints" / f"step-{self.step:06d}.pt"
            with atomic_path(keep) as tmp:
                shutil.copyfile(self.run / "checkpoint.pt", tmp)

    def _load(self, path: Path) -> None:
        st = read_checkpoint(path)
        family = st["train"].get("family", "cgan") if isinstance(st.get("train"), dict) else None
        if family != self.cfg.family:
            raise InputError(f"checkpoint {path} is of the {family} family, not this run's "
                             f"{self.cfg.family}: it is another run's; resume the run that "
                             "wrote it")
        if st["net"] != self.net_config.to_dict():
            raise InputError(f"checkpoint {path} has network {st['net']}, not "
                             f"{self.net_config.to_dict()}; resume with the same preset")
        self.G.load_state_dict(st["G"])
        self.opt_g.load_state_dict(st["opt_g"])
        if self.D is not None:
            self.D.load_state_dict(st["D"])
            self.opt_d.load_state_dict(st["opt_d"])
        self.step, self.batch_counter = st["step"], st["batch_counter"]
        if self.G_ema is not None:
            if st.get("G_ema") is not None:
                self.G_ema.load_state_dict(st["G_ema"])
                self.ema_since = st.get("ema_since", 0)
            else:  # the average is switched on by this resume: it starts from the weights
                self.G_ema.load_state_dict(st["G"])
                self.ema_since = self.step
        log = self.run / "log.csv"
        if log.exists() and self.rank == 0:  # drop rows past the checkpoint: they are redone
            from apcg_core.io.csv_table import read_csv
            table = read_csv(log, required=LOG_FIELDS, what="training log")
            rows = [{k: r[k] for k in LOG_FIELDS} for r in table if r.int("step") <= self.step]
            self._write_log_rows(rows, mode="w")
            if rows:  # the log's clock is training time summed over all runs
                self.seconds_before = float(rows[-1]["seconds"])

    def _check_divergence(self, row: dict, recent_gp: list) -> None:
        """Stop, without checkpointing the broken state, when the losses leave finite values or
        the critic's gradient penalty runs away (a healthy WGAN-GP keeps it well below 1)."""
        bad = [k for k in ("loss_d", "loss_g", "gp") if not math.isfinite(row[k])]
        runaway = (self.cfg.diverge_gp > 0 and len(recent_gp) == 50
                   and float(np.mean(recent_gp)) > self.cfg.diverge_gp)
        if not bad and not runaway:
            return
        if self.rank == 0:
            self._write_log_rows([row])
        what = (f"non-finite {', '.join(bad)}" if bad else
                f"mean gradient penalty {np.mean(recent_gp):.3g} over 50 steps > diverge_gp "
                f"{self.cfg.diverge_gp:g}")
        snaps = sorted((self.run / "checkpoints").glob("step-*.pt"))
        back = (f"; roll back with: cp {snaps[-1]} {self.run / 'checkpoint.pt'} and resume with "
                "other settings" if snaps else "")
        raise TrainingDiverged(f"training diverged at step {self.step}: {what}. checkpoint.pt "
                               f"(step {self.step - self.step % self.cfg.checkpoint_every}) was "
                               f"not overwritten{back}")

    # --- logging ------------------------------------------------------------------------------
    def _write_log_rows(self, rows, mode="a") -> None:
        path = self.run / "log.csv"
        new = mode == "w" or not path.exists()
        with open(path, mode, newline="") as f:
            w = csv.DictWriter(f, fieldnames=LOG_FIELDS)
            if new:
                w.writeheader()
            w.writerows(rows)

    def _tensorboard(self, row: dict) -> None:
        if self._tb is None:
            try:
                from torch.utils.tensorboard import SummaryWriter
                self._tb = SummaryWriter(str(self.run / "tensorboard"), purge_step=self.step)
            except ImportError:
                self._tb = False
        if self._tb:
            for k in ("loss_d", "loss_g", "gp", "wasserstein"):
                self._tb.add_scalar(k, row[k], row["step"])

    # --- one step (the family computes it with these) -----------------------------------------
    def next_batch(self):
        """(the family's real batch of this rank, nu): the batch counter's next batch."""
        idx = self.data.batch_indices(self.cfg.seed, self.batch_counter, self.cfg.batch_size,
                                      self.rank, self.world)
        self.batch_counter += 1
        return self.family.batch(self, idx), torch.from_numpy(self.data.nu[idx])

    def autocast(self):
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.cfg.bf16)

    def update_average(self) -> None:
        if self.G_ema is None:
            return
        # warm-up: early weights are forgotten quickly (decay (1 + n) / (10 + n) until it
        # reaches cfg.ema), so a short run's average is not dominated by its initialisation
        n = self.step - self.ema_since
        ema_update(self.G_ema, self.G, min(self.cfg.ema, (1.0 + n) / (10.0 + n)))

    def finish_step(self, loss_d, loss_g, gp, wasserstein) -> dict:
        """After the optimiser steps: the generator's average, the step count, the log row."""
        self.update_average()
        self.step += 1
        return {"step": self.step, "epoch": round(self.batch_counter / self.bpe, 4),
                "loss_d": _g7(loss_d), "loss_g": _g7(loss_g), "gp": _g7(gp),
                "wasserstein": _g7(wasserstein)}

    def allreduce_grads(self, model) -> None:
        _allreduce_grads(model, self.world)

    def sync_buffers(self, model) -> None:
        """Data parallel: BatchNorm buffers follow rank 0."""
        if self.world > 1:
            _broadcast(model, buffers_only=True)

    def train_step(self) -> dict:
        return self.family.train_step(self)

    def _any_rank(self, flag: bool) -> bool:
        """True on every rank when it is true on one: clocks differ between processes, and a
        rank that leaves the loop alone would leave the others waiting in all_reduce."""
        if self.world == 1:
            return flag
        import torch.distributed as dist
        t = torch.tensor([int(flag)])
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item())

    def fit(self, max_seconds: float | None = None) -> dict:
        """Train to ``total_steps`` (or until ``max_seconds`` pass); checkpoint on the way."""
        bar = None
        if self.progress and self.rank == 0:
            try:
                from tqdm import tqdm
                bar = tqdm(total=self.total_steps, initial=self.step, unit="step")
            except ImportError:
                bar = None
        t0 = time.perf_counter()
        pending = []
        last = {}
        recent_gp: list[float] = []
        budget_s = None if self.cfg.hours is None else budget_seconds(self.cfg.hours)
        with _StopOnSignal(enabled=self.world == 1) as interrupted:
            while self.step < self.total_steps and (budget_s is None
                                                    or self.seconds_before < budget_s):
                row = self.train_step()
                recent_gp = (recent_gp + [row["gp"]])[-50:]
                self._check_divergence(row, recent_gp)
                row["seconds"] = round(self.seconds_before + time.perf_counter() - t0, 3)
                last = row
                if self.rank == 0:
                    pending.append(row)
                    if self.step % self.cfg.log_every == 0 or self.step == self.total_steps:
                        self._write_log_rows(pending)
                        for r in pending:
                            self._tensorboard(r)
                        pending = []
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(L_D=f"{row['loss_d']:.3f}", L_G=f"{row['loss_g']:.3f}")
                    elif self.progress and self.step % 50 == 0:
                        print(f"step {self.step}/{self.total_steps} L_D {row['loss_d']:.4f} "
                              f"L_G {row['loss_g']:.4f}", file=sys.stderr, flush=True)
                if self.step % self.cfg.checkpoint_every == 0:
                    if self.rank == 0:
                        self._write_log_rows(pending)
                        pending = []
                    self.save()
                stop = ((max_seconds is not None and time.perf_counter() - t0 > max_seconds)
                        or (budget_s is not None and row["seconds"] >= budget_s)
                        or interrupted.fired is not None)
                if self._any_rank(bool(stop)):
                    break
            if self.rank == 0 and pending:
                self._write_log_rows(pending)
            self.save()
        if bar is not None:
            bar.close()
        if self._tb:
            self._tb.flush()
        out = {"step": self.step, "total_steps": self.total_steps, "last": last,
               "seconds": round(time.perf_counter() - t0, 3),
               "param_checksum": param_checksum(self.G) + param_checksum(self.D)
               + param_checksum(self.G_ema)}
        if interrupted.fired:
            out["interrupted"] = interrupted.fired
        return out


class _StopOnSignal:
    """Ctrl-C (SIGINT) or SIGTERM during training: finish the current step, checkpoint, stop.

    The first signal only sets :attr:`fired` (the loop checks it after each step, so the
    checkpoint is a whole step); the handlers are then put back, so a second Ctrl-C stops at
    once. Only in a single process on the main thread (torchrun stops its ranks itself)."""

    SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.fired: str | None = None
        self._old = {}

    def _handle(self, signum, frame) -> None:
        self.fired = signal.Signals(signum).name
        self._restore()

    def _restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}

    def __enter__(self):
        if self.enabled:
            for name in self.SIGNALS:
                sig = getattr(signal, name)
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()


# What a resumed run may change (its length, budget and bookkeeping); every other setting is
# the run's own, and a different value given on resume is refused rather than ignored.
RESUMABLE = ("steps", "epochs", "checkpoint_every", "threads", "keep_every", "diverge_gp",
             "ema", "hours", "bf16")


def read_checkpoint(path) -> dict:
    """A training checkpoint; one that cannot be read (a partial copy, a full disk, another
    file under its name) is named, with what to do, instead of a traceback."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except FileNotFoundError:
        raise
    except Exception as exc:  # noqa: BLE001 - pickle and zip raise many types on bad files
        raise InputError(f"{path} is not a readable checkpoint ({type(exc).__name__}: {exc}); "
                         + _checkpoint_way_on(path)) from exc
    if not isinstance(state, dict) or "step" not in state or "train" not in state:
        raise InputError(f"{path} is not an APCG training checkpoint (no step and settings)")
    return state


def _checkpoint_way_on(path: Path) -> str:
    """What can replace an unreadable checkpoint ``path`` (the run's checkpoint.pt or one of
    its kept copies): the run's other kept copies where there are any, else nothing can, and
    the run must start again."""
    kept_dir = path.parent if path.parent.name == "checkpoints" else path.parent / "checkpoints"
    run = kept_dir.parent
    kept = [p for p in sorted(kept_dir.glob("step-*.pt")) if p.resolve() != path.resolve()]
    if kept:
        return (f"a kept copy in {kept_dir} (--keep-every; the latest is {kept[-1].name}) can "
                f"replace it: cp {kept[-1]} {run / 'checkpoint.pt'} and resume (or export "
                f"--checkpoint {kept[-1]})")
    return (f"the run kept no other copy ({kept_dir} "
            + ("holds none" if kept_dir.is_dir() else "does not exist")
            + "; --keep-every keeps them), so nothing can replace it: train the run again "
            f"without --resume, into another -o (or after removing {run})")


def dataset_type_names(header: dict) -> list[str]:
    """The type names of a dataset header in code order: what a run's network learnt code by
    code, recorded with the run."""
    from apcg_core.typetable import TypeTable
    return TypeTable.from_records(header["types"]).names


# What of a dataset defines a run's network (train_config.json ``dataset_defines``), in the
# order a refusal lists what differs: the types code by code, the lidar (its window is the
# network's image), the condition space (nu is scaled over it), the range quantisation and the
# sensor (photon clouds, or none: ideal standard clouds).
DATASET_DEFINES = ("types", "lidar", "condition_space", "quantize", "sensor")


def dataset_defines(header: dict) -> dict:
    """What the dataset whose header is ``header`` defines for a network trained on it
    (:data:`DATASET_DEFINES`), recorded with a run when it starts."""
    cfg = header.get("config") if isinstance(header.get("config"), dict) else {}
    return {"types": dataset_type_names(header), "lidar": header.get("lidar"),
            "condition_space": header.get("condition_space"),
            "quantize": bool(cfg.get("quantize", True)),  # the builder's default
            "sensor": header.get("sensor")}


def _said(key: str, value) -> str:
    if key == "sensor":
        if value is None:
            return "none (ideal standard clouds)"
        name = value.get("name") if isinstance(value, dict) else None
        return f"{name or 'unnamed'} (photon clouds)"
    if key == "types":
        return repr(list(value)) + " code by code"
    return json.dumps(value, sort_keys=True, separators=(", ", ": "))


def _one_difference(key: str, now, ran) -> str:
    """``key`` of the dataset against the run's record, only the parts that differ of a
    table (a lidar, a condition space, a sensor of other values)."""
    same_sensor_name = (key == "sensor" and isinstance(now, dict) and isinstance(ran, dict)
                        and now.get("name") == ran.get("name"))
    if isinstance(now, dict) and isinstance(ran, dict) and (key != "sensor" or same_sensor_name):
        keys = [k for k in sorted(set(now) | set(ran)) if _canon(now.get(k)) != _canon(ran.get(k))]
        show = lambda d: ", ".join(f"{k} {json.dumps(d.get(k))}" for k in keys)  # noqa: E731
        return f"{key} {show(now)} (the run's: {show(ran)})"
    return f"{key} {_said(key, now)} (the run's: {_said(key, ran)})"


def _canon(value) -> str:
    return json.dumps(value, sort_keys=True)


def check_same_dataset(record: dict, header: dict, data, what: str, run=None) -> None:
    """Refuse (``what``: the step asking; ``run``: the run) a dataset that is not the one the
    run trained on: what its record's ``dataset_defines`` says of that dataset (types code by
    code, lidar, condition space, quantisation, sensor) against ``header``. A run recorded
    before that record is compared on what it records (``dataset_types``; one before those is
    not checked). A dataset rebuilt or replaced at the run's path would otherwise silently
    train on, or export a model of, clouds the network never learnt."""
    ran = record.get("dataset_defines")
    if not isinstance(ran, dict):
        ran = ({"types": record["dataset_types"]} if record.get("dataset_types") is not None
               else {})
    now = dataset_defines(header)
    differ = [_one_difference(k, now[k], ran[k]) for k in DATASET_DEFINES
              if k in ran and _canon(now[k]) != _canon(list(ran[k]) if k == "types"
                                                           else ran[k])]
    if differ:
        record_of = f"{run}'s train_config.json" if run is not None else "its record"
        raise InputError(f"{what}: the dataset {data} is not the dataset the run learnt "
                         f"({record_of} says another): its " + "; its ".join(differ)
                         + ". Give the run's own dataset (or train a new run on this one)")


def read_run_record(run) -> dict | None:
    """A run's ``train_config.json`` (None when the run has none); a damaged one is named."""
    path = Path(run) / "train_config.json"
    if not path.exists():
        return None
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path} is corrupt ({exc}); it is written by `apcg train`") from exc
    if not isinstance(rec, dict) or not isinstance(rec.get("train"), dict) or "data" not in rec:
        raise InputError(f"{path} is not an APCG run record (needs 'train' and 'data'); it is "
                         "written by `apcg train`")
    return rec


def budget_seconds(hours: float) -> float:
    """An hours budget in logged seconds.

    The log keeps milliseconds, so the budget does too: 0.0004 h is 1.4400000000000002 s in
    floating point, and a step logged at 1.440 s must count as having spent it.
    """
    return round(hours * 3600.0, 3)


def _g7(t) -> float:
    """A logged loss: 7 significant digits keep the log small (it ships with the model)."""
    return float(f"{float(t.detach() if isinstance(t, torch.Tensor) else t):.7g}")


class TrainingDiverged(APCGError):
    """The losses ran away; the last good checkpoint is kept."""


def param_checksum(model) -> float:
    if model is None:
        return 0.0
    return float(sum(p.detach().double().sum() for p in model.parameters()))


def _dist_rank_world() -> tuple[int, int]:
    if "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        import torch.distributed as dist
        if not dist.is_initialized():
            dist.init_process_group("gloo")
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _allreduce_grads(model, world: int) -> None:
    if world == 1:
        return
    import torch.distributed as dist
    for p in model.parameters():
        if p.grad is not None:
            dist.all_reduce(p.grad, op=dist.ReduceOp.SUM)
            p.grad /= world


def _broadcast(model, buffers_only: bool = False) -> None:
    import torch.distributed as dist
    tensors = list(model.buffers()) if buffers_only else list(model.state_dict().values())
    for t in tensors:
        if t.dtype.is_floating_point or t.dtype in (torch.int64,):
            dist.broadcast(t, 0)


def config_from(preset: str, **overrides) -> TrainConfig:
    """The preset, then the family's own defaults (a family's ``train_defaults``: what its
    training needs that the preset, made for the GANs, does not say), then ``overrides``."""
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; accepted: {', '.join(PRESETS)}")
    over = {k: v for k, v in overrides.items() if v is not None}
    family = get_family(over.get("family", PRESETS[preset].family), need="train_step")
    cfg = replace(PRESETS[preset], **getattr(family, "train_defaults", {}))
    return replace(cfg, **over)
