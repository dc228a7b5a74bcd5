"""Table 3, the ablation: the 8 combinations of {transposed convolutions or fully connected,
self-attention on or off, Wasserstein-GP or BCE loss}, trained under one equal budget (the same
steps, batch, critic steps, width and data), scored by FD-depth (our encoder, not FID) and by
MMD / JSD on held-out conditions.

    apcg ablation --data DIR -o RUNS [--steps 500] [--width 0.25] [--encoder DIR]

A ninth run, the full network without Norm (the paper's "APCG w/o Norm."), shares the budget.
Each run resumes where it stopped; finished runs are scored, not retrained.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from apcg_core.errors import InputError
from apcg_core.io.dataset import write_atomic

from .trainer import Trainer, config_from

VARIANTS = [dict(conv=c, attention=a, loss=loss) for c, a, loss in
            itertools.product((True, False), (True, False), ("wgan-gp", "bce"))]
# The paper's "APCG w/o Norm.": the full network trained on depth images without Eq. (2),
# under the same budget, so w/ and w/o Norm compare like for like.
NO_NORM = dict(conv=True, attention=True, loss="wgan-gp", norm=False)


def variant_name(v: dict) -> str:
    return (f"{'tconv' if v['conv'] else 'fc'}-{'attn' if v['attention'] else 'noattn'}-"
            f"{'wgan' if v['loss'] == 'wgan-gp' else 'bce'}"
            f"{'' if v.get('norm', True) else '-nonorm'}")


def run_ablation(data_dir, out_dir, steps: int = 500, width: float = 0.25, encoder=None,
                 pairs: int = 400, seed: int = 0, progress: bool = True,
                 variants=VARIANTS, encoder_epochs: float = 4.0, no_norm: bool = True) -> dict:
    from apcg_core.families import load_model

    from . import protocol
    from .export import export_model
    from .fd_depth import encoder_meta, fd_depth, load_encoder, train_encoder
    out = Path(out_dir)
    plan = [(v, out / variant_name(v),
             config_from("cpu", width=width, steps=steps, seed=seed, keep_every=0, **v))
            for v in list(variants) + ([NO_NORM] if no_norm else [])]
    # before any work: the runs already there are this ablation's (the same data, seed and
    # network), and a given encoder can be read
    check_resume(data_dir, plan, None if encoder is not None else out / "encoder", seed)
    if encoder is not None:
        encoder_meta(encoder)
        load_encoder(encoder)
    out.mkdir(parents=True, exist_ok=True)
    given_encoder = encoder
    if encoder is None:
        encoder = out / "encoder"
        if not (encoder / "encoder.pt").exists():
            train_encoder(data_dir, encoder, epochs=encoder_epochs, seed=seed,
                          progress=progress)
    enc_meta = encoder_meta(encoder)
    test_pairs = protocol.draw_pairs(data_dir, pairs, seed, half="test")
    rows = []
    for v, run, cfg in plan:
        name = run.name
        resume = (run / "checkpoint.pt").exists()
        if not resume and (run / "train_config.json").exists():
            (run / "train_config.json").unlink()  # a start that never checkpointed: redo it
        t0 = time.perf_counter()
        tr = Trainer(data_dir, run, cfg, resume=resume, progress=progress)
        if tr.step < tr.total_steps:
            tr.fit()
        wall = time.perf_counter() - t0
        # Each variant gets its own Im2PC threshold, chosen on the validation half (a young
        # generator's speckle makes a fixed tau favour some variants; the pairs that score it
        # must not choose it).
        first = export_model(run, run / "model", force=True)
        sweep = protocol.choose_tau(load_model(first), data_dir, n_pairs=pairs, seed=seed)
        model = load_model(export_model(run, run / "model", tau=sweep["best"], force=True))
        write_atomic(run / "model" / "tau_sweep.json",
                     (json.dumps(sweep, indent=1) + "\n").encode())
        bands = protocol.score(model, test_pairs, floor=False, pointflow=False)["mean"]
        fresh = protocol.score(protocol.untrained(model, run / "untrained", seed=seed),
                               test_pairs, floor=False, pointflow=False)["mean"]
        fd_pairs = None if pairs is None else max(pairs, 400)  # None: every held-out pair
        fd = fd_depth(encoder, model, data_dir, n_pairs=fd_pairs, seed=seed)
        from apcg_core.io.csv_table import read_csv
        log = read_csv(run / "log.csv", required=("seconds",), what="training log").rows
        rows.append({"variant": name, "norm": True, **v, "steps": tr.step,
                     "train_seconds": log[-1].float("seconds") if log else wall,
                     "fd_depth": fd["fd_depth"], "fd_depth_real_halves":
                     fd["fd_depth_real_halves"], "tau": sweep["best"],
                     "mmd": bands["mmd"], "jsd": bands["jsd"],
                     "mmd_untrained": fresh["mmd"], "jsd_untrained": fresh["jsd"]})
        if progress:
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    report = {"budget": {"steps": steps, "width": width, "batch": 32, "n_critic": 5,
                         "data": str(data_dir), "seed": seed},
              "encoder": {"path": str(encoder),
                          "test_accuracy_type": enc_meta["test_accuracy_type"],
                          "chance": enc_meta["chance"]},
              **test_pairs.record(), "protocol": protocol.constants(),
              "jsd_bins": protocol.JSD_BINS, "rows": rows,
              "command": (f"apcg ablation --data {data_dir} -o {out_dir} --steps {steps} "
                          f"--width {width:g} --pairs {pairs} --seed {seed}"
                          + (f" --encoder {given_encoder}" if given_encoder else "")
                          + ("" if no_norm else " --skip-no-norm"))}
    write_atomic(out / "table3.json", (json.dumps(report, indent=1) + "\n").encode())
    write_atomic(out / "table3.md", markdown(report).encode())
    return report


def check_resume(data_dir, plan, own_encoder, seed: int) -> None:
    """Refuse to resume an ablation with other settings than its runs were started with:
    each variant's run that has a checkpoint must have the variant's training settings (all
    but those a resume may change, ``trainer.RESUMABLE``: steps and the like) and the same
    dataset, and the ablation's own encoder (``own_encoder``, None when one is given) the
    same dataset and seed. Names every setting that differs, with the runs' value."""
    from .trainer import RESUMABLE, TrainConfig, read_checkpoint, read_run_record
    flags = {"seed": "--seed", "width": "--width"}
    differ: dict[str, str] = {}

    def note(key: str, given, theirs, where: Path) -> None:
        flag = flags.get(key, key)
        differ.setdefault(key, f"{flag} {given} (the run's in {where}: {theirs})")

    for _, run, cfg in plan:
        ck = run / "checkpoint.pt"
        if not ck.exists():
            continue
        ran = TrainConfig.from_dict(read_checkpoint(ck)["train"])
        for k, v in asdict(cfg).items():
            if k not in RESUMABLE and getattr(ran, k) != v:
                note(k, v, getattr(ran, k), run)
        rec = read_run_record(run)
        if rec is not None and Path(rec["data"]).resolve() != Path(data_dir).resolve():
            note("--data", data_dir, rec["data"], run)
    if own_encoder is not None and (Path(own_encoder) / "encoder.pt").exists():
        from .fd_depth import encoder_meta
        meta = encoder_meta(own_encoder)
        if "seed" in meta and meta["seed"] != seed:
            note("seed", seed, meta["seed"], Path(own_encoder))
        if "data" in meta and Path(meta["data"]).resolve() != Path(data_dir).resolve():
            note("--data", data_dir, meta["data"], Path(own_encoder))
    if differ:
        raise InputError("this ablation's runs were started with other settings: "
                         + "; ".join(differ.values()) + ". Resume them with the runs' "
                         "settings (only --steps, --pairs and --encoder may change), or "
                         "give another -o")


