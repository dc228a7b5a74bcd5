"""A model (the shipped default unless ``--model``) on held-out lidars (issue 33), with no
retraining: for each lidar preset, a small dataset of every built-in type at Table 1 conditions
built at that lidar, and the one evaluation protocol (`apcg evaluate`: MMD, JSD, faithfulness
per band, beside the point z-buffer and embree 2x2 at that lidar) with the model generating at
the lidar's cells.

    .venv/bin/python bench/lidar_heldout.py -o docs/evaluation/lidars [--samples-per-type 8]
        [--lidars paper,half-cells,...] [--pairs 0] [--work /tmp/lidar_heldout]
        [--types all|drones|aircraft|NAME,NAME] [--name heldout] [--model DIR] [--force]

Each lidar is the same as these commands (CFG: the config below, written to WORK/cfg.toml):

    apcg dataset build --config CFG --lidar LIDAR -o WORK/LIDAR
    apcg evaluate --data WORK/LIDAR --lidar LIDAR --pairs 0 -o WORK/LIDAR-report [--model DIR]

Writes OUT/NAME.json (every band's numbers) and OUT/NAME.md (the table), kept when they exist
unless ``--force`` (``bench_output.refuse``, checked before any work); ``--types drones``
(or ``aircraft``) measures one kind alone with more conditions a band for the same time.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.cli import main as apcg  # noqa: E402

LIDARS = ("paper", "half-cells", "double-cells", "bin-0.05m", "bin-0.6m", "anisotropic")
CONFIG = """description = "issue 33: built-in types at random Table 1 conditions"
seed = 33
backend = "embree"
shard_size = 500
test_fraction = 0.5
quantize = true
supersample = 1
sampling = "random"
samples_per_type = {n}
types = {types}
"""


def types_value(spec: str) -> str:
    """The config's ``types``: "all", every drone or every aircraft of the built-in catalog, or
    the names given."""
    if spec == "all":
        return '"all"'
    from apcg_core.catalog.catalog import Catalog
    catalog = Catalog(include_user=False)
    if spec in ("drones", "aircraft"):
        names = [t.name for t in catalog.types
                 if (t.range_band == "near") == (spec == "drones")]
    else:
        names = [n.strip() for n in spec.split(",") if n.strip()]
    return json.dumps(names)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--work", default="/tmp/lidar_heldout")
    ap.add_argument("--samples-per-type", type=int, default=8)
    ap.add_argument("--pairs", type=int, default=0, help="0: the whole test half")
    ap.add_argument("--lidars", default=",".join(LIDARS))
    ap.add_argument("--types", default="all",
                    help="all (default), drones, aircraft, or type names separated by commas")
    ap.add_argument("--name", default="heldout", help="the output files' name (NAME.json, .md)")
    ap.add_argument("--model", default=None,
                    help="model directory (default: the shipped default model)")
    ap.add_argument("--render", action="store_true",
                    help="only write OUT/NAME.md again from OUT/NAME.json")
    ap.add_argument("--force", action="store_true",
                    help="replace OUT/NAME.json and OUT/NAME.md when they exist")
    args = ap.parse_args()
    from bench_output import refuse, write_text
    work, out = Path(args.work), Path(args.output)
    if args.render:
        refuse([out / f"{args.name}.md"], args.force, [out / f"{args.name}.json"])
        record = json.loads((out / f"{args.name}.json").read_text())
        write_text(out / f"{args.name}.md", markdown(record))
        print(markdown(record))
        return 0
    refuse([out / f"{args.name}.json", out / f"{args.name}.md"], args.force)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    cfg = work / "cfg.toml"
    config = CONFIG.format(n=args.samples_per_type, types=types_value(args.types))
    write_text(cfg, config)  # the bench's own work directory: its config of this run
    rows = {}
    for lidar in args.lidars.split(","):
        t0 = time.perf_counter()
        data, rep = work / lidar, work / f"{lidar}-report"
        rc = apcg(["dataset", "build", "--config", str(cfg), "--lidar", lidar, "-o", str(data),
                   "--no-progress"])
        assert rc == 0, f"build at {lidar}: {rc}"
        t1 = time.perf_counter()
        rc = apcg(["evaluate", "--data", str(data), "--lidar", lidar, "--pairs",
                   str(args.pairs), "-o", str(rep), "--force"]
                  + (["--model", args.model] if args.model else []))
        assert rc == 0, f"evaluate at {lidar}: {rc}"
        m = json.loads((rep / "metrics.json").read_text())
        m.pop("per_pair", None)
        m["seconds_build"] = round(t1 - t0, 1)
        m["seconds_evaluate"] = round(time.perf_counter() - t1, 1)
        rows[lidar] = m
    record = {"command": "python bench/lidar_heldout.py " + shlex.join(sys.argv[1:]),
              "config": config, "lidars": rows}
    write_text(out / f"{args.name}.json", json.dumps(record, indent=1) + "\n")
    write_text(out / f"{args.name}.md", markdown(record))
    print(markdown(record))
    return 0


def _f(v, fmt="{:.4f}"):
    return "-" if v is None else fmt.format(v)


def markdown(record: dict) -> str:
    lines = ["| lidar | band | pairs | APCG+ MMD | z-buffer MMD | embree 2x2 MMD | APCG+ faithful "
             "| z-buffer faithful | APCG+ median point ratio |",
             "|---|---|---|---|---|---|---|---|---|"]
    for lidar, m in record["lidars"].items():
        refs = m.get("references", {})
        for band, b in m["bands"].items():
            zb = refs.get("points", {}).get("bands", {}).get(band, {})
            e2 = refs.get("embree 2x2", {}).get("bands", {}).get(band, {})
            fa = (b.get("faithfulness") or {}).get("share")
            fz = (zb.get("faithfulness") or {}).get("share")
            ratio = (b.get("points_ratio_p10_p50_p90") or [None, None, None])[1]
            lines.append(f"| {lidar} | {band} | {b.get('scored')} | {_f(b.get('mmd'))} | "
                         f"{_f(zb.get('mmd'))} | {_f(e2.get('mmd'))} | "
                         f"{_f(fa, '{:.0%}')} | {_f(fz, '{:.0%}')} | {_f(ratio, '{:.2f}')} |")
        mean = m.get("mean", {})
        fa = mean.get("faithfulness") or {}
        zb = refs.get("points", {}).get("bands", {})
        e2 = refs.get("embree 2x2", {}).get("bands", {})

        def band_mean(bands, key, kind=None):  # every band alike, as the protocol's means
            vals = [(b.get("faithfulness") or {}).get("share") if key == "faithful"
                    else b.get(key) for name, b in bands.items()
                    if kind is None or name.startswith(kind)]
            vals = [v for v in vals if v is not None]
            return sum(vals) / len(vals) if vals else None
        lines.append(f"| {lidar} | **mean** | {m.get('pairs')} | {_f(mean.get('mmd'))} | "
                     f"{_f(band_mean(zb, 'mmd'))} | {_f(band_mean(e2, 'mmd'))} | "
                     f"aircraft {_f(fa.get('aircraft'), '{:.0%}')}, drones "
                     f"{_f(fa.get('drone'), '{:.0%}')} | aircraft "
                     f"{_f(band_mean(zb, 'faithful', 'aircraft'), '{:.0%}')}, drones "
                     f"{_f(band_mean(zb, 'faithful', 'drone'), '{:.0%}')} | |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
