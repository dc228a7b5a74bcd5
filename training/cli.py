"""``apcg train``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from apcg_core.lidar_options import add_lidar_argument, lidar_or_default, model_at_lidar
from apcg_core.options import option_name
from apcg_core.outputs import ANY, DIRECTORY, FILE, PICTURE_SUFFIXES, add_output


def register_train(sub) -> None:
    from apcg_core.families import family_names
    p = sub.add_parser("train", help="train a model family (default: the cGAN) on a dataset",
                       description="Train a model family (--family; default the improved cGAN) "
                                   "on a dataset built by `apcg dataset build`. Checkpoints to "
                                   "RUN/checkpoint.pt; --resume continues exactly. Logs: "
                                   "RUN/log.csv and RUN/tensorboard. For several processes: "
                                   "torchrun --nproc_per_node N -m apcg_core.cli train ...")
    p.add_argument("--data", required=True, help="dataset directory")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="run directory",
               files=("train_config.json", "checkpoint.pt", "log.csv"),
               record=("train_config.json",))
    p.add_argument("--preset", default=None, choices=["paper", "cpu", "tiny"],
                   help="paper: full width for a GPU; cpu: quarter width, bf16 (default); "
                        "tiny: for tests (a resumed run keeps its own)")
    p.add_argument("--resume", action="store_true", help="continue the run in -o")
    p.add_argument("--steps", type=int, help="generator steps (overrides --epochs)")
    p.add_argument("--epochs", type=float, help="epochs over the training split")
    p.add_argument("--seed", type=int)
    p.add_argument("--width", type=float, help="channel width multiplier (1.0 = the paper)")
    p.add_argument("--n-critic", type=int, help="critic steps per generator step")
    p.add_argument("--batch-size", type=int)
    # bfloat16 autocast is slower where the CPU has no bf16 instructions: on an AMD EPYC without
    # avx512_bf16 (2026-11-28), 200 steps of 32 of the width 0.75 APCG+ network from its
    # default took 28.9 s with --bf16 against 13.3 s with --no-bf16, whole process (medians of
    # 3, the two in turn; `apcg train --data D --family apcg-plus --init
    # apcg_core/models/default --width 0.75 --sheet 32 --head upconv --steps 200 --threads 1`)
    p.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                   help="bfloat16 autocast (default: the preset's; --no-bf16 on a CPU without "
                        "bf16 instructions, where it is slower than fp32: 2.2 times a whole "
                        "200-step run measured)")
    p.add_argument("--no-conv", action="store_true", help="ablation: fully connected layers")
    p.add_argument("--no-attention", action="store_true", help="ablation: no self-attention")
    p.add_argument("--bce", action="store_true", help="ablation: BCE loss, no Wasserstein/GP")
    p.add_argument("--family", choices=family_names(), default=None,
                   help="the model family to train: the paper's cgan (default) or a "
                        "comparison family (a resumed run keeps its own)")
    # Sizes some families take (a family's train_options() says which; others refuse them):
    p.add_argument("--n-points", type=int, metavar="N",
                   help="points per generated set (default 256; the lidar's nearest clouds "
                        "have more, see the README)")
    p.add_argument("--voxel-res", type=int, metavar="R",
                   help="occupancy grid resolution, 4 * 2^k (default 32)")
    p.add_argument("--diffusion-steps", type=int, metavar="T",
                   help="steps of the DDPM schedule (default 200)")
    p.add_argument("--sheet", type=int, metavar="S",
                   help="apcg-plus: side of the sheet the network draws (4 x 2^k; default 64)")
    from apcg_core.families.plus_heads import HEADS
    p.add_argument("--head", choices=HEADS,
                   help="apcg-plus: how the network draws its sheet: conv (a 3 x 3 convolution "
                        "at the sheet's resolution, default) or upconv (the last upsampling "
                        "step draws it; about 0.6 times the CPU cost)")
    from .families.apcg_plus import QUERY_MIXES
    p.add_argument("--queries", choices=QUERY_MIXES,
                   help="apcg-plus: where the loss is taken: returns (a quarter of the cells "
                        "among the sample's returns, a quarter over its box, half near the "
                        "returns; default) or silhouette (a quarter over the box, the rest near "
                        "the returns: hit probabilities that match the data's, SPEC 7a)")
    p.add_argument("--lr", type=float,
                   help="learning rate (default: the family's; a fine-tune from --init "
                        "usually wants a smaller one)")
    p.add_argument("--init", metavar="MODEL",
                   help="start the network from this model's weights (the same family, types "
                        "and network; e.g. one made by `apcg distill`) and fine-tune it on "
                        "--data")
    p.add_argument("--no-norm", action="store_true",
                   help="train on depth images without Norm (the paper's 'APCG w/o Norm.')")
    p.add_argument("--checkpoint-every", type=int, help="steps between checkpoints")
    p.add_argument("--keep-every", type=int,
                   help="also keep a copy of the checkpoint every this many steps")
    p.add_argument("--diverge-gp", type=float,
                   help="stop when the gradient penalty's 50-step mean exceeds this (0: never)")
    p.add_argument("--ema", type=float,
                   help="decay of the generator's moving average that export uses (cpu preset "
                        "0.999; 0 turns it off; may be switched on when resuming)")
    p.add_argument("--max-minutes", type=float, help="stop (after a checkpoint) after this long")
    p.add_argument("--hours", type=float,
                   help="a training-time budget: stop once the run's training time, summed "
                        "over resumes, reaches it (saved with the run; equal-hours comparisons)")
    p.add_argument("--threads", type=int, help="torch CPU threads")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_train, resume_hint="Add --resume to the same command to continue "
                                                "from the last checkpoint.")


def _run_train(args) -> int:
    """One training process per run: a second one (another resume, a second torchrun) is
    refused while the first lives; torchrun's rank 0 holds the lock for all ranks."""
    if os.environ.get("RANK", "0") != "0":
        return _train(args)
    from apcg_core.lock import ProcessLock
    with ProcessLock(Path(args.output) / ".train.lock", f"training run in {args.output}"):
        return _train(args)


