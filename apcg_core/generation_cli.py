"""``apcg generate``: APCG point clouds for one condition or a CSV of conditions."""

from __future__ import annotations

import json

from .cli import add_pose_arguments
from .io.clouds import FORMATS as CLOUD_FORMATS
from .lidar_options import add_lidar_argument, model_at_lidar
from .outputs import FILE, add_output
from .sensor.options import add_sensor_arguments, sensor_of


def register_generate(sub) -> None:
    p = sub.add_parser("generate", help="generate point clouds with a trained APCG model",
                       description="nu + noise -> generator -> DeNorm -> Im2PC. Without --model "
                                   "the default model shipped with the package is used.")
    p.add_argument("--model", metavar="DIR",
                   help="model directory, any family (default: the shipped default model); "
                        "families other than the cGAN need the training extra")
    p.add_argument("--type", help="catalog type name or index (with the pose options)")
    p.add_argument("--conditions", help="CSV with type,range_m,elevation_deg,pitch_deg,"
                                        "yaw_deg,roll_deg (instead of --type and the pose)")
    add_pose_arguments(p, required=False)  # not needed with --conditions
    # None: not given (0 with --type, refused with --conditions, whose rows hold the pose)
    p.set_defaults(pitch_deg=None, yaw_deg=None, roll_deg=None)
    p.add_argument("--count", type=int, default=1,
                   help="clouds per condition (default 1); a model without noise (APCG+) "
                        "draws the same cloud each time, unless --sensor adds photons")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the model's noise and of --sensor's photons (default 0); "
                        "a model without noise (APCG+) and no --sensor: no effect")
    p.add_argument("--runtime", choices=["auto", "onnx", "torch"], default="auto",
                   help="cGAN inference: auto (torch when installed, else onnxruntime), onnx, "
                        "torch; the same points either way, ranges equal to float32 rounding "
                        "(within about 1e-4 m)")
    p.add_argument("--tau", type=float, help="output threshold (default: the model's): the "
                                             "cGAN's Im2PC tau, APCG+'s hit logit")
    add_lidar_argument(p, default_help="the model's own (its model.json lidar); another is "
                                       "read at its cells where the family can (apcg-plus)")
    p.add_argument("--resumable", action="store_true",
                   help="keep finished blocks in OUT.parts/ so that a Ctrl-C'd run continues "
                        "where it stopped (automatic from 131,072 clouds: docs/SCALE.md)")
    p.add_argument("--engine", metavar="NAME",
                   help="compute the blocks on the dataset builder's engine NAME (dask: a "
                        "local Dask cluster of --workers processes, or the one at --address; "
                        "local: a pool of --workers processes); a resumable job, the same "
                        "bytes as one process. Default: this process, all cores")
    p.add_argument("--workers", type=int,
                   help=f"with --engine and no --address: worker processes (default "
                        f"{DEFAULT_WORKERS}: this machine's cores); with --address the "
                        "cluster's own workers run the parts")
    p.add_argument("--address", metavar="ADDR",
                   help="with --engine dask: a running cluster's scheduler; OUT must be on "
                        "storage every worker mounts at the same path")
    add_sensor_arguments(p, seed=False)  # --seed seeds the photons too
    add_output(p, "-o", "--output", kind=FILE, suffixes=CLOUD_FORMATS, required=True,
                   help=".ply / .npz / .las / .laz; several clouds go in one file, told apart by "
                        "their `sample` attribute")
    p.set_defaults(func=_run_generate, resume_hint="Run the same command again: a resumable "
                   "generation (--resumable, --engine, or 131,072 clouds or more) continues "
                   "where it stopped; any other starts again.")


POSE_OPTIONS = ("range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg")
DEFAULT_WORKERS = 2  # --engine's local processes when --workers is not given


