"""What each command-line option accepts: one table, by option name, for every command.

An option's name has one meaning across the commands (``--seed`` is a seed wherever it
appears), so its rule lives here once and ``apcg`` checks every parsed value against it before a
command runs: a refused value is named with what is accepted, exit code 2, no traceback. Every
numeric option of every command must have a rule (a test walks the parsers), so an option added
later cannot go unchecked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Rule:
    accepted: str  # for the message: "an integer >= 1"
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False  # lo itself excluded
    hi_open: bool = False

    def ok(self, v: float) -> bool:
        if not math.isfinite(v):
            return False
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below


COUNT = Rule("an integer >= 1", lo=1)
POSITIVE = Rule("a finite number > 0", lo=0, lo_open=True)
SEED = Rule("an integer from 0 to 4294967295", lo=0, hi=2**32 - 1)
ANY = Rule("a finite number")
ANGLE = Rule("a finite angle in degrees from -360 to 360", lo=-360, hi=360)
# Clouds per type a dataset plan (dataset_builder/schema.py samples_per_type) or a benchmark
# (--train-per-type) may ask for: 10^7, about a day of this project's CPU build per type.
MAX_PER_TYPE = 10**7
PER_TYPE = Rule(f"an integer from 1 to {MAX_PER_TYPE}", lo=1, hi=MAX_PER_TYPE)

# dest (the option's name with "_" for "-") -> Rule.
RULES: dict[str, Rule] = {
    # sizes and counts
    "count": COUNT, "steps": COUNT,
    # teach: fewer than 8 conditions leave too few held out to score the type
    "samples": Rule("an integer >= 8", lo=8),
    # beyond these a request only exhausts the machine (processes, memory) before failing
    "batch_size": Rule("an integer from 1 to 65536", lo=1, hi=65536),
    "pairs": Rule("an integer >= 0 (0: every held-out pair)", lo=0),
    "workers": Rule("an integer from 1 to 1024", lo=1, hi=1024),
    "threads": Rule("an integer from 1 to 1024", lo=1, hi=1024),
    "columns": Rule("an integer from 1 to 64", lo=1, hi=64),
    # a critic trained 100 times a generator step is past any WGAN's use (the paper's 5)
    "n_critic": Rule("an integer from 1 to 100", lo=1, hi=100),
    # points a point-set network draws a cloud: 2^16 is 100 times the densest cloud here
    "n_points": Rule("an integer from 1 to 65536", lo=1, hi=65536),
    "checkpoint_every": COUNT, "keep_every": COUNT, "log_every": COUNT,
    "train_per_type": PER_TYPE, "test_per_type": PER_TYPE, "networks": COUNT,  # recognize
    "bootstrap": Rule("an integer >= 0 (0: no interval)", lo=0),
    # a diffusion schedule of 10^4 steps is ten times DDPM's 1,000 (Ho et al., NeurIPS 2020)
    "sampling_steps": Rule("an integer from 1 to 10000", lo=1, hi=10_000),
    "diffusion_steps": Rule("an integer from 1 to 10000", lo=1, hi=10_000),
    "max_checkpoints": COUNT,
    # steps a memory measurement trains (compare): a few show the peak
    "memory_steps": Rule("an integer from 0 to 1000 (0: skip)", lo=0, hi=1000),
    "tasks_per_process": COUNT,
    "dpi": Rule("an integer from 10 to 1200", lo=10, hi=1200),
    "supersample": Rule("an integer from 1 to 16", lo=1, hi=16),
    "voxel_res": Rule("an integer 4 x 2^k from 8 to 256 (8, 16, 32, 64, 128, 256)", lo=8,
                      hi=256),
    "sheet": Rule("an integer 4 x 2^k from 8 to 256 (8, 16, 32, 64, 128, 256)", lo=8,
                  hi=256),
    "number": ANY,  # a figure number: argparse's choices check it
    "seed": SEED,
    # amounts of time and training
    "connect_timeout_s": Rule("a number of seconds > 0 and <= 3600", lo=0, hi=3600,
                              lo_open=True),
    # beyond 10^6 epochs a step count overflows before any training is done
    "epochs": Rule("a number > 0 and <= 1000000", lo=0, hi=1e6, lo_open=True),
    "hours": POSITIVE, "minutes": POSITIVE, "max_minutes": POSITIVE,
    "width": Rule("a number > 0 and <= 4 (1.0 = the paper's width)", lo=0, hi=4,
                  lo_open=True),
    "ema": Rule("a number from 0 to 1, 1 excluded", lo=0, hi=1, hi_open=True),
    "diverge_gp": Rule("a finite number >= 0 (0: never)", lo=0),
    "lr": Rule("a finite learning rate > 0 and <= 1", lo=0, hi=1, lo_open=True),
    "tau": ANY,  # its range is the model's own (Model.check_tau), checked where it is used
    # geometry
    "range_m": Rule("a finite range in metres > 0 and <= 1e6", lo=0, hi=1e6, lo_open=True),
    # +-90 itself passes here to the pose check, which says why overhead is refused
    "elevation_deg": Rule("a finite elevation in degrees from -90 to 90", lo=-90, hi=90),
    # the pose check's own ranges (condition.Condition: nose up or down at most vertical, yaw
    # and roll a half turn either way), so that a refusal names the option the user typed;
    # tests/test_options.py holds them equal to the Condition's
    "pitch_deg": Rule("a finite pitch in degrees from -90 to 90", lo=-90, hi=90),
    "yaw_deg": Rule("a finite yaw in degrees from -180 to 180", lo=-180, hi=180),
    "roll_deg": Rule("a finite roll in degrees from -180 to 180", lo=-180, hi=180),
    "azimuth_deg": ANGLE,
    "length_m": Rule("a finite length in metres > 0 and <= 1000", lo=0, hi=1000,
                     lo_open=True),
    "unit_scale": Rule("a finite factor > 0 and <= 1000", lo=0, hi=1000, lo_open=True),
    "reflectivity": Rule("a diffuse reflectance > 0 and <= 1", lo=0, hi=1, lo_open=True),
}


def option_name(dest: str) -> str:
    return "--" + dest.replace("_", "-")


def problems(values: dict) -> list[str]:
    """Messages for every numeric value in ``values`` (an argparse namespace's dict) that its
    rule refuses; a float without a rule must still be finite."""
    out = []
    for dest, value in values.items():
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            rule = RULES.get(dest, ANY)
            if not rule.ok(float(v)):
                out.append(f"{option_name(dest)} {v!r} not accepted: {rule.accepted}")
    return out


# A seed from a Python caller: None is no seed (a draw left unseeded would not repeat), and a
# float is not one either (3.0 may be 3.0000000001 computed); other names' None is the
# function's own default, and their whole floats count as integers, as on the command line.
_SEED_NAMES = ("seed",)


def _integer(dest: str, v):
    """``v`` as a Python int (any integer type, numpy's too, through operator.index; a whole
    float where ``dest`` is not a seed), else None."""
    import operator
    if isinstance(v, bool | str):
        return None
    try:
        return operator.index(v)
    except TypeError:
        pass
    if dest in _SEED_NAMES:
        return None
    try:
        f = float(v)
        return int(f) if f.is_integer() else None
    except (TypeError, ValueError, OverflowError):
        return None


def check_values(**values) -> dict:
    """The same rules for a Python function's keyword arguments (the Blender add-on's API takes
    the command line's names): raise InputError naming the first refused value and what is
    accepted. None is skipped (the function's own default applies), except for a seed.
    Returns the values, an integer rule's as a Python int."""
    from .errors import InputError
    out = {}
    for dest, v in values.items():
        rule = RULES.get(dest, ANY)
        if v is None and dest not in _SEED_NAMES:
            out[dest] = v
            continue
        integer = rule.accepted.startswith("an integer")
        try:
            number = _integer(dest, v) if integer else (
                None if isinstance(v, bool | str) else float(v))
            ok = number is not None and rule.ok(float(number))
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise InputError(f"{dest} = {v!r} not accepted: {rule.accepted}")
        out[dest] = number if integer else v
    return out


def model_condition(model, args):
    """``model.condition`` of a command's --type and pose options, whose attitude options
    default to None (not given: 0 deg); a refusal of such a 0 says it was the default."""
    from .errors import InputError
    from .lidar import DEG
    attitude = [(getattr(args, k) or 0.0) * DEG for k in ("pitch_deg", "yaw_deg", "roll_deg")]
    try:
        return model.condition(args.type, args.range_m, args.elevation_deg * DEG, *attitude)
    except InputError as exc:
        raise pose_defaults_hint(exc, args) from None


def pose_defaults_hint(exc, args):
    """A refusal of the pose that names the option its value came from (the condition names
    its field: range_m, elevation, ...), and, for a default (pitch, yaw, roll: 0 deg when
    not given), that the user did not write the value."""
    from .errors import InputError
    for k in ("range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg"):
        field = k if k == "range_m" else k[:-len("_deg")]
        if f"{field} = " not in str(exc):
            continue
        option = option_name(k)
        if getattr(args, k, 0.0) is None:
            return InputError(f"{exc}; {field} 0 deg is the default of {option}, which "
                              f"was not given: give {option} within that range")
        return InputError(f"{exc}; the value of {option}")
    return exc