def _f(v, d=3) -> str:
    return "-" if v is None else f"{v:.{d}f}"


def markdown(report: dict) -> str:
    b, e = report["budget"], report["encoder"]
    floor = report["rows"][0]["fd_depth_real_halves"] if report["rows"] else None
    lines = ["# Table 3: ablation under one budget", "",
             f"Reproduce: `{report['command']}`", "",
             f"Budget per variant: {b['steps']} generator steps, width {b['width']}, batch "
             f"{b['batch']}, {b['n_critic']} critic steps, seed {b['seed']}, data {b['data']}. "
             f"FD-depth: Fréchet distance over our depth encoder's features (type accuracy "
             f"{e['test_accuracy_type']:.3f} held out, chance {e['chance']:.3f}); not FID. "
             f"MMD / JSD ({report['jsd_bins']}^3 bins): means over slant-range bands, "
             f"{report['pairs']} held-out pairs.", "",
             f"FD-depth floor (two halves of the real test images against each other): "
             f"{_f(floor, 1)}. Train s: logged training time on this machine (the budget is "
             f"the steps; the seconds show what each variant costs).", "",
             "tau: the Im2PC threshold, chosen per variant on the validation half (lowest "
             "MMD; `apcg choose-tau`). In brackets: the same network untrained, at the same "
             "tau.", "",
             "| TConv | self-attention | Wasserstein | Norm | FD-depth | tau | MMD | JSD | "
             "train s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {'yes' if r['conv'] else 'no (FC)'} | "
                     f"{'yes' if r['attention'] else 'no'} | "
                     f"{'yes' if r['loss'] == 'wgan-gp' else 'no (BCE)'} | "
                     f"{'yes' if r.get('norm', True) else 'no'} | "
                     f"{_f(r['fd_depth'], 0)} | {r.get('tau', '-')} | "
                     f"{_f(r['mmd'])} ({_f(r.get('mmd_untrained'))}) | "
                     f"{_f(r['jsd'], 2)} ({_f(r.get('jsd_untrained'), 2)}) | "
                     f"{r['train_seconds']:.0f} |")
    return "\n".join(lines) + "\n"