def check_request(args) -> None:
    """Refuse a request whose options do not go together, before anything is read or made
    (a refused request leaves no file and no parts directory behind)."""
    from .errors import InputError
    from .generation_job import MAX_CLOUDS
    from .options import option_name
    if args.count > MAX_CLOUDS:
        raise InputError(f"--count {args.count} not accepted: at most {MAX_CLOUDS:,} clouds "
                         "in one request; split it into several")
    if args.conditions is not None and not args.conditions.strip():
        raise InputError(f"--conditions {args.conditions!r}: an empty name; give a CSV file")
    if args.conditions:
        if args.type:
            raise InputError("give either --conditions or --type with a pose, not both")
        given = [option_name(k) for k in POSE_OPTIONS if getattr(args, k) is not None]
        if given:
            raise InputError(f"{', '.join(given)} not accepted with --conditions: each row of "
                             f"{args.conditions} gives its own pose; leave "
                             f"{'it' if len(given) == 1 else 'them'} out, or give --type "
                             "with a pose instead of --conditions")
    elif args.type is None or args.range_m is None or args.elevation_deg is None:
        raise InputError("give --type, --range-m and --elevation-deg (or --conditions)")
    if args.engine is None:
        if args.address:
            raise InputError("--address needs --engine dask")
        if args.workers is not None:
            raise InputError(f"--workers {args.workers} needs --engine (dask or local): "
                             "without it this process generates, on all cores")


def engine_workers(args) -> int:
    """--workers as given; else 1 with --address (the cluster's own workers run the parts:
    the engine refuses a size given with it, as for `apcg dataset build`), else
    DEFAULT_WORKERS."""
    if args.workers is not None:
        return args.workers
    return 1 if args.address else DEFAULT_WORKERS


