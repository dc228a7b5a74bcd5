"""Teach a trained model a type it does not know (a catalog type, e.g. one added with
``apcg catalog add``), without retraining it: ``apcg teach``.

The command builds a small dataset of that type alone (embree, random conditions in the model's
condition space, the model's lidar), then asks the model's family to fit the new type on it
(APCG+: one new row of the type embedding, every other weight frozen, so the types the model
knew generate exactly as before), and writes a new model directory with the type added. The
report beside it scores the new type on the held-out half of that dataset with the evaluation
protocol (MMD, point counts, faithfulness).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from apcg_core.errors import InputError, check_int
from apcg_core.families import get_family
from apcg_core.outputs import ANY, DIRECTORY, add_output

TEST_FRACTION = 0.25


def teach_config(model, type_name: str, samples: int, seed: int) -> dict:
    """The dataset config of the new type: the model's lidar, ranges and quantisation."""
    sp = model.space
    deg = 180.0 / 3.141592653589793
    return {"description": f"teach {type_name}: {samples} random conditions", "seed": seed,
            "backend": "embree", "shard_size": 200, "test_fraction": TEST_FRACTION,
            "quantize": bool(getattr(model, "quantize", True)), "supersample": 1,
            "sampling": "random", "samples_per_type": samples, "types": [type_name],
            "lidar": model.lidar.to_dict(),
            "ranges": {"aircraft_range_m": list(sp.aircraft_range_m),
                       "drone_range_m": list(sp.drone_range_m),
                       **{f"{k}_deg": [v * deg for v in getattr(sp, k)]
                          for k in ("elevation", "pitch", "yaw", "roll")}}}


def teach(model_dir, type_name: str, out_dir, samples: int = 400, minutes: float = 10.0,
          steps: int | None = None, workers: int = 1, seed: int = 0, data_dir=None,
          force: bool = False, progress: bool = True, lidar=None) -> dict:
    """Teach the model in ``model_dir`` the catalog type ``type_name``; the new model goes to
    ``out_dir``. Returns the report (also written as ``out_dir/teach.json``). ``lidar``
    (LidarParams): simulate, fit and score the type at that lidar (default: the model's)."""
    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.families import load_model
    from dataset_builder.build import build_dataset

    from . import protocol
    check_int("samples", samples, 8)
    check_int("workers", workers, 1)
    check_int("seed", seed, 0)
    if steps is not None:
        check_int("steps", steps, 1)
    if not (minutes > 0):
        raise InputError(f"--minutes must be > 0, got {minutes!r}")
    model = load_model(model_dir)
    if lidar is not None:
        model.use_lidar(lidar)  # refused by a family that draws at its own lidar only
    family = get_family(model.family, need="load")
    if not callable(getattr(family, "teach", None)):
        raise InputError(f"{model.directory} is a {model.family} model, which cannot be taught "
                         "a type (its network takes the type as one scaled number); teach an "
                         "apcg-plus model (the default), or train a new model with the type")
    t = default_catalog().get(type_name)  # refuses an unknown type, naming what is accepted
    if t.name in model.types:
        raise InputError(f"{model.directory} already knows {t.name!r}; nothing to teach")
    out = Path(out_dir)
    if out.resolve() == Path(model.directory).resolve():
        raise InputError("-o must be a new directory, not the model being taught")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise InputError(f"{out} exists and is not empty; choose another -o or pass --force "
                         "(files of the same names are replaced, others kept)")
    from apcg_core.io.dataset import write_atomic
    from apcg_core.outputs import staged_directory
    t0 = time.perf_counter()
    tmp = None
    if data_dir is None:
        tmp = tempfile.mkdtemp(prefix="apcg-teach-")
        data_dir = Path(tmp) / "data"
    try:
        # the new model is made in a staging directory and published into -o file by file
        # when whole: an interrupted teach leaves -o as it was; nothing in -o is deleted
        with staged_directory(out) as stage:
            build_dataset(teach_config(model, t.name, samples, seed), data_dir,
                          workers=workers, progress=progress)
            t_data = time.perf_counter() - t0
            fit = family.teach(model, data_dir, stage, minutes=minutes - t_data / 60.0,
                               steps=steps, seed=seed, progress=progress)
            taught = load_model(stage)
            taught.use_lidar(model.lidar)
            # nothing is chosen on this small dataset's validation half: score all it holds out
            pairs = protocol.draw_pairs(data_dir, None, seed, half=protocol.WHOLE)
            score = protocol.score(taught, pairs, floor=False, pointflow=False,
                                   faithfulness=True)
            score.pop("per_pair", None)
            report = {"type": t.name, "model": str(model.directory), "taught_model": str(out),
                      "samples": samples, "seed": seed, "fit": fit,
                      "lidar": model.lidar.to_dict(),
                      "seconds": {"dataset": round(t_data, 2),
                                  "total": round(time.perf_counter() - t0, 2)},
                      "score": score}
            write_atomic(stage / "teach.json", (json.dumps(report, indent=1) + "\n").encode())
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    if progress:
        print(f"taught {t.name} in {report['seconds']['total']:.0f} s -> {out}",
              file=sys.stderr)
    return report


def register_teach(sub) -> None:
    p = sub.add_parser("teach", help="teach a trained model a new type without retraining it",
                       description="Builds a small dataset of one catalog type (e.g. one added "
                                   "with `apcg catalog add`), fits that type into a copy of "
                                   "the model (APCG+: a new type embedding, all else frozen) "
                                   "and scores it on the dataset's held-out conditions.")
    p.add_argument("--model", required=True, metavar="DIR", help="the trained model")
    p.add_argument("--type", required=True, help="catalog name of the type to teach")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, files=ANY,
               help="the new model directory",
               force_help="write into a -o that holds files (files of the same names are "
                          "replaced, others kept; never the model being taught)")
    p.add_argument("--samples", type=int, default=400,
                   help="conditions of the type to simulate (default 400, a quarter held out)")
    p.add_argument("--minutes", type=float, default=10.0,
                   help="time budget, dataset included (default 10)")
    p.add_argument("--steps", type=int, help="stop after this many fitting steps")
    p.add_argument("--workers", type=int, default=1, help="dataset build processes")
    p.add_argument("--seed", type=int, default=0)
    from apcg_core.lidar_options import add_lidar_argument
    add_lidar_argument(p, default_help="the model's own: the type is simulated, fitted and "
                                       "scored at this lidar")
    from dataset_builder.cli import DATASET_FILES, DATASET_RECORD
    add_output(p, "--data", kind=DIRECTORY, files=DATASET_FILES, record=DATASET_RECORD,
               help="keep the type's dataset here (default: a temporary one)")
    p.set_defaults(func=_run_teach)


def _run_teach(args) -> int:
    from apcg_core.lidar_options import lidar_of
    rep = teach(args.model, args.type, args.output, samples=args.samples, minutes=args.minutes,
                steps=args.steps, workers=args.workers, seed=args.seed, data_dir=args.data,
                force=args.force, lidar=lidar_of(args))
    s = rep["score"]
    print(json.dumps({"model": rep["taught_model"], "type": rep["type"],
                      "seconds": rep["seconds"], "mmd": s["mean"]["mmd"],
                      "faithfulness": s["mean"].get("faithfulness"),
                      "fit_steps": rep["fit"]["steps"]}))
    return 0
