"""Distil a trained model into a cheaper network of its family: ``apcg distill``.

A model of the APCG+ family is a function of the condition (its sheets depend on nothing
else), so a smaller network can be fitted to it directly, with no dataset: every step draws a
batch of conditions uniformly over the teacher's condition space and types (nu in [-1, 1]),
asks the teacher for its sheets and fits the student's to them, cell by cell, over the whole
sheet (the family's ``distill_loss``). The student inherits the teacher's condition space,
lidar, types and tau; ``apcg choose-tau`` may pick its own afterwards, and ``apcg evaluate``
scores it against the simulator like any model.

Determinism: the conditions of step k come from (seed, k) alone, so a resumed run draws what
an uninterrupted one would. The step count fixes the schedule (cosine decay); ``--minutes``
caps the run's time, and a run stopped by the cap has followed the schedule by time instead
(so its rate has reached the end too), which no longer depends on the step count alone.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from apcg_core.errors import InputError, check_finite, check_int
from apcg_core.outputs import DIRECTORY, add_output


@dataclass(frozen=True)
class DistillConfig:
    teacher: str
    width: float = 0.5
    head: str = "upconv"
    steps: int = 20000
    minutes: float | None = None
    batch_size: int = 512
    lr: float = 2e-3
    warmup: int = 200
    ema: float = 0.999
    seed: int = 0
    checkpoint_every: int = 1000
    log_every: int = 10

    def check(self) -> None:
        """The run's own settings; the student's architecture (width, head) is checked by its
        network configuration (PlusConfig), before anything is written."""
        check_int("steps", self.steps, 1)
        check_int("batch_size", self.batch_size, 2)
        check_int("seed", self.seed, 0)
        check_int("checkpoint_every", self.checkpoint_every, 1)
        check_int("log_every", self.log_every, 1)
        if not check_finite("--lr", self.lr) > 0:
            raise InputError(f"--lr must be a number > 0, got {self.lr!r}")
        if not 0 <= check_finite("--ema", self.ema) < 1:
            raise InputError(f"--ema must be in [0, 1), got {self.ema!r}")
        if self.minutes is not None and not check_finite("--minutes", self.minutes) > 0:
            raise InputError(f"--minutes must be > 0, got {self.minutes!r}")


def step_conditions(n_types: int, n: int, seed: int, step: int):
    """Step ``step``'s batch: type codes uniform over the model's types, the scaled pose
    (nu without its type column) uniform in [-1, 1]^5: the whole condition space."""
    rng = np.random.default_rng([seed, step])
    codes = rng.integers(0, n_types, n).astype(np.int64)
    pose = rng.uniform(-1.0, 1.0, (n, 5)).astype(np.float32)
    return codes, pose


def schedule(cfg: DistillConfig, step: int, elapsed_s: float) -> float:
    """The learning rate: linear warm-up, then cosine decay to 1 % over the run, the run's
    progress being its steps or, under ``minutes``, its time, whichever is further."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    p = step / cfg.steps
    if cfg.minutes is not None:
        p = max(p, elapsed_s / (60.0 * cfg.minutes))
    p = min(1.0, p)
    return cfg.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * p)))


def pick_device(name: str):
    import torch
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: torch sees no CUDA device here; use --device cpu")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