def _run_generate(args) -> int:
    from . import generation_job as job
    from .errors import InputError
    from .families import conditions_from_csv, load_model
    from .options import model_condition

    check_request(args)
    sensor = sensor_of(args)
    model = model_at_lidar(load_model(args.model, runtime=args.runtime), args, "generate")
    # a model of a sensor's photon clouds draws them already: no second photon stage on top
    model.refuse_sensor(sensor, "--sensor" if args.sensor is not None
                        else f"the [sensor] table of --lidar {args.lidar}")
    if args.tau is not None:
        if getattr(model, "tau", None) is None:
            raise InputError(f"--tau is an output threshold; {model.directory} is a "
                             f"{model.family} model, which has none")
        model.tau = model.check_tau(args.tau)
    if args.conditions:
        table = conditions_from_csv(args.conditions, model)
    else:
        table = model_condition(model, args)
    total = len(table) * args.count
    if total > job.MAX_CLOUDS:
        raise InputError(f"{len(table):,} conditions x --count {args.count} = {total:,} "
                         f"clouds: at most {job.MAX_CLOUDS:,} in one request; split it into "
                         "several (other rows, other seeds)")
    model.expect_clouds(total)
    import numpy as np

    from .progress import say
    for line in model.stale_meshes(table.types.names[c] for c in np.unique(table.codes)):
        say(f"apcg generate: warning: {line}")
    window = _warn_window(model, table)
    meta = {"model": str(model.directory), "family": model.family,
            "runtime": getattr(model, "runtime", None), "seed": args.seed,
            "count": args.count, "tau": getattr(model, "tau", None),
            "lidar": model.lidar.to_dict()}
    if sensor is not None:  # SPEC section 8: the photon stage on the generated clouds
        meta["sensor"] = sensor.to_dict()
    if len(table) <= MAX_LISTED_CONDITIONS:
        meta["conditions"] = [{"type": name, "range_m": float(r[1]),
                               "elevation_rad": float(r[2]), "pitch_rad": float(r[3]),
                               "yaw_rad": float(r[4]), "roll_rad": float(r[5])}
                              for name, r in zip(table.names, table.table, strict=True)]
    else:  # the file names them instead of repeating a long list in every header
        meta["conditions_csv"], meta["n_conditions"] = str(args.conditions), len(table)
    from .io.clouds import CloudWriter
    from .progress import Progress
    from .testpoints import wait_point

    def progress_from(done: int = 0) -> Progress:
        return Progress(total, "cloud", enabled=total > BLOCK_CLOUDS, done=done)
    points = empty = 0
    fields = () if sensor is None else ("label", "count") + (
        ("pulse",) if sensor.output == "events" else ())

    def block_clouds(item):
        block, (part, count, offset) = item
        return job.generate_block(model, sensor, args.seed, block, part, count, offset)

    size = min(BLOCK_CLOUDS, getattr(model, "block_clouds", BLOCK_CLOUDS))
    work = enumerate(blocks(table, args.count, size))
    lanes = getattr(model, "lanes", 1)
    engine = task_of = None
    if args.engine is not None:
        engine = job.engine(args.engine, engine_workers(args), args.address,
                            job.parts_dir(args.output))
        lidar = model.lidar if getattr(args, "lidar", None) is not None else None

        def task_of(i, part_blocks, path):
            return job.PartTask(i, path, [(b, part, count, offset)
                                          for b, (part, count, offset) in part_blocks],
                                str(model.directory), args.runtime,
                                getattr(model, "tau", None) if args.tau is not None else None,
                                lidar, args.seed, sensor, fields)
    if args.resumable or args.engine is not None or total >= job.RESUMABLE_CLOUDS:
        record = job.job_record(meta, model.directory, args.conditions)
        per_part = max(1, min(BLOCK_CLOUDS, job.PART_CLOUDS) // size)
        try:
            points, empty = job.run_job(args.output, meta, record, fields, work, per_part,
                                        block_clouds, lanes, progress_from, engine, task_of)
        except job.GenerateInterrupted as stop:  # Ctrl-C: say how far it got
            import sys
            print(f"apcg generate: {stop}", file=sys.stderr)
            return 130
    else:
        progress = progress_from()
        with CloudWriter(args.output, meta, photon_fields=fields) as out:
            for cloud, n in job.in_order(block_clouds, work, lanes):
                out.write(cloud)
                wait_point("generate.block-written")
                points += len(cloud)
                empty += n - job.clouds_with_points(cloud.sample)
                progress.update(n)
        progress.close()
    window.result()  # its line printed (above the bar) before the command's last ones
    _warn_unseeded(model, sensor, args)
    from .plausibility import empty_clouds_warning
    if (warning := empty_clouds_warning(empty, total, sensor is not None)) is not None:
        import sys
        print(f"apcg generate: warning: {warning}", file=sys.stderr)
    print(json.dumps({"output": args.output, "clouds": total, "points": points,
                      "empty_clouds": empty,
                      "family": model.family, "runtime": getattr(model, "runtime", None)}))
    return 0


def _warn_unseeded(model, sensor, args) -> None:
    """A model whose clouds are a function of the condition (``SEEDED`` False), without a
    sensor's photons: --count writes identical copies and --seed changes nothing; say so
    rather than let a user take copies for variations."""
    if getattr(model, "SEEDED", True) or sensor is not None:
        return
    from .progress import say
    what = f"the model ({model.family})"
    if args.count > 1:
        say(f"apcg generate: warning: {what} draws one cloud per condition: --count "
            f"{args.count} writes {args.count} identical copies of each (with --sensor, each "
            "copy gets photons of its own)")
    if args.seed != 0:
        say(f"apcg generate: warning: {what} has no noise: --seed {args.seed} changes "
            "nothing without --sensor")


def _warn_window(model, table):
    """One "window too small" line when the lidar's window cuts a requested target, found on
    a thread of its own beside the first blocks (the meshes' loading and the check are 0.1-0.2
    s that the start would otherwise spend on one core) and printed above the progress bar
    when found; returns its future (``result()`` waits for it, and raises what it raised)."""
    def check() -> None:
        from .catalog.catalog import default_catalog
        from .errors import InputError
        from .plausibility import WINDOW_CHECK_ROWS, window_fit, window_warning
        from .progress import say
        cat, part = default_catalog(), table[:WINDOW_CHECK_ROWS]
        try:
            fit = window_fit(model.lidar, lambda n: cat.mesh(n).vertices, part.names,
                             part.table)
        except InputError:  # a type of the model that this catalog no longer holds: no mesh
            return
        warning = window_warning(model.lidar, *fit, "the requested targets")
        if warning:
            say(f"apcg generate: warning: {warning}")

    from concurrent.futures import ThreadPoolExecutor
    pool = ThreadPoolExecutor(1, thread_name_prefix="apcg-window-check")
    done = pool.submit(check)
    pool.shutdown(wait=False)  # the thread ends with the check
    return done


# Clouds generated per block: large requests are made and written block by block, so memory
# stays bounded whatever --count is. A request of one block is generated exactly as before.
# (A model whose clouds depend on neither the seed nor the blocks may ask for smaller ones:
# its ``block_clouds``.)
BLOCK_CLOUDS = 8192
MAX_LISTED_CONDITIONS = 10000


def blocks(table, count: int, size: int):
    """(conditions, count, first sample index) blocks of at most ``size`` clouds covering
    every row of ``table`` ``count`` times, rows in order (a row's repeats stay together)."""
    rows_per_block = max(1, size // count)
    offset = 0
    for start in range(0, len(table), rows_per_block):
        part = table[start:start + rows_per_block]
        if count <= size:
            yield part, count, offset
            offset += len(part) * count
            continue
        for done in range(0, count, size):  # one row, its repeats in several blocks
            k = min(size, count - done)
            yield part, k, offset
            offset += k