def _train(args) -> int:
    from .trainer import RESUMABLE, Trainer, config_from, read_checkpoint
    over = {"steps": args.steps, "epochs": args.epochs, "seed": args.seed, "width": args.width,
            "n_critic": args.n_critic, "batch_size": args.batch_size,
            "checkpoint_every": args.checkpoint_every, "threads": args.threads,
            "keep_every": args.keep_every, "diverge_gp": args.diverge_gp, "ema": args.ema,
            "hours": args.hours, "n_points": args.n_points, "voxel_res": args.voxel_res,
            "diffusion_steps": args.diffusion_steps, "sheet": args.sheet, "head": args.head,
            "queries": args.queries,
            "init": args.init, "lr": args.lr, "bf16": args.bf16}
    if args.no_conv:
        over["conv"] = False
    if args.no_attention:
        over["attention"] = False
    if args.bce:
        over["loss"] = "bce"
    if args.no_norm:
        over["norm"] = False
    over["family"] = args.family
    saved = None
    if args.resume:
        from pathlib import Path

        ck = Path(args.output) / "checkpoint.pt"
        if ck.exists():  # a resumed run keeps its own configuration
            saved = read_checkpoint(ck)["train"]
    family = (saved.get("family", "cgan") if saved is not None  # the run's own, on resume
              else args.family or "cgan")
    _check_family_options(family, args.family, over)
    if saved is not None:
        _check_resume_matches(args, saved, over)
        saved.update({k: v for k, v in over.items() if v is not None and k in RESUMABLE})
        from .trainer import TrainConfig
        cfg = TrainConfig.from_dict(saved)
    else:
        cfg = config_from(args.preset or "cpu", **over)
    trainer = Trainer(args.data, args.output, cfg, resume=args.resume,
                      progress=not args.no_progress, preset=args.preset or "cpu")
    max_s = args.max_minutes * 60 if args.max_minutes else None
    summary = trainer.fit(max_seconds=max_s)
    if trainer.world > 1:
        summary["rank"] = trainer.rank
        print(json.dumps(summary), flush=True)
        import torch.distributed as dist
        # Leave together: a rank that exits while its peer still talks to it aborts the run.
        dist.barrier()
        dist.destroy_process_group()
        # torch's gloo threads can abort the interpreter's teardown ("terminate called without
        # an active exception", seen in 1 of 12 runs); everything is saved and flushed by now.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    elif trainer.rank == 0:
        print(json.dumps(summary))
    if summary.get("interrupted"):
        print(f"apcg train: {summary['interrupted']} at step {summary['step']}: the checkpoint "
              f"is saved; continue with: apcg train --data {args.data} -o {args.output} "
              "--resume", file=sys.stderr)
        return 130
    return 0


