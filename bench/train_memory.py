"""Peak memory and time per step of training, per model family (the paper's Fig. 15), each in
its own process so the peaks do not mix.

    .venv/bin/python bench/train_memory.py --data data/cpu [--steps 20]
        [--json bench/results/train_memory.json] [--plot docs/fig15.png] [--force]

Peak memory is the training process's own high-water resident set (VmHWM) on CPU, or torch's
peak allocated device memory on a GPU; both include the dataset held in memory. An existing
--plot file stops the run before any work unless ``--force`` (``bench_output.refuse``); the
--json result is replaced in place, as every bench's is.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from training.compare import training_memory  # noqa: E402
from training.trainer import config_from  # noqa: E402

CONFIGS = {
    "cgan (cpu preset, width 0.25, bf16)": {"preset": "cpu"},
    "cgan (paper, width 1.0)": {"preset": "paper", "bf16": True},
    # the comparison families train with the same cpu preset (bf16) as the cGAN
    "point-gan (cpu preset, bf16)": {"preset": "cpu", "family": "point-gan"},
    "voxel-gan (cpu preset, bf16)": {"preset": "cpu", "family": "voxel-gan"},
    "diffusion (cpu preset, bf16)": {"preset": "cpu", "family": "diffusion"},
}


def main() -> int:
    from bench_output import emit, refuse, save_figure

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--only", action="append",
                    help="run only the configurations whose name contains this (repeatable)")
    ap.add_argument("--json")
    ap.add_argument("--plot")
    ap.add_argument("--force", action="store_true", help="replace the --plot file")
    args = ap.parse_args()
    refuse([args.plot], args.force, [args.data])
    names = [n for n in CONFIGS if not args.only or any(o in n for o in args.only)]
    if not names:
        ap.error(f"--only {args.only} matches none of: {', '.join(CONFIGS)}")
    rows = []
    for name in names:
        spec = dict(CONFIGS[name])
        cfg = asdict(config_from(spec.pop("preset"), **spec))
        row = {"config": name, **training_memory(cfg, args.data, args.steps)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"command": "python bench/train_memory.py " + shlex.join(sys.argv[1:]),
           "steps": args.steps, "rows": rows}
    emit(out, args.json, show=False)
    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
        ax.barh([r["config"] for r in rows], [r["peak_rss_mb"] for r in rows])
        ax.set_xlabel("peak resident memory while training (MB, CPU)")
        ax.set_title("Training memory per model (paper Fig. 15)")
        save_figure(fig, args.plot, dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
