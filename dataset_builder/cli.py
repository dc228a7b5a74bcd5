"""``apcg simulate`` and ``apcg dataset build / info / configs``."""

from __future__ import annotations

import json
import sys

from apcg_core.cli import add_pose_arguments, print_mapping
from apcg_core.io.clouds import FORMATS as CLOUD_FORMATS
from apcg_core.io.images import DEPTH_IMAGE_SUFFIXES
from apcg_core.lidar_options import add_lidar_argument, lidar_of, lidar_or_default
from apcg_core.outputs import DIRECTORY, FILE, add_output
from apcg_core.sensor.options import add_sensor_arguments, sensor_of

from .backends import BACKENDS
from .engine import ENGINES


def register_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate", help="simulate the SPC-Lidar on one catalog type: a standard point cloud",
        description="Place a catalog type at a condition and sample it as the SPC-Lidar would "
                    "(one return per cell, first surface, ranges quantized to the time bin). "
                    "Writes the standard point cloud in the observation frame (metres).")
    p.add_argument("--type", required=True, help="catalog type name or index "
                                                 "(`apcg catalog list`)")
    add_pose_arguments(p)
    p.add_argument("--backend", choices=BACKENDS, default="embree",
                   help="ray casting: embree (default), blender (Geometry Nodes), blender-bvh; "
                        "or points (the paper's z-buffer over a fine point cloud)")
    p.add_argument("--supersample", type=int, default=None, metavar="K",
                   help="K x K rays per cell, nearest hit kept (default 1; 4 with a sensor, "
                        "whose stage takes every sub-ray)")
    p.add_argument("--no-quantize", action="store_true",
                   help="keep exact ranges instead of the time-bin centres")
    add_lidar_argument(p)
    add_sensor_arguments(p)
    add_output(p, "-o", "--output", kind=FILE, suffixes=CLOUD_FORMATS, required=True,
               help="cloud file: .ply, .npz, .las or .laz")
    add_output(p, "--depth-image", kind=FILE, suffixes=DEPTH_IMAGE_SUFFIXES,
               help="also write the depth image (PC2Im): .npy or .png")
    add_output(p, "--normalized-image", kind=FILE, suffixes=DEPTH_IMAGE_SUFFIXES,
               help="also write Norm(depth image): .npy or .png")
    p.set_defaults(func=_run_simulate)


def _run_simulate(args) -> int:
    import numpy as np

    from apcg_core.catalog.catalog import default_catalog
    from apcg_core.condition import Condition
    from apcg_core.depth import norm
    from apcg_core.errors import InputError
    from apcg_core.io import write_cloud, write_depth_image
    from apcg_core.options import pose_defaults_hint
    from apcg_core.plausibility import range_band_warning, sparse_cloud_warning

    from .simulate import Simulator

    lidar = lidar_or_default(args)
    sensor = sensor_of(args)
    supersample = args.supersample or (4 if sensor else 1)
    cat = default_catalog()
    t = cat.get(args.type)
    try:  # a refusal of the pose (here or by the geometry) names the option it came from
        cond = Condition.from_degrees(t.index, args.range_m, args.elevation_deg,
                                      args.pitch_deg, args.yaw_deg, args.roll_deg)
        table = cond.as_array()[None]
        with Simulator(args.backend, lidar, quantize=not args.no_quantize,
                       supersample=supersample) as sim:
            if sensor:
                from apcg_core.sensor import to_cloud

                from .simulate import SimResult
                photons, clipped, n_rays = sim.photon_cells_type(cat, t, table, sensor,
                                                                 args.seed)
                res = SimResult(to_cloud(photons, table[:, 2], sim.lidar), 1, clipped,
                                n_rays, args.backend)
            else:
                res = sim.simulate_type(cat, t, table)
    except InputError as exc:
        raise pose_defaults_hint(exc, args) from None
    length = cat.depth_length_m(t)
    meta = {"type": t.name, "catalog_index": t.index, "condition": cond.to_degrees(),
            "backend": args.backend, "quantized": not args.no_quantize,
            "supersample": supersample, "lidar": sim.lidar.to_dict(),
            "depth_length_m": length, "clipped": bool(res.clipped[0])}
    if sensor:
        from apcg_core.sensor import reflectivity_of
        meta.update(sensor=sensor.to_dict(), seed=args.seed, reflectivity=reflectivity_of(t))
    img, stats = res.depth_images(table, length, sim.lidar,
                                  image=bool(args.depth_image or args.normalized_image))
    cloud = res.cloud
    cloud.sample = None
    write_cloud(args.output, cloud, meta)
    if args.depth_image:
        write_depth_image(args.depth_image, img[0])
    if args.normalized_image:
        write_depth_image(args.normalized_image, norm(img[0], cond.q))
    summary = {"output": args.output, "points": len(cloud), "rays": int(res.n_rays[0]),
               "clipped": bool(res.clipped[0]), "clamped_pixels": stats.n_clamped,
               "range_m": [float(np.min(cloud.range_m)), float(np.max(cloud.range_m))]
               if len(cloud) else None}
    if sensor:
        summary.update(sensor=sensor.name, photon_output=sensor.output,
                       signal=int((cloud.label == 1).sum()), noise=int((cloud.label == 0).sum()))
    print(json.dumps(summary))
    from apcg_core.plausibility import window_fit, window_warning
    warnings = [range_band_warning(t, args.range_m),
                sparse_cloud_warning(int((cloud.label == 1).sum()) if sensor else len(cloud),
                                     f"the cloud of {t.name} at {args.range_m:g} m",
                                     len(photons.target_w) if sensor else None,
                                     clipped=bool(res.clipped[0])),
                window_warning(lidar, *window_fit(lidar, lambda n: cat.mesh(n).vertices,
                                                  [t.name], table),
                               f"{t.name} at {args.range_m:g} m")]
    for w in filter(None, warnings):
        print(f"apcg simulate: warning: {w}", file=sys.stderr)
    return 0