def _check_resume_matches(args, saved: dict, over: dict) -> None:
    from pathlib import Path

    from apcg_core.errors import InputError

    from .trainer import RESUMABLE, TrainConfig, read_run_record

    # against the run's value, or the default it ran with when its record predates the setting
    ran = TrainConfig.from_dict(saved)
    differ = [f"--{k.replace('_', '-')} {v} (the run's: {getattr(ran, k)})"
              for k, v in over.items()
              if v is not None and k not in RESUMABLE and k != "family" and hasattr(ran, k)
              and getattr(ran, k) != v]
    record = read_run_record(args.output)
    if args.preset is not None:
        _check_resume_preset(args.preset, ran, over, (record or {}).get("preset"), differ)
    if record is not None:
        ran_on = record.get("data")
        if ran_on and Path(ran_on).resolve() != Path(args.data).resolve():
            differ.append(f"--data {args.data} (the run's: {ran_on})")
    if differ:
        raise InputError("a resumed run keeps its own settings; these differ from it: "
                         + "; ".join(differ) + ". Leave them out to resume, or train a new "
                         "run with another -o")


def _check_resume_preset(preset: str, ran, over: dict, recorded: str | None,
                         differ: list) -> None:
    """A --preset given on resume: the run's own (as recorded), or, for a run that predates
    the record, one whose settings are the run's (those not given otherwise)."""
    from .trainer import config_from
    if recorded is not None:
        if recorded != preset:
            differ.append(f"--preset {preset} (the run's: {recorded})")
        return
    asked = config_from(preset, family=ran.family)
    # what a preset's network is (a run's batch size may have been given on its own)
    shape = ("width", "conv", "attention", "loss", "norm", "sheet", "head", "n_points",
             "voxel_res", "diffusion_steps")
    keys = [k for k in shape if hasattr(ran, k) and over.get(k) is None
            and getattr(asked, k) != getattr(ran, k)]
    if keys:
        differ.append(f"--preset {preset} (" + ", ".join(
            f"{k} {getattr(asked, k)!r}, the run's {getattr(ran, k)!r}" for k in keys[:4]) + ")")


def _check_family_options(family: str, asked: str | None, over: dict) -> None:
    """Refuse a family-specific size the family does not take (naming those that do), and a
    --family that is not the resumed run's."""
    from apcg_core.errors import InputError
    from apcg_core.families import family_names, get_family

    from .trainer import size_defaults
    if asked is not None and asked != family:
        raise InputError(f"--family {asked}: the run being resumed is a {family} run")
    takes = get_family(family, need="train_options").train_options()
    for name in size_defaults():
        if over.get(name) is None or name in takes:
            continue
        others = []
        for other in family_names():
            try:
                if name in get_family(other, need="train_options").train_options():
                    others.append(other)
            except InputError:  # a family that cannot train here takes nothing here
                pass
        raise InputError(f"--{name.replace('_', '-')} does not apply to the {family} family; "
                         f"it sizes {', '.join(others) or 'no installed family'} (--family)")
    fam = get_family(family, need="train_options")
    for name, option in _SWITCHES.items():
        if over.get(name) is None or name in getattr(fam, "switches", ()):
            continue
        others = [o for o in family_names()
                  if name in getattr(get_family(o), "switches", ())]
        raise InputError(f"{option} does not apply to the {family} family (its training never "
                         f"reads it); it changes {', '.join(others) or 'no installed family'} "
                         "(--family)")