def distill(teacher_dir, run_dir, cfg: DistillConfig, device: str = "auto",
            resume: bool = False, force: bool = False, progress: bool = True) -> dict:
    """Fit a student of ``cfg`` to the teacher model in ``teacher_dir``; the run (checkpoint,
    log, config) goes to ``run_dir`` and the model to ``run_dir/model``. Returns a summary."""
    import torch

    from apcg_core.families import get_family, load_model
    from apcg_core.io.atomic import atomic_path
    from apcg_core.io.dataset import write_atomic
    from apcg_core.testpoints import wait_point
    cfg.check()
    teacher_model = load_model(teacher_dir)
    family = get_family(teacher_model.family, need="load")
    if not callable(getattr(family, "distill_networks", None)):
        raise InputError(f"{teacher_model.directory} is a {teacher_model.family} model, which "
                         "cannot be distilled (its output is not a function of the condition "
                         "alone); distil an apcg-plus model (the default)")
    run = Path(run_dir)
    ck_path = run / "checkpoint.pt"
    if run.is_dir() and any(run.iterdir()) and not (resume or force):
        raise InputError(f"{run} exists and is not empty; --resume continues the run there, "
                         "or choose another -o")
    if resume and not ck_path.is_file():
        raise InputError(f"--resume: {ck_path} does not exist; nothing to continue")
    dev = pick_device(device)
    torch.manual_seed(cfg.seed)
    # the student first: a refused width or head leaves nothing on disk
    teacher, student = family.distill_networks(teacher_model, width=cfg.width, head=cfg.head)
    teacher, student = teacher.to(dev).eval(), student.to(dev)
    for p in teacher.parameters():
        p.requires_grad_(False)
    ema = [p.detach().clone() for p in student.parameters()]
    opt = torch.optim.Adam(student.parameters(), lr=cfg.lr, betas=(0.9, 0.99))
    step, elapsed = 0, 0.0
    if resume:
        st = torch.load(ck_path, map_location=dev, weights_only=False)
        if st["config"] != asdict(cfg):
            diff = sorted(k for k in st["config"] if st["config"][k] != asdict(cfg).get(k))
            raise InputError(f"--resume: the run in {run} was started with other settings "
                             f"({', '.join(diff)}); resume it with the same ones")
        student.load_state_dict(st["student"])
        opt.load_state_dict(st["opt"])
        ema = [t.to(dev) for t in st["ema"]]
        step, elapsed = st["step"], st["elapsed_s"]
    # every file through the running command's guard (an input is never written), whole
    write_atomic(run / "distill_config.json", (json.dumps(
        {**asdict(cfg), "device": str(dev), "teacher_tau": teacher_model.tau}, indent=1)
        + "\n").encode())
    log_path = run / "log.csv"
    head = "step,loss_logit,loss_depth,lr,seconds\n"
    if resume and log_path.exists():  # drop rows past the checkpoint: they are redone
        from apcg_core.io.csv_table import read_csv
        table = read_csv(log_path, required=("step",), what="distillation log")
        head += "".join(table.lines[r.line - 1].rstrip("\r\n") + "\n" for r in table
                        if r.int("step") <= step)
    write_atomic(log_path, head.encode())
    tau = float(teacher_model.tau)
    n_types = len(teacher_model.types.names)

    def save() -> int:
        with atomic_path(ck_path) as tmp:
            torch.save({"config": asdict(cfg), "student": student.state_dict(),
                        "opt": opt.state_dict(), "ema": [t.cpu() for t in ema], "step": step,
                        "elapsed_s": elapsed, "net": student.cfg.to_dict()}, tmp)
        return step

    saved = step  # the step of the checkpoint on disk (a resumed run's, or none yet: 0)
    t_start = time.perf_counter() - elapsed
    last_report = 0.0
    with log_path.open("a", newline="") as log:
        writer = csv.writer(log)
        try:
            while step < cfg.steps:
                elapsed = time.perf_counter() - t_start
                if cfg.minutes is not None and elapsed >= 60.0 * cfg.minutes:
                    break
                lr = schedule(cfg, step, elapsed)
                for g in opt.param_groups:
                    g["lr"] = lr
                codes, pose = step_conditions(n_types, cfg.batch_size, cfg.seed, step)
                codes_t = torch.from_numpy(codes).to(dev)
                pose_t = torch.from_numpy(pose).to(dev)
                with torch.no_grad():
                    target = teacher(codes_t, pose_t)
                out = student(codes_t, pose_t)
                l_logit, l_depth = family.distill_loss(out, target, tau)
                loss = l_logit + l_depth
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(student.parameters(), 1.0)
                opt.step()
                decay = min(cfg.ema, (1.0 + step) / (10.0 + step))  # short runs average less
                with torch.no_grad():
                    for e, p in zip(ema, student.parameters(), strict=True):
                        e.lerp_(p.detach(), 1.0 - decay)
                step += 1
                if step % cfg.log_every == 0 or step == cfg.steps:
                    elapsed = time.perf_counter() - t_start
                    writer.writerow([step, f"{l_logit.item():.6g}", f"{l_depth.item():.6g}",
                                     f"{lr:.4g}", f"{elapsed:.1f}"])
                    if progress and elapsed - last_report >= 10.0:
                        last_report = elapsed
                        print(f"distill: step {step}/{cfg.steps}  logit {l_logit.item():.4f}  "
                              f"depth {l_depth.item():.5f}  lr {lr:.2e}  {elapsed:.0f} s "
                              f"({step / max(elapsed, 1e-9):.1f} steps/s)", file=sys.stderr,
                              flush=True)
                if step % cfg.checkpoint_every == 0:
                    log.flush()
                    saved = save()
                    wait_point("distill.checkpoint-written")
        except KeyboardInterrupt:
            # Ctrl-C may land inside a step: the last checkpoint, whole and consistent, is
            # kept, and --resume redoes the steps after it exactly as they were
            print(f"distill: interrupted at step {step}; `apcg distill --resume -o {run}` "
                  f"goes on from the checkpoint at step {saved}", file=sys.stderr, flush=True)
            raise
    elapsed = time.perf_counter() - t_start
    if saved != step or not ck_path.is_file():  # else written at its last step already
        save()
    with torch.no_grad():
        for e, p in zip(ema, student.parameters(), strict=True):
            p.copy_(e)
    student = student.cpu().eval()
    meta = {"distilled": {"teacher": str(teacher_model.directory), "teacher_tau": tau,
                          "steps": step, "seconds": round(elapsed, 1), "device": str(dev),
                          "config": asdict(cfg)}}
    from apcg_core.outputs import staged_directory
    with staged_directory(run / "model") as stage:
        family.export_distilled(student, teacher_model, stage, meta)
        for name in ("distill_config.json", "log.csv"):
            (stage / name).write_bytes((run / name).read_bytes())
    summary = {"run": str(run), "model": str(run / "model"), "steps": step,
               "seconds": round(elapsed, 1), "device": str(dev)}
    if progress:
        print(f"distilled {step} steps in {elapsed:.0f} s -> {run / 'model'}", file=sys.stderr)
    return summary