# What a build writes at the top of its directory, and what says a directory is a build's own
# (its header, written first: build.py; concurrent --shard builds share it).
DATASET_FILES = ("conditions.csv", "dataset.json", "manifest.json")
DATASET_RECORD = ("dataset.json",)


def register_dataset(sub) -> None:
    p = sub.add_parser("dataset", help="build and inspect training datasets",
                       description="Build a dataset of standard depth images from a TOML config "
                                   "(see docs/DATASET.md), or describe one.")
    dsub = p.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)
    b = dsub.add_parser("build", help="build (or resume) a dataset",
                        description="Deterministic from the config's seed; killed at any point "
                                    "and run again, it finishes the same dataset byte for byte.")
    b.add_argument("--config", required=True,
                   help="TOML file, or a committed config name (see `apcg dataset configs`)")
    add_output(b, "-o", "--output", kind=DIRECTORY, required=True, help="dataset directory",
               files=DATASET_FILES, record=DATASET_RECORD)
    b.add_argument("--backend", choices=BACKENDS, help="override the config's backend")
    add_lidar_argument(b, default_help="the config's [lidar] table, else the paper's; a "
                                       "--lidar overrides the config's")
    b.add_argument("--sensor", metavar="PRESET|FILE.toml",
                   help="override the config's sensor (SPEC section 8): store what that "
                        "single-photon lidar records, with labels; default the config's, "
                        "else the ideal standard cloud")
    b.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    b.add_argument("--shard", metavar="I/N",
                   help="build only shards with index %% N == I (0 <= I < N), for job arrays")
    b.add_argument("--tasks-per-process", type=int, default=None,
                   help="shards a local pool's worker builds before it is replaced "
                        "(default: workers live for the whole build)")
    b.add_argument("--engine", default="local", metavar="NAME",
                   help="where the shards are computed: " + "; ".join(
                       f"{name}: {engine.summary}" for name, engine in ENGINES.items()))
    b.add_argument("--address", metavar="ADDR",
                   help="a running cluster's scheduler (e.g. tcp://head-node:8786) for "
                        "--engine dask; the output directory must be shared storage, mounted "
                        "at the same path on every machine")
    b.add_argument("--connect-timeout-s", type=float, default=None, metavar="S",
                   help="with --address: give up when no Dask scheduler answers there within "
                        "S seconds (default 10)")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    b.set_defaults(func=_run_build, resume_hint="Run the same command again: the build "
                                                "continues where it stopped.")
    i = dsub.add_parser("info", help="describe a dataset directory")
    i.add_argument("directory")
    i.add_argument("--verify", action="store_true",
                   help="read every shard and check it against the manifest")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=_run_info)
    c = dsub.add_parser("configs", help="list the committed dataset configs")
    c.set_defaults(func=_run_configs)


def _run_build(args) -> int:
    from .build import BuildInterrupted, build_dataset
    try:
        summary = build_dataset(args.config, args.output, backend=args.backend,
                                workers=args.workers, shard_spec=args.shard,
                                progress=not args.no_progress,
                                tasks_per_process=args.tasks_per_process, engine=args.engine,
                                address=args.address, connect_timeout_s=args.connect_timeout_s,
                                sensor=args.sensor, lidar=args.lidar,
                                warn=lambda w: print(f"apcg dataset: warning: {w}",
                                                     file=sys.stderr, flush=True))
    except BuildInterrupted as stop:  # Ctrl-C among the shards: say how far it got
        print(f"apcg dataset: {stop}", file=sys.stderr)
        return 130  # as shells do; main() answers a Ctrl-C before the shards alike
    print(json.dumps(summary))
    from apcg_core.plausibility import band_share_warning
    warning = band_share_warning(summary["samples_outside_table1_bands"], summary["n_samples"])
    if warning:
        print(f"apcg dataset: warning: {warning}", file=sys.stderr)
    return 0


def _run_info(args) -> int:
    from .build import dataset_info
    print_mapping(dataset_info(args.directory, verify=args.verify), args.json)
    return 0


def _run_configs(args) -> int:
    from .plan import builtin_configs, load_config
    for name in builtin_configs():
        print(f"{name:14s} {load_config(name).get('description', '')}")
    return 0