# the ablation's switches: TrainConfig name -> the option that sets it
_SWITCHES = {"conv": "--no-conv", "attention": "--no-attention", "loss": "--bce",
             "norm": "--no-norm", "n_critic": "--n-critic"}


def register_export(sub) -> None:
    p = sub.add_parser("export", help="export a training run as a model directory",
                       description="Writes a model directory for `apcg generate --model`: "
                                   "model.json and what the run's family stores (the cGAN: "
                                   "generator.onnx), with the run's config and log beside "
                                   "them.")
    p.add_argument("--run", required=True, help="training run directory")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="model directory",
               files=ANY, force_help="write into an output directory that holds files "
               "(files of the same names are replaced, others kept)")
    p.add_argument("--tau", type=float, default=None,
                   help="output threshold to record (the cGAN's Im2PC tau, default -0.95; "
                        "APCG+'s hit logit, default 0); `apcg choose-tau` chooses it")
    p.add_argument("--checkpoint", help="a kept checkpoint of the run (default: the latest)")
    p.add_argument("--data", default=None,
                   help="the dataset the run trained on, where it is now (default: the path "
                        "its train_config.json records); it must be the dataset the run "
                        "learnt: its types (code by code), lidar, condition space, "
                        "quantisation and sensor, as the run recorded them")
    p.add_argument("--raw", action="store_true",
                   help="export the generator's raw weights, not their moving average")
    p.add_argument("--log-every", type=int, default=1, metavar="N",
                   help="keep every N-th step of the run's log (and the last; default 1: all), "
                        "e.g. for a model small enough to ship")
    p.add_argument("--sampling-steps", type=int, metavar="N",
                   help="families that sample on a schedule (diffusion): sample on N evenly "
                        "spaced steps of it (default: all of them; fewer is faster and "
                        "coarser); the others refuse it")
    p.set_defaults(func=_run_export)


def _run_export(args) -> int:
    from .export import export_model
    out = export_model(args.run, args.output, tau=args.tau, data_dir=args.data,
                       checkpoint=args.checkpoint, raw=args.raw,
                       sampling_steps=args.sampling_steps,
                       log_every=args.log_every, force=args.force)
    print(json.dumps({"model": str(out)}))
    return 0


def add_model_argument(p, many: bool = False) -> None:
    """``--model DIR``: a model directory, whatever its family (model.json says which)."""
    if many:
        p.add_argument("--model", action="append", required=True, metavar="DIR",
                       help="a model directory (repeatable); the method's name is the "
                            "directory's name")
    else:
        p.add_argument("--model", metavar="DIR",
                       help="model directory, any family (default: the shipped default model)")


def _pairs(args) -> int | None:
    """--pairs as the protocol takes it: 0 is every held-out pair (None), for every command
    (apcg_core/options.py states the rule once)."""
    return args.pairs or None


def add_protocol_arguments(p, pairs: bool = True) -> None:
    """The evaluation protocol's choices a user may make (training/protocol.py fixes the rest)."""
    from .protocol import DEFAULT_PAIRS
    if pairs:
        p.add_argument("--pairs", type=int, default=DEFAULT_PAIRS,
                       help="held-out pairs, stratified by band (0: the whole half); default "
                            f"{DEFAULT_PAIRS}")
    p.add_argument("--seed", type=int, default=0, help="pair draw and noise seed (default 0)")


def add_runtime_argument(p) -> None:
    from apcg_core.families import RUNTIMES
    p.add_argument("--runtime", choices=RUNTIMES, default="auto",
                   help="cGAN inference: auto (torch when installed, else onnxruntime), "
                        "onnx, torch; the same images either way")


def warn_other_lidar(command: str, data_dir, model) -> None:
    """One warning line when the dataset's lidar (its dataset.json) is not the model's
    (its model.json): the scores would compare clouds of two lidars."""
    from apcg_core.io.dataset import read_header
    from apcg_core.plausibility import lidar_mismatch_warning
    warning = lidar_mismatch_warning(read_header(data_dir).get("lidar"), data_dir,
                                     model.lidar.to_dict(), model.directory)
    if warning:
        print(f"apcg {command}: warning: {warning}", file=sys.stderr, flush=True)


