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

Resuming (``--resume``): the settings that define the run (teacher, compared as a path; width,
head, batch size, learning rate, seed) must be the run's, and those left out on the command
line are taken from its checkpoint; ``--steps``, ``--minutes`` and ``--checkpoint-every`` may
change (:data:`RESUMABLE`). Every torch file read back goes through :func:`read_torch_state`.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, fields
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


# What may change when a run is resumed (as `apcg train` lets its budget change): the length of
# the run and how often it writes. Every other setting defines the run; a resume that gives
# another value is refused, and one that leaves a setting out takes the run's.
RESUMABLE = ("steps", "minutes", "checkpoint_every", "log_every")
# How the CLI says to continue an interrupted run (the Ctrl-C message; apcg_core.cli)
RESUME_HINT = "Add --resume to the same command (or run `apcg distill --resume -o RUN`) to " \
              "continue from the last checkpoint."


def _one_line(exc: BaseException, limit: int = 200) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[:limit - 3] + "..."


# What a torch file of this project holds, by its keys: how a foreign one is named.
_KINDS = ((("train", "step"), "a checkpoint of `apcg train` (continue it with `apcg train "
                              "--resume`)"),
          (("config", "student", "step"), "a checkpoint of `apcg distill`"),
          (("state", "n_types", "shape"), "an FD-depth encoder of `apcg fd-depth train`"))


def holds(state) -> str:
    """What a loaded torch file holds, in words, for a message."""
    if isinstance(state, dict):
        for keys, name in _KINDS:
            if all(k in state for k in keys):
                return name
        keys = sorted(map(str, state))
        shown = ", ".join(keys[:8]) + (f" ... ({len(keys)} keys)" if len(keys) > 8 else "")
        return f"a dict of {shown}" if keys else "an empty dict"
    return f"a {type(state).__module__}.{type(state).__qualname__}".replace("builtins.", "")