# What a scene sequence writes at the top of its directory, and what says a directory is one
# (its header, written first: scene.py; the frames go under frames/).
SEQUENCE_FILES = ("sequence.json", "poses.csv", "manifest.json")
SEQUENCE_RECORD = ("sequence.json",)


def register_scene(sub) -> None:
    p = sub.add_parser("scene", help="scan scenes of several targets, static or moving, into "
                                     "labelled clouds and sequences",
                       description="A scene file (TOML, docs/SCENES.md) holds [[target]] "
                                   "tables (type, range_m, azimuth_deg, elevation_deg, "
                                   "pitch_deg, yaw_deg, roll_deg, an optional trajectory) and "
                                   "optional [lidar], [pointing], [scan] and [sequence] "
                                   "tables. Nearest surface of all targets per cell; every "
                                   "point labelled with its target's instance and type.")
    ssub = p.add_subparsers(dest="scene_command", metavar="ACTION", required=True)
    s = ssub.add_parser("scan", help="one frame of a scene to an NPZ cloud",
                        description="The scene at its first frame (its [sequence] start_s, 0 "
                                    "by default). One target alone at azimuth 0 gives `apcg "
                                    "simulate`'s cloud, byte for byte.")
    q = ssub.add_parser("sequence", help="every frame of a scene to a sequence directory",
                        description="One cloud per frame with instance and type labels, every "
                                    "target's pose per frame and track ids (docs/SCENES.md; "
                                    "read back with apcg_core.scene.load_sequence). Killed and "
                                    "run again it finishes the same bytes; any engine, the "
                                    "same bytes.")
    for c in (s, q):
        c.add_argument("scene", help="the scene file (TOML)")
        c.add_argument("--backend", choices=[b for b in BACKENDS if b != "points"],
                       default="embree", help="ray casting: embree (default), blender, "
                                              "blender-bvh")
        c.add_argument("--supersample", type=int, default=None, metavar="K",
                       help="K x K rays per cell, nearest hit kept (default 1; 4 with a "
                            "sensor, whose stage takes every sub-ray)")
        c.add_argument("--no-quantize", action="store_true",
                       help="keep exact ranges instead of the time-bin centres")
        add_sensor_arguments(c)
        add_lidar_argument(c, "the scene file's [lidar] table, else the paper's")
        c.add_argument("--generator", metavar="MODEL",
                       help="draw every target whose [[target]] has no generator key with a "
                            "model instead of the simulator: \"default\" (the shipped model) "
                            "or a model directory; composited by range, nearest wins; a pose "
                            "outside the model's condition space is simulated in that frame "
                            "(docs/SCENES.md)")
    add_output(s, "-o", "--output", kind=FILE, suffixes=(".npz",), required=True,
               help="the cloud: .npz (xyz, range_m, cell_w, cell_h, instance, type, poses)")
    s.set_defaults(func=_run_scene_scan)
    add_output(q, "-o", "--output", kind=DIRECTORY, required=True, files=SEQUENCE_FILES,
               record=SEQUENCE_RECORD, help="the sequence directory")
    q.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    q.add_argument("--engine", default="local", metavar="NAME",
                   help="where the frames are computed: " + "; ".join(
                       f"{name}: {engine.summary}" for name, engine in ENGINES.items()))
    q.add_argument("--address", metavar="ADDR",
                   help="a running Dask cluster's scheduler for --engine dask")
    q.add_argument("--connect-timeout-s", type=float, default=None, metavar="S",
                   help="with --address: give up when no scheduler answers within S seconds")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")
    q.set_defaults(func=_run_scene_sequence)


def _scene_warnings(args, summary: dict, found: list) -> None:
    from .scene import fallback_warning, sequence_warnings
    for w in [*sequence_warnings(args.scene, lidar_of(args), args.generator), *found,
              fallback_warning(summary.get("generator", {}))]:
        if w:
            print(f"apcg scene: warning: {w}", file=sys.stderr)


def _run_scene_scan(args) -> int:
    from .scene import scan_scene
    found = []
    summary = scan_scene(args.scene, args.output, args.backend, args.supersample,
                         not args.no_quantize, sensor_of(args), args.seed, lidar_of(args),
                         args.generator, warnings=found)
    print(json.dumps(summary))
    _scene_warnings(args, summary, found)
    return 0


def _run_scene_sequence(args) -> int:
    from .build import BuildInterrupted
    from .scene import build_sequence
    found = []
    try:
        summary = build_sequence(args.scene, args.output, args.backend, args.supersample,
                                 not args.no_quantize, sensor_of(args), args.seed,
                                 lidar_of(args), workers=args.workers, engine=args.engine,
                                 address=args.address, connect_timeout_s=args.connect_timeout_s,
                                 progress=not args.no_progress, generator=args.generator,
                                 warnings=found)
    except BuildInterrupted as stop:  # Ctrl-C among the frames: how far it got
        print(f"apcg scene: {stop}", file=sys.stderr)
        return 130
    print(json.dumps(summary))
    _scene_warnings(args, summary, found)
    return 0