def warn_other_data(command: str, data_dir, model) -> None:
    """The one check of a dataset against the model scored on it, for every command that
    scores a model against --data (evaluate, compare, choose-tau, figure 19, fd-depth score):
    a warning line for another lidar and one for clouds of another kind (a sensor's)."""
    warn_other_lidar(command, data_dir, model)
    warn_other_sensor(command, data_dir, model)


def warn_other_sensor(command: str, data_dir, model) -> None:
    """One warning line when the dataset's clouds (a sensor's photon clouds: its dataset.json
    ``sensor``) are not of the kind the model makes (its model.json ``sensor``, or none)."""
    from .evaluate import sensor_mismatch_warning
    warning = sensor_mismatch_warning(data_dir, model)
    if warning:
        print(f"apcg {command}: warning: {warning}", file=sys.stderr, flush=True)


def register_evaluate(sub) -> None:
    import argparse

    p = sub.add_parser("evaluate", help="score a model against the simulator per range band",
                       description="Held-out test conditions: a model's clouds against the "
                                   "standard clouds, MMD / JSD / Chamfer per slant-range band "
                                   "and per type beside the cell-jitter floor, by the one "
                                   "evaluation protocol (training/protocol.py); writes "
                                   "metrics.json, report.md and fig17.png.")
    add_model_argument(p)
    p.add_argument("--data", required=True, help="dataset directory (its test split is used)")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="report directory",
               files=_evaluate_files)
    add_protocol_arguments(p)
    add_runtime_argument(p)
    add_lidar_argument(p, default_help="the model's own; give the dataset's lidar to score "
                                       "the model at another lidar")
    p.add_argument("--jsd-bins-study", action="store_true",
                   help="instead: measure which bin count separates good from wrong clouds")
    p.add_argument("--with-untrained", action="store_true",
                   help="also score a freshly initialised copy of the network")
    p.add_argument("--faithfulness", action=argparse.BooleanOptionalAction, default=True,
                   help="score faithfulness (closer to its own standard cloud than to the same "
                        "type at yaw +-45 deg and to another category's type) beside the point "
                        "z-buffer and embree 2x2 on the same pairs (default: on)")
    p.set_defaults(func=_run_evaluate)


def _evaluate_files(args) -> tuple[str, ...]:
    return (("jsd_bins.json",) if args.jsd_bins_study
            else ("metrics.json", "report.md", "fig17.png"))


def _run_evaluate(args) -> int:
    from pathlib import Path

    from apcg_core.families import load_model

    from .evaluate import evaluate, jsd_bins_study, markdown, write_report
    model = model_at_lidar(load_model(args.model, runtime=args.runtime), args, "evaluate")
    warn_other_data("evaluate", args.data, model)
    command = args.command_line
    if args.jsd_bins_study:
        study = jsd_bins_study(model, args.data, seed=args.seed)
        study["command"] = command
        from apcg_core.io.dataset import write_atomic
        write_atomic(Path(args.output) / "jsd_bins.json",
                     (json.dumps(study, indent=1) + "\n").encode())
        print(json.dumps({"best": study["best"], "min_gap": study["min_gap"]}))
        return 0
    report = evaluate(model, args.data, n_pairs=_pairs(args), seed=args.seed,
                      with_untrained=args.with_untrained, progress=True,
                      faithfulness=args.faithfulness)
    report["command"] = command
    report["lidar"] = model.lidar.to_dict()  # the lidar the model generated at
    out = write_report(report, args.output)
    print(markdown(report))
    print(f"wrote {out}/metrics.json, report.md, fig17.png")
    return 0


