"""``apcg generate``: APCG point clouds for one condition or a CSV of conditions."""

from __future__ import annotations

import json

from .cli import add_pose_arguments


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
    p.add_argument("--count", type=int, default=1, help="clouds per condition (default 1)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--runtime", choices=["auto", "onnx", "torch"], default="auto",
                   help="cGAN inference: auto (torch when installed, else onnxruntime), onnx, "
                        "torch; the same images either way")
    p.add_argument("--tau", type=float, help="output threshold (default: the model's): the "
                                             "cGAN's Im2PC tau, APCG+'s hit logit")
    p.add_argument("-o", "--output", required=True,
                   help=".ply / .npz / .las / .laz; several clouds go in one file, told apart by "
                        "their `sample` attribute")
    p.set_defaults(func=_run_generate)


def _run_generate(args) -> int:
    from .errors import InputError
    from .generation import conditions_from_csv, load_model
    from .io import write_cloud
    from .lidar import DEG

    model = load_model(args.model, runtime=args.runtime)
    if args.tau is not None:
        if getattr(model, "tau", None) is None:
            raise InputError(f"--tau is an output threshold; {model.directory} is a "
                             f"{model.family} model, which has none")
        model.tau = model.check_tau(args.tau)
    if args.conditions:
        if args.type:
            raise InputError("give either --conditions or --type with a pose, not both")
        table = conditions_from_csv(args.conditions, model)
    else:
        if args.type is None or args.range_m is None or args.elevation_deg is None:
            raise InputError("give --type, --range-m and --elevation-deg (or --conditions)")
        table = model.condition(args.type, args.range_m, args.elevation_deg * DEG,
                                args.pitch_deg * DEG, args.yaw_deg * DEG, args.roll_deg * DEG)
    res = model.generate(table, count=args.count, seed=args.seed)
    first = res.conditions[:: args.count]
    meta = {"model": str(model.directory), "family": model.family,
            "runtime": getattr(model, "runtime", None), "seed": args.seed,
            "count": args.count, "tau": getattr(model, "tau", None),
            "conditions": [{"type": name, "range_m": float(r[1]), "elevation_rad": float(r[2]),
                            "pitch_rad": float(r[3]), "yaw_rad": float(r[4]),
                            "roll_rad": float(r[5])}
                           for name, r in zip(first.names, first.table, strict=True)]}
    write_cloud(args.output, res.cloud, meta)
    print(json.dumps({"output": args.output, "clouds": len(res.table),
                      "points": len(res.cloud), "family": model.family,
                      "runtime": getattr(model, "runtime", None)}))
    return 0