def register_distill(sub) -> None:
    from apcg_core.families.plus_heads import HEADS
    d = DistillConfig(teacher="")
    p = sub.add_parser("distill", help="fit a cheaper network to a trained model (no dataset)",
                       description="Distils a model of the apcg-plus family into a smaller "
                                   "network: conditions drawn over the model's space, the "
                                   "teacher's sheets as targets. Writes RUN/checkpoint.pt, "
                                   "RUN/log.csv and the model, RUN/model.")
    p.add_argument("--teacher", default=None, metavar="DIR",
                   help="the model to distil (default: the shipped default model)")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="run directory",
               files=("distill_config.json", "checkpoint.pt", "log.csv"),
               record=("distill_config.json",))
    p.add_argument("--resume", action="store_true", help="continue the run in -o")
    p.add_argument("--width", type=float, default=d.width,
                   help=f"the student's channel width (default {d.width})")
    p.add_argument("--head", choices=HEADS, default=d.head,
                   help=f"how the student draws its sheet (default {d.head})")
    p.add_argument("--steps", type=int, default=d.steps, help=f"default {d.steps}")
    p.add_argument("--minutes", type=float, default=None, help="cap on the run's time")
    p.add_argument("--batch-size", type=int, default=d.batch_size,
                   help=f"conditions a step (default {d.batch_size})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"peak learning rate ({d.lr:g})")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every)
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="auto (a GPU when torch sees one, default), cpu or cuda")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_distill)


def _run_distill(args) -> int:
    from apcg_core.families import default_model_dir
    teacher = args.teacher or str(default_model_dir())
    cfg = DistillConfig(teacher=str(teacher), width=args.width, head=args.head,
                        steps=args.steps, minutes=args.minutes, batch_size=args.batch_size,
                        lr=args.lr, seed=args.seed, checkpoint_every=args.checkpoint_every)
    out = distill(teacher, args.output, cfg, device=args.device, resume=args.resume,
                  force=args.force, progress=not args.no_progress)
    print(json.dumps(out))
    return 0


__all__ = ["DistillConfig", "distill", "register_distill", "schedule", "step_conditions"]
