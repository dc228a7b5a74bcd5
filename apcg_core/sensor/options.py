"""The command line's sensor options, one definition for every command that takes them."""

from __future__ import annotations

from ..errors import InputError
from ..lidar import lidar_sensor_file
from .params import OUTPUTS, load_sensor, preset_names


def add_sensor_arguments(p, seed: bool = True) -> None:
    """``--sensor``, ``--seed`` (unless the command has its own, which then seeds the photons
    too) and ``--photon-output``: the photon stage (SPEC section 8)."""
    p.add_argument("--sensor", metavar="PRESET|FILE.toml",
                   help="what a real single-photon lidar records (SPEC section 8): a preset ("
                        + ", ".join(preset_names()) + ") or a TOML file with a [sensor] "
                        "table; default ideal (the standard cloud, no photon statistics)")
    if seed:
        p.add_argument("--seed", type=int, default=0,
                       help="seed of the photon draws (default 0); the same seed, the same "
                            "bytes")
    p.add_argument("--photon-output", choices=OUTPUTS,
                   help="override the sensor's output: points (one per cell at the "
                        "histogram's peak) or events (every detector event)")


def sensor_of(args):
    """The sensor the options ask for (None: the ideal lidar), with ``--photon-output``;
    without ``--sensor``, the ``[sensor]`` table of the ``--lidar`` file when it has one."""
    ref = args.sensor
    if ref is None:
        ref = lidar_sensor_file(getattr(args, "lidar", None))
    sensor = load_sensor(ref, lidar_file=args.sensor is None)
    if sensor is not None and getattr(args, "backend", None) == "points":
        raise InputError("--sensor needs a ray-casting backend (the photon stage takes every "
                         "sub-ray's range and incidence); accepted: embree, blender, "
                         "blender-bvh")
    if sensor is not None and getattr(args, "no_quantize", False):
        raise InputError("--no-quantize does not apply with --sensor: a sensor's points sit at "
                         "their time bins' centres (SPEC section 8); drop one of the two")
    if sensor is None:
        if args.photon_output:
            raise InputError("--photon-output needs a --sensor other than ideal")
        return None
    return sensor.with_output(args.photon_output) if args.photon_output else sensor
