"""Teach a trained model a type it does not know (a catalog type, e.g. one added with
``apcg catalog add``), without retraining it: ``apcg teach``.

The command builds a small dataset of that type alone (embree, random conditions in the model's
condition space, the model's lidar), then asks the model's family to fit the new type on it
(APCG+: one new row of the type embedding, every other weight frozen, so the types the model
knew generate exactly as before), and writes a new model directory with the type added. The
report beside it scores the new type on the held-out half of that dataset with the evaluation
protocol (MMD, point counts, faithfulness).

The type is named as the catalog names it (a bare number is refused, not taken for an index).
``--minutes`` bounds building the dataset and fitting (at least :data:`MIN_MINUTES`): it is
checked between fitting steps, the fit runs at least 5 s unless ``--steps`` stops it sooner,
and the scoring after it is not counted; ``teach.json`` records each phase's seconds and
whether the budget was kept.
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
# The least --minutes a teach can keep to: the family's fit runs at least 5 s (one step at
# least), after the type's dataset is built. The budget is checked between fitting steps (the
# fit ends after the step that crosses it); scoring the taught type afterwards is not counted.
MIN_MINUTES = 0.1


def catalog_type(catalog, key):
    """The catalog type named ``key``. A type is taught by its name (the README's, `apcg
    catalog list`'s): a bare number (an int, or a string of digits) is refused, unless some
    type is named so, rather than taken for the type at that index."""
    import re

    from apcg_core.typetable import name_key, normalize_name
    numeric = isinstance(key, int) and not isinstance(key, bool) or (
        isinstance(key, str) and re.fullmatch(r"[+-]?[0-9]+", normalize_name(key)))
    if numeric:
        named = [t for t in catalog.types if name_key(t.name) == name_key(str(key))]
        if named:
            return named[0]
        at = next((t for t in catalog.types if str(t.index) == normalize_name(str(key))),
                  None)
        hint = f" (the type at index {key} is {at.name!r})" if at is not None else ""
        raise InputError(f"--type {str(key)!r} is a number, not a type's name{hint}; teach "
                         "takes a catalog type by name (`apcg catalog list` shows them)")
    if not isinstance(key, str):
        raise InputError(f"--type must be a catalog type's name, got {key!r}")
    return catalog.get(key)  # refuses an unknown name, naming close matches


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
    from apcg_core.errors import check_finite
    if not check_finite("--minutes", minutes) >= MIN_MINUTES:
        raise InputError(f"--minutes {minutes!r} not accepted: at least {MIN_MINUTES:g} "
                         "(the type's dataset is built and then fitted for at least 5 s; give "
                         "--steps to shorten the fit, --samples to shorten the dataset)")
    model = load_model(model_dir)
    if lidar is not None:
        model.use_lidar(lidar)  # refused by a family that draws at its own lidar only
    family = get_family(model.family, need="load")
    if not callable(getattr(family, "teach", None)):
        raise InputError(f"{model.directory} is a {model.family} model, which cannot be taught "
                         "a type (its network takes the type as one scaled number); teach an "
                         "apcg-plus model (the default), or train a new model with the type")
    t = catalog_type(default_catalog(), type_name)  # by name; refuses an unknown one
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
            t_fit = time.perf_counter() - t0 - t_data
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
                      "budget": {"minutes": minutes, "counts": "dataset and fit",
                                 "kept": t_data + t_fit <= 60.0 * minutes},
                      "seconds": {"dataset": round(t_data, 2), "fit": round(t_fit, 2),
                                  "score": round(time.perf_counter() - t0 - t_data - t_fit,
                                                 2),
                                  "total": round(time.perf_counter() - t0, 2)},
                      "score": score}
            write_atomic(stage / "teach.json", (json.dumps(report, indent=1) + "\n").encode())
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    if progress:
        print(f"taught {t.name} in {report['seconds']['total']:.0f} s -> {out}",
              file=sys.stderr)
    if not report["budget"]["kept"]:
        sec = report["seconds"]
        print(f"teach: the dataset ({sec['dataset']:.0f} s) and the fit ({sec['fit']:.0f} s) "
              f"took longer than --minutes {minutes:g}: the budget is checked between "
              "fitting steps, and the fit runs at least 5 s", file=sys.stderr)
    return report


def register_teach(sub) -> None:
    p = sub.add_parser("teach", help="teach a trained model a new type without retraining it",
                       description="Builds a small dataset of one catalog type (e.g. one added "
                                   "with `apcg catalog add`), fits that type into a copy of "
                                   "the model (APCG+: a new type embedding, all else frozen) "
                                   "and scores it on the dataset's held-out conditions.")
    p.add_argument("--model", required=True, metavar="DIR", help="the trained model")
    p.add_argument("--type", required=True,
                   help="catalog name of the type to teach (a name, not an index)")
    add_output(p, "-o", "--output", kind=DIRECTORY, required=True, files=ANY,
               help="the new model directory",
               force_help="write into a -o that holds files (files of the same names are "
                          "replaced, others kept; never the model being taught)")
    p.add_argument("--samples", type=int, default=400,
                   help="conditions of the type to simulate (default 400, a quarter held out)")
    p.add_argument("--minutes", type=float, default=10.0,
                   help=f"time budget of building the type's dataset and fitting it (default "
                        f"10, at least {MIN_MINUTES:g}); checked between fitting steps, the "
                        "fit runs at least 5 s, and scoring the taught type afterwards is "
                        "extra")
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