def register_choose_tau(sub) -> None:
    p = sub.add_parser("choose-tau", help="choose a model's output threshold tau on the "
                                          "validation half",
                       description="Scores the model at several output thresholds tau (the "
                                   "cGAN's Im2PC threshold, APCG+'s hit logit) on the "
                                   "validation half of the dataset's held-out split (never "
                                   "the half that `apcg evaluate` reports on) and picks the "
                                   "lowest mean MMD that leaves at most 1% of clouds empty. "
                                   "--apply writes it into the model's model.json.")
    add_model_argument(p)
    p.add_argument("--data", required=True, help="dataset directory")
    p.add_argument("--taus", help="comma-separated thresholds (default: the model's own: "
                                  "-0.99 .. 0 for the cGAN's Im2PC, -1 .. 3 for APCG+'s hit "
                                  "logit)")
    add_protocol_arguments(p, pairs=False)
    p.add_argument("--pairs", type=int, default=400, help="validation pairs (default 400)")
    add_runtime_argument(p)
    p.add_argument("--apply", action="store_true",
                   help="write the chosen tau into the model's model.json")
    add_output(p, "-o", "--output", kind=FILE, suffixes=(".json",),
               help="also write the sweep as JSON here")
    p.set_defaults(func=_run_choose_tau)


def _run_choose_tau(args) -> int:
    from pathlib import Path

    from apcg_core.errors import InputError
    from apcg_core.families import default_model_dir, load_model
    from apcg_core.io.dataset import json_bytes, write_atomic

    from .protocol import choose_tau
    taus = None  # the model's own candidates
    if args.taus:
        try:
            taus = tuple(float(t) for t in args.taus.split(","))
        except ValueError as exc:
            raise InputError(f"--taus takes comma-separated numbers, got {args.taus!r}") from exc
    model = load_model(args.model, runtime=args.runtime)
    warn_other_data("choose-tau", args.data, model)
    rep = choose_tau(model, args.data, taus=taus, n_pairs=_pairs(args), seed=args.seed)
    rep["command"] = args.command_line
    text = json.dumps(rep, indent=1)
    print(text)
    if args.output:
        write_atomic(Path(args.output), (text + "\n").encode())
    if args.apply:
        if Path(model.directory).resolve() == default_model_dir().resolve():
            raise InputError("--apply would change the shipped default model; export a copy "
                             "(or copy its directory) and apply it there")
        meta = dict(model.meta, tau=rep["best"], tau_choice=rep)
        from apcg_core.outputs import allow_update
        allow_update(Path(model.directory) / "model.json")  # --apply changes it, by design
        write_atomic(Path(model.directory) / "model.json", json_bytes(meta))
        print(f"wrote tau {rep['best']:g} into {model.directory}/model.json", file=sys.stderr)
    return 0


def register_figure(sub) -> None:
    p = sub.add_parser("figure", help="the paper's figures 13, 14, 16, 18, 19 (and photons) "
                                      "as PNG + JSON",
                       description="13: |L_D| and L_G per epoch from a run's log. 14: MMD and "
                                   "JSD of the run's kept checkpoints against training time. "
                                   "16: generated clouds beside standard ones, 6 types x 3 "
                                   "ranges. 18: generation time against the number of clouds. 19: "
                                   "generated clouds against standard and cell-jittered ones.")
    p.add_argument("number", choices=["13", "14", "16", "18", "19", "photons"],
                   help="a figure of the paper, or photons: what a single-photon lidar "
                        "records against range and background (SPEC section 8)")
    p.add_argument("--run", action="append", metavar="[NAME=]RUN",
                   help="training run directory (13; 14 takes several, any family)")
    p.add_argument("--tau", type=float,
                   help="Im2PC threshold for the cGAN checkpoints of figure 14 (default: the "
                        "export default; use the shipped model's tau to match it)")
    p.add_argument("--model", help="model directory (16, 18, 19; default: the default model)")
    p.add_argument("--data", help="dataset directory (figure 14)")
    p.add_argument("--pairs", type=int, default=None,
                   help="test pairs per checkpoint (14, 19; default 400; 0: every test pair)")
    add_lidar_argument(p, default_help="the model's own (16, 18, 19), the paper's (photons); "
                                       "13 and 14 take none")
    p.add_argument("--max-checkpoints", type=int, metavar="K",
                   help="figure 14: score at most K kept checkpoints per run, evenly spaced, "
                        "the last always (default: all)")
    add_output(p, "-o", "--output", kind=FILE, suffixes=PICTURE_SUFFIXES, required=True,
               sidecars=(".json",), help="PNG path (the data goes beside it, as .json)")
    p.set_defaults(func=_run_figure)


