"""What each idea of APCG+ buys: short runs of design variants, the same number of steps each
(a shared machine makes equal wall time unfair), scored by the evaluation protocol on the
**validation** half (design choices are made there, never on test).

    .venv/bin/python bench/plus_ablation.py --data data/cpu --steps 3000 --pairs 400 \
        [--variants base,no-film,sheet32,sheet128,narrow] [-o bench/results/plus_ablation]
        [--force]

Each variant trains from scratch (one process, all threads), is exported, and is scored: mean
MMD / JSD over bands, the median generated / standard point ratio, seconds per training step
and milliseconds per cloud (generation alone, batched). Runs and models stay in ``-o``; a
variant whose run exists is resumed to its step count rather than redone. The table,
``-o``/ablation.json (rewritten after each variant, with this run's variants), is kept when it
exists: the run stops before any work unless ``--force`` (``bench_output.refuse``), which a
resumed run into the same ``-o`` therefore needs.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.families import register  # noqa: E402
from training import protocol  # noqa: E402
from training.families.apcg_plus import PlusFamily  # noqa: E402


class _NoFilm(PlusFamily):
    """The condition enters at the first layer only (no modulation per block)."""

    name = "apcg-plus-no-film"

    def net_config(self, cfg, dataset):
        return replace(super().net_config(cfg, dataset), film=False)


register(_NoFilm())

VARIANTS = {
    "base": {},
    "no-film": {"family": "apcg-plus-no-film"},
    "sheet32": {"sheet": 32},
    "sheet128": {"sheet": 128, "width": 0.5},
    "narrow": {"width": 0.5},
}


def run_variant(name: str, data: str, out: Path, steps: int, pairs) -> dict:
    from apcg_core.families import load_model
    from training.export import export_model
    from training.trainer import Trainer, config_from
    over = {"family": "apcg-plus", **VARIANTS[name]}
    run = out / "runs" / name
    cfg = config_from("cpu", steps=steps, checkpoint_every=500, keep_every=0, **over)
    tr = Trainer(data, run, cfg, resume=(run / "checkpoint.pt").exists(), progress=False)
    fit = tr.fit()
    model = load_model(export_model(run, out / "models" / name, force=True))
    model.sheets(model.repeated_conditions(pairs.ds.condition_rows(pairs.idx[:8]), 1))  # warm
    rep = protocol.score(model, pairs, floor=False, pointflow=False)
    ratios = [b["points_ratio_p10_p50_p90"][1] for b in rep["bands"].values()]
    return {"variant": name, "settings": over, "steps": fit["step"],
            "train_seconds": tr.seconds_before + fit["seconds"],
            "seconds_per_step": round((tr.seconds_before + fit["seconds"]) / max(fit["step"], 1),
                                      4),
            "mmd": rep["mean"]["mmd"], "jsd": rep["mean"]["jsd"],
            "points_ratio_median_per_band": ratios,
            "ms_per_cloud": round(1e3 * rep["seconds"]["generate"] / len(pairs), 4),
            "bands": {k: {m: v[m] for m in ("mmd", "jsd", "points_ratio_p10_p50_p90")}
                      for k, v in rep["bands"].items()}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--pairs", type=int, default=400)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("-o", "--output", default="bench/results/plus_ablation")
    ap.add_argument("--force", action="store_true",
                    help="replace OUT/ablation.json when it exists (a resumed run)")
    args = ap.parse_args()
    from bench_output import refuse, write_text
    out = Path(args.output)
    refuse([out / "ablation.json"], args.force, [args.data])
    out.mkdir(parents=True, exist_ok=True)
    pairs = protocol.draw_pairs(args.data, args.pairs, 0, half="validation")
    results = []
    for name in args.variants.split(","):
        if name not in VARIANTS:
            ap.error(f"unknown variant {name!r}; accepted: {', '.join(VARIANTS)}")
        t0 = time.perf_counter()
        results.append(run_variant(name, args.data, out, args.steps, pairs))
        r = results[-1]
        print(f"{name}: {r['steps']} steps, MMD {r['mmd']:.4f}, JSD {r['jsd']:.3f}, "
              f"{r['ms_per_cloud']:.3f} ms/cloud ({time.perf_counter() - t0:.0f} s)",
              flush=True)
        write_text(out / "ablation.json", json.dumps(
            {"command": "python bench/plus_ablation.py " + shlex.join(sys.argv[1:]),
             **pairs.record(), "steps_each": args.steps, "results": results}, indent=1))
    print(markdown(results))
    return 0


def markdown(results: list[dict]) -> str:
    lines = ["| variant | steps | s/step | MMD | JSD | median point ratio (min-max over bands) "
             "| ms/cloud |", "|---|---|---|---|---|---|---|"]
    for r in results:
        rat = [x for x in r["points_ratio_median_per_band"] if x is not None]
        lines.append(f"| {r['variant']} | {r['steps']} | {r['seconds_per_step']:.3f} | "
                     f"{r['mmd']:.4f} | {r['jsd']:.3f} | "
                     f"{min(rat):.2f}-{max(rat):.2f} | {r['ms_per_cloud']:.3f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