def read_torch_state(path, what: str, needs: tuple, made_by: str,
                     remedy: str | None = None) -> dict:
    """The dict a torch file of this project holds (a distillation checkpoint, an FD-depth
    encoder; ``training.trainer.read_checkpoint`` reads training checkpoints the same way):
    a missing, empty, truncated or corrupt file, or one holding something else, is one
    InputError naming the file, what it holds and what was expected, never a traceback.
    Loaded with ``weights_only``: a foreign pickle runs no code. ``remedy``: what to do about
    a damaged file (default: make it again with ``made_by``)."""
    import torch
    path = Path(path)
    remedy = remedy or f"{made_by} writes it again"
    if path.is_dir():
        raise InputError(f"{path} is a directory, not {what}; {made_by} writes one")
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(f"{path} does not exist; expected {what}, which {made_by} "
                         "writes") from None
    if size == 0:
        raise InputError(f"{path} is empty (0 bytes), not {what}: an interrupted copy or a "
                         f"full disk? {remedy}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except PermissionError:
        raise  # the CLI names the file and says to check its permissions
    except Exception as exc:  # noqa: BLE001 - zip, pickle and torch raise many types
        raise InputError(f"{path} ({size} bytes) cannot be read as {what} "
                         f"({type(exc).__name__}: {_one_line(exc)}): truncated, corrupt or "
                         f"another kind of file; {remedy}") from exc
    missing = [k for k in needs if not isinstance(state, dict) or k not in state]
    if missing:
        raise InputError(f"{path} holds {holds(state)}, not {what} (which holds "
                         f"{', '.join(needs)}); {made_by} writes one")
    return state


def read_distill_checkpoint(path) -> dict:
    """A distillation run's checkpoint (see :func:`read_torch_state`), its settings checked
    to be a :class:`DistillConfig`'s."""
    st = read_torch_state(path, "an `apcg distill` checkpoint",
                          ("config", "student", "opt", "ema", "step", "elapsed_s"),
                          "`apcg distill`", remedy="the run cannot continue from it: start it "
                          "over with --force (without --resume), or choose another -o")
    names = {f.name for f in fields(DistillConfig)}
    cfg = st["config"]
    if not isinstance(cfg, dict) or "teacher" not in cfg or set(cfg) - names:
        raise InputError(f"{path} holds settings {holds(cfg)}, not an `apcg distill` run's "
                         f"({', '.join(sorted(names))})")
    return st


def same_path(a, b) -> bool:
    """Whether two spellings name one file or directory (./m and m, a link and its target)."""
    return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()


def resume_differences(run_cfg: dict, cfg: DistillConfig) -> list[str]:
    """The settings that define a run (all but :data:`RESUMABLE`) in which ``cfg`` differs
    from the run's own, as ``--name value (the run's: value)``; the teacher compared as a
    path (``./m`` and ``m`` are one teacher)."""
    new = asdict(cfg)
    out = []
    for k, v in new.items():
        if k in RESUMABLE or k not in run_cfg:
            continue
        old = run_cfg[k]
        if k == "teacher" and same_path(old, v) or old == v:
            continue
        out.append(f"--{k.replace('_', '-')} {v} (the run's: {old})")
    return out


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
    # a run of ours that stopped before its first checkpoint has nothing to keep: the same
    # command, with --resume or without, starts it over
    unstarted = (run / "distill_config.json").is_file() and not ck_path.exists()
    if run.is_dir() and any(run.iterdir()) and not (resume or force or unstarted):
        raise InputError(f"{run} exists and is not empty; --resume continues the run there, "
                         "or choose another -o")
    if resume and not ck_path.exists():
        if not unstarted:
            raise InputError(f"--resume: {ck_path} does not exist; nothing to continue")
        resume = False
    if unstarted and progress:
        print(f"distill: {run} stopped before its first checkpoint; starting it over",
              file=sys.stderr)
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
        st = read_distill_checkpoint(ck_path)
        diff = resume_differences(st["config"], cfg)
        if diff:
            raise InputError(f"--resume: the run in {run} was started with other settings: "
                             f"{'; '.join(diff)}; leave them out (or give the run's) to "
                             "resume it, or choose another -o for a new run")
        try:
            student.load_state_dict(st["student"])
            opt.load_state_dict(st["opt"])
            ema = [t.to(dev) for t in st["ema"]]
            if len(ema) != len(list(student.parameters())):
                raise ValueError(f"{len(ema)} averaged tensors for "
                                 f"{len(list(student.parameters()))} parameters")
        except (RuntimeError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise InputError(f"{ck_path} does not fit the student of its own settings "
                             f"({_one_line(exc)}); it is not this run's checkpoint: "
                             "choose another -o for a new run") from exc
        step, elapsed = int(st["step"]), float(st["elapsed_s"])
        if step > cfg.steps:
            raise InputError(f"--steps {cfg.steps}: the run in {run} is at step {step} "
                             f"already; give --steps >= {step} to resume it")
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
            import shlex
            print(f"distill: interrupted at step {step}; `apcg distill --resume -o "
                  f"{shlex.quote(str(run))}` goes on from the checkpoint at step {saved}"
                  + ("" if saved else " (none written yet: it starts over)"),
                  file=sys.stderr, flush=True)
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
    left = " (on --resume: the run's)"
    p = sub.add_parser("distill", help="fit a cheaper network to a trained model (no dataset)",
                       description="Distils a model of the apcg-plus family into a smaller "
                                   "network: conditions drawn over the model's space, the "
                                   "teacher's sheets as targets. Writes RUN/checkpoint.pt, "
                                   "RUN/log.csv and the model, RUN/model. --resume continues "
                                   "a run: settings left out are the run's, --steps and "
                                   "--minutes may change, any other setting must be the "
                                   "run's.")
    p.add_argument("--teacher", default=None, metavar="DIR",
                   help="the model to distil (default: the shipped default model; on "
                        "--resume: the run's)")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="run directory",
               files=("distill_config.json", "checkpoint.pt", "log.csv"),
               record=("distill_config.json",))
    p.add_argument("--resume", action="store_true", help="continue the run in -o")
    p.add_argument("--width", type=float, help=f"the student's channel width (default "
                                               f"{d.width}){left}")
    p.add_argument("--head", choices=HEADS,
                   help=f"how the student draws its sheet (default {d.head}){left}")
    p.add_argument("--steps", type=int, help=f"default {d.steps}{left}; may change on resume")
    p.add_argument("--minutes", type=float,
                   help=f"cap on the run's time, summed over resumes{left}; may change on "
                        "resume")
    p.add_argument("--batch-size", type=int,
                   help=f"conditions a step (default {d.batch_size}){left}")
    p.add_argument("--lr", type=float, help=f"peak learning rate ({d.lr:g}){left}")
    p.add_argument("--seed", type=int, help=f"default {d.seed}{left}")
    p.add_argument("--checkpoint-every", type=int,
                   help=f"default {d.checkpoint_every}{left}; may change on resume")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="auto (a GPU when torch sees one, default), cpu or cuda")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_distill, resume_hint=RESUME_HINT)


# the options that are DistillConfig's fields (None: not given)
_OPTIONS = ("width", "head", "steps", "minutes", "batch_size", "lr", "seed", "checkpoint_every")


def config_of(args) -> DistillConfig:
    """The run's settings from the command line: those given; on --resume of a run that has
    a checkpoint, the run's own for those left out (teacher included), else the defaults."""
    given = {k: getattr(args, k) for k in _OPTIONS if getattr(args, k, None) is not None}
    if args.teacher:
        # a path that means the same from any directory (a resume may run elsewhere)
        given["teacher"] = str(Path(args.teacher).expanduser().absolute())
    ck = Path(args.output) / "checkpoint.pt"
    if args.resume and ck.exists():
        values = {**read_distill_checkpoint(ck)["config"], **given}
    else:
        from apcg_core.families import default_model_dir
        values = {**asdict(DistillConfig(teacher=str(default_model_dir()))), **given}
    return DistillConfig(**values)


def _run_distill(args) -> int:
    cfg = config_of(args)
    out = distill(cfg.teacher, args.output, cfg, device=args.device, resume=args.resume,
                  force=args.force, progress=not args.no_progress)
    print(json.dumps(out))
    return 0


__all__ = ["RESUMABLE", "DistillConfig", "config_of", "distill", "read_distill_checkpoint",
           "read_torch_state", "register_distill", "resume_differences", "schedule",
           "step_conditions"]