# The options each figure reads (the others are refused by name); --output it always takes.
FIGURE_OPTIONS = {"13": ("run",), "14": ("run", "tau", "data", "pairs", "max_checkpoints"),
                  "16": ("model", "lidar"), "18": ("model", "lidar"),
                  "19": ("model", "lidar", "data", "pairs"), "photons": ("lidar",)}
FIGURE_OPTIONS["all"] = tuple(dict.fromkeys(k for v in FIGURE_OPTIONS.values() for k in v))
FIGURE_PAIRS = 400  # test pairs per checkpoint (figure 14) or in all (19) unless --pairs


def _run_figure(args) -> int:
    from pathlib import Path

    from apcg_core.errors import InputError

    from .figures import fig13, fig14, fig16, fig18, fig19, fig_photons
    given = [k for k in FIGURE_OPTIONS["all"] if getattr(args, k) is not None]
    extra = [k for k in given if k not in FIGURE_OPTIONS[args.number]]
    if extra:  # an option the figure does not read is refused, not ignored
        takes = ", ".join(option_name(k) for k in FIGURE_OPTIONS[args.number]) or "none of them"
        raise InputError(f"figure {args.number} does not take "
                         f"{', '.join(option_name(k) for k in extra)}; it takes {takes}")
    if args.pairs is None:
        args.pairs = FIGURE_PAIRS
    if args.number == "photons":
        fig_photons(args.output, lidar=lidar_or_default(args))
        print(f"wrote {args.output} and its .json")
        return 0
    args.number = int(args.number)
    if args.number in (13, 14) and not args.run:
        raise InputError(f"figure {args.number} needs --run (a training run directory)")
    if args.number in (14, 19) and not args.data:
        raise InputError(f"figure {args.number} needs --data (the dataset whose test split "
                         "scores)")
    if args.number == 13:
        if len(args.run) > 1:
            raise InputError(f"figure 13 takes one --run, got {len(args.run)}")
        fig13(args.run[0].split("=", 1)[-1], args.output)
    elif args.number == 14:
        runs = [(r.split("=", 1)[0], r.split("=", 1)[1]) if "=" in r
                else (Path(r).name, r) for r in args.run]
        if len({n for n, _ in runs}) < len(runs):
            raise InputError(f"figure 14: run names must differ, got {[n for n, _ in runs]}")
        fig14(runs, args.data, args.output, n_pairs=_pairs(args), tau=args.tau,
              max_checkpoints=args.max_checkpoints)
    else:
        from apcg_core.families import load_model
        model = model_at_lidar(load_model(args.model), args, "figure")
        if args.number == 16:
            fig16(model, args.output)
        elif args.number == 18:
            fig18(model, args.output)
        else:
            warn_other_data("figure", args.data, model)
            fig19(model, args.data, args.output, n_pairs=_pairs(args))
    print(f"wrote {args.output} and its .json")
    return 0


def register_fd_depth(sub) -> None:
    p = sub.add_parser("fd-depth", help="FD-depth: the Fréchet distance over features of our "
                                        "own depth-image encoder (not FID)",
                       description="train: a CNN that tells the type from a normalised depth "
                                   "image (its held-out accuracy is saved). score: the "
                                   "Fréchet distance between real and generated test images "
                                   "in its feature space.")
    s = p.add_subparsers(dest="fd_cmd", required=True)
    t = s.add_parser("train", help="train the encoder on a dataset's train split")
    t.add_argument("--data", required=True)
    add_output(t, "-o", "--output", kind=DIRECTORY, required=True, help="encoder directory",
               files=("encoder.pt", "encoder.json"))
    t.add_argument("--epochs", type=float, default=4.0)
    t.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=_run_fd_train)
    c = s.add_parser("score", help="FD-depth of a model on a dataset's test split")
    c.add_argument("--encoder", required=True)
    c.add_argument("--data", required=True)
    c.add_argument("--model", help="model directory (default: the default model)")
    c.add_argument("--pairs", type=int, default=2000)
    c.add_argument("--seed", type=int, default=0)
    c.set_defaults(func=_run_fd_score)


def _run_fd_train(args) -> int:
    from .fd_depth import train_encoder
    print(json.dumps(train_encoder(args.data, args.output, epochs=args.epochs,
                                   seed=args.seed)))
    return 0


def _run_fd_score(args) -> int:
    from apcg_core.families import load_model

    from .fd_depth import fd_depth, load_encoder
    encoder = load_encoder(args.encoder)  # its refusal first, then the dataset's
    model = load_model(args.model)
    warn_other_data("fd-depth", args.data, model)
    print(json.dumps(fd_depth(encoder, model, args.data, n_pairs=_pairs(args),
                              seed=args.seed)))
    return 0


def register_ablation(sub) -> None:
    p = sub.add_parser("ablation", help="Table 3: the 8 network / loss variants under one "
                                        "budget, scored by FD-depth, MMD and JSD",
                       description="Trains (or resumes) the 8 combinations of TConv / FC, "
                                   "self-attention on / off and Wasserstein-GP / BCE with the "
                                   "same steps, plus the full network without Norm, then "
                                   "writes table3.md and table3.json.")
    p.add_argument("--data", required=True)
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True,
               help="directory for the 9 runs + table", files=("table3.json", "table3.md"),
               record=("encoder/encoder.json", "*/train_config.json"))
    p.add_argument("--steps", type=int, default=500,
                   help="generator steps per variant (default 500, the documented Table 3)")
    p.add_argument("--width", type=float, default=0.25)
    p.add_argument("--encoder", help="FD-depth encoder (default: trained into OUTPUT/encoder)")
    p.add_argument("--pairs", type=int, default=400)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip-no-norm", action="store_true",
                   help="leave out the ninth run (the full network without Norm)")
    p.set_defaults(func=_run_ablation)


def _run_ablation(args) -> int:
    from .ablation import markdown, run_ablation
    rep = run_ablation(args.data, args.output, steps=args.steps, width=args.width,
                       encoder=args.encoder, pairs=_pairs(args), seed=args.seed,
                       no_norm=not args.skip_no_norm)
    print(markdown(rep))
    return 0


def register_compare(sub) -> None:
    import argparse

    p = sub.add_parser("compare", help="every method side by side: budget, memory, speed, "
                                       "MMD / JSD per band",
                       description="Scores each model on the same held-out pairs (the one "
                                   "evaluation protocol) beside its untrained network, "
                                   "measures its training memory in a fresh process and its "
                                   "generation time; writes compare.json, compare.md and "
                                   "compare.png.")
    p.add_argument("--data", required=True, help="dataset directory (its test split is used)")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, help="report directory",
               files=("compare.json", "compare.md", "compare.png"))
    add_model_argument(p, many=True)
    add_protocol_arguments(p)
    add_runtime_argument(p)
    add_lidar_argument(p, default_help="each model's own; give the dataset's lidar to score "
                                       "the models at another lidar")
    p.add_argument("--memory-steps", type=int, default=5,
                   help="training steps timed for the memory peak (0: skip)")
    p.add_argument("--no-untrained", action="store_true",
                   help="skip the untrained networks")
    p.add_argument("--faithfulness", action=argparse.BooleanOptionalAction, default=True,
                   help="each method's faithfulness per band, beside the point z-buffer and "
                        "embree 2x2 (decoys and references made once; default: on)")
    p.set_defaults(func=_run_compare)


def _run_compare(args) -> int:
    from apcg_core.families import load_model

    from .compare import compare, markdown, method_names, write
    models = [(name, model_at_lidar(load_model(path, runtime=args.runtime), args, "compare"))
              for name, path in method_names(args.model)]
    for _, model in models:
        warn_other_data("compare", args.data, model)
    report = compare(models, args.data, n_pairs=_pairs(args), seed=args.seed,
                     memory_steps=args.memory_steps, with_untrained=not args.no_untrained,
                     progress=True, faithfulness=args.faithfulness)
    report["command"] = args.command_line
    out = write(report, args.output)
    print(markdown(report))
    print(f"wrote {out}/compare.json, compare.md, compare.png")
    return 0
