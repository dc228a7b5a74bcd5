"""The ``apcg`` command line. Subcommands are plugged in through the ``apcg.commands`` entry
point group (see pyproject.toml), so that this core package never imports the packages that
stand on it (dataset_builder, training): the arrows point down only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shlex
import sys
import threading
from importlib.metadata import entry_points

from . import __version__
from .errors import APCGError, os_error_message


def build_parser(registrars=None, command: str | None = None) -> argparse.ArgumentParser:
    """The ``apcg`` parser; ``registrars`` (functions adding subparsers) replace the installed
    entry points, for runs where the package is not installed (e.g. inside a Blender binary).
    ``command``: the command about to run; where an installed entry point has its name (each
    registers the command it is named after), only that one is loaded (a command does not
    import every other command's modules: a fifth of a short command's start-up)."""
    parser = argparse.ArgumentParser(
        prog="apcg",
        description="Aircraft point clouds as a single-photon counting lidar sees them.")
    parser.add_argument("--version", action="version", version=f"apcg {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    if registrars is None:
        installed = sorted(entry_points(group="apcg.commands"), key=lambda e: e.name)
        named = [ep for ep in installed if ep.name == command]
        registrars = [ep.load() for ep in (named or installed)]
    for register in registrars:
        register(sub)
    return parser


# Options whose value may begin with a minus sign that argparse would read as an option
# ("--forward -X"): such a pair is joined ("--forward=-X") before parsing.
SIGNED_VALUE_OPTIONS = ("--forward", "--up")
_AXIS = re.compile(r"^[+-]?[XYZxyz]$")


# A value beginning with a minus sign that argparse takes for an option (its own pattern
# knows -1 and -0.5, not -1e9, -inf or a shard spec -1/4): joined to the long option before it
# ("--tau -1e9" -> "--tau=-1e9"), whose own check then judges the value ("-inf" is refused as
# not finite, "-1/4" as no shard). No option of apcg begins with a minus and a digit.
_NEGATIVE_NUMBER = re.compile(r"^-(\d|\.\d)|^-(inf|infinity|nan)$", re.IGNORECASE)


def join_signed_values(argv: list[str]) -> list[str]:
    """``--forward -X`` -> ``--forward=-X`` for the options that take an axis, and
    ``--tau -1e9`` -> ``--tau=-1e9`` for a negative number argparse would read as an
    option."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        if nxt is not None and a.startswith("--") and "=" not in a \
                and _NEGATIVE_NUMBER.match(nxt):
            out.append(f"{a}={nxt}")
            i += 2
            continue
        if a in SIGNED_VALUE_OPTIONS and i + 1 < len(argv) and _AXIS.match(argv[i + 1]):
            out.append(f"{a}={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


class _PipeSafe:
    """sys.stdout or sys.stderr of the `apcg` process, whose reader may go away (`apcg ... |
    head -1`, `2>/dev/null | true`): a write after the pipe broke is dropped (the stream sent
    to /dev/null), so the command runs to its end and its files are kept. A BrokenPipeError
    that unwound the command lost them: its outputs are renamed into place when it ends.

    Lines are written whole: each thread's text is held until its line ends (or it
    flushes: a progress bar redrawn in place), so a warning from a worker thread and the main
    thread's error never share a line (print writes a line and its end in two calls)."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self._lock = threading.Lock()
        self._held: dict[int, str] = {}  # thread id -> its text after its last line end

    def _broke(self) -> None:
        with contextlib.suppress(OSError, ValueError):  # later flushes, at exit too, go nowhere
            os.dup2(os.open(os.devnull, os.O_WRONLY), self._stream.fileno())

    def _emit(self, text: str, flush: bool = False) -> None:
        try:
            self._stream.write(text)
            if flush:
                self._stream.flush()
        except BrokenPipeError:
            self._broke()

    def write(self, text):
        key = threading.get_ident()
        with self._lock:
            text_all = self._held.pop(key, "") + text
            cut = text_all.rfind("\n") + 1
            if cut < len(text_all):
                self._held[key] = text_all[cut:]
            if cut:
                self._emit(text_all[:cut], flush=True)
        return len(text)

    def flush(self) -> None:
        """This thread's held text, then the stream's buffer."""
        with self._lock:
            self._emit(self._held.pop(threading.get_ident(), ""), flush=True)

    def drain(self) -> None:
        """Every thread's held text (the command has ended)."""
        with self._lock:
            held, self._held = self._held, {}
            self._emit("".join(held.values()), flush=True)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None, registrars=None) -> int:
    command = ["apcg"]  # grows to "apcg COMMAND" once parsed, for the messages
    resume_hint = [RUN_AGAIN]  # the command's own once parsed (its parser's resume_hint)
    restore = _terminate_as_interrupt()
    if argv is None and not isinstance(sys.stdout, _PipeSafe):  # the `apcg` process itself
        sys.stdout, sys.stderr = _PipeSafe(sys.stdout), _PipeSafe(sys.stderr)
    try:
        code = _run(argv, registrars, command, resume_hint)
        if argv is None:  # done: a stop from here on is held back (a stop before: 130)
            _ignore_late_stops()
            from .testpoints import wait_point
            wait_point("cli.command-ended")
        return code
    except BrokenPipeError:  # e.g. `apcg catalog list | head`
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - silence the flush at exit
        return 0
    except APCGError as exc:  # a clear message, not a traceback, for the user's own mistakes
        print(f"{' '.join(command)}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C, even while starting: outputs go through temporary names
        print(f"{' '.join(command)}: interrupted; nothing half-written is left under a final "
              f"name. {resume_hint[0]}", file=sys.stderr)
        return 130
    except OSError as exc:  # the file system said no (full disk, permissions): name the file
        print(f"{' '.join(command)}: error: {os_error_message(exc)}", file=sys.stderr)
        return 1
    except MemoryError as exc:  # the request's arrays outgrew the machine: say so in one line
        from .sensor.stage import COST_SETTINGS  # what drives the photon stage's cost
        detail = f" ({exc})" if str(exc) else ""
        print(f"{' '.join(command)}: error: out of memory{detail}; nothing half-written is "
              "left under a final name. Ask for less at once: fewer clouds or conditions a "
              "call, a smaller lidar window, or sensor values that make fewer events "
              f"({COST_SETTINGS})", file=sys.stderr)
        return 1
    finally:
        if argv is None:  # the `apcg` process itself: its command has ended, whatever its end
            _ignore_late_stops()
            for stream in (sys.stdout, sys.stderr):
                if isinstance(stream, _PipeSafe):
                    stream.drain()
        else:
            restore()


def _ignore_late_stops() -> None:
    """Ctrl-C or SIGTERM arriving after the command has ended (while the interpreter exits)
    would kill the process by the signal (Python re-raises an uncaught KeyboardInterrupt as
    SIGINT): the exit status would say "killed" of a command that had finished, or had
    already stopped cleanly with 130. They are ignored from here on (the disposition is the
    process's, whichever thread the signal reaches); the process exits with the command's own
    status."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _terminate_as_interrupt():
    """SIGTERM (a job scheduler's time limit, `kill`) stops a command as Ctrl-C does: outputs
    finished or absent, locks released, exit 130. Returns what puts the old handler back."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return lambda: None
    signal.signal(signal.SIGTERM, _interrupt)
    return lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL)


# What Ctrl-C's message tells to do next, unless the command's parser sets ``resume_hint``
# (a build, a resumable generation, a training run: each says how it continues).
RUN_AGAIN = "Run the same command again to redo it."


def _run(argv, registrars, command: list, resume_hint: list) -> int:
    given = list(sys.argv[1:] if argv is None else argv)
    argv = join_signed_values(given)
    parser = build_parser(registrars, argv[0] if argv else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    command.append(args.command)
    resume_hint[0] = getattr(args, "resume_hint", None) or RUN_AGAIN
    # the command as typed, quoted so that it can be pasted back (reports record it)
    args.command_line = shlex.join(["apcg", *given])
    from .options import problems
    from .outputs import guarding, output_problems
    # one line, the first problem: an option's value before the outputs it would name
    refused = problems(vars(args)) or output_problems(args)
    if refused:
        print(f"apcg {args.command}: error: {refused[0]}", file=sys.stderr)
        return 2
    with guarding(args):  # every file written goes through its guard (outputs.py)
        return int(args.func(args) or 0)


def print_mapping(mapping: dict, as_json: bool, key_width: int = 24) -> None:
    """A command's result: indented JSON, or one aligned ``key value`` line per entry."""
    if as_json:
        print(json.dumps(mapping, indent=2))
    else:
        for k, v in mapping.items():
            print(f"{k:{key_width}s} {v}")


def add_pose_arguments(p: argparse.ArgumentParser, required: bool = True) -> None:
    """The pose options shared by simulate / generate / condition (edges use degrees);
    ``required`` False where a command can take its conditions from elsewhere (a CSV)."""
    p.add_argument("--range-m", type=float, required=required, help="slant range r0 in metres")
    p.add_argument("--elevation-deg", type=float, required=required,
                   help="elevation beta0 (deg)")
    p.add_argument("--pitch-deg", type=float, default=0.0, help="pitch theta (deg, + nose up)")
    p.add_argument("--yaw-deg", type=float, default=0.0,
                   help="yaw phi (deg, + swings the nose toward +X)")
    p.add_argument("--roll-deg", type=float, default=0.0,
                   help="roll gamma (deg, + lowers the right wing)")


def register_condition(sub) -> None:
    p = sub.add_parser("condition", help="show a condition's vector nu, q and frames",
                       description="Encode one condition as a model's vector nu (its type "
                                   "code is the type's place in that model's own type table) "
                                   "and show the reference range, q and the target centre in "
                                   "each frame.")
    p.add_argument("--type", required=True,
                   help="catalog type name (or catalog index) the model knows")
    p.add_argument("--model", metavar="DIR",
                   help="model directory whose types and ranges code nu (default: the "
                        "shipped default model)")
    add_pose_arguments(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    # None: not given (0 deg), so a refusal of that 0 says it is the default
    p.set_defaults(func=_run_condition, pitch_deg=None, yaw_deg=None, roll_deg=None)


def _run_condition(args) -> int:
    from .condition import Condition
    from .families import ModelTypes
    from .frames import observation_to_blender, target_centre
    from .options import model_condition
    model = ModelTypes(args.model)  # its type table and ranges; its network is not needed
    cond = model_condition(model, args)
    one = Condition.from_array(cond.table[0])
    centre = target_centre(one.range_m, one.elevation)
    out = {"type": cond.names[0], "model": str(model.directory),
           "type_code": f"{int(cond.table[0, 0])} of {len(model.types)}",
           "condition": {k: v for k, v in one.to_degrees().items() if k != "type_index"},
           "nu": model.space.encode(cond.table).round(6)[0].tolist(),
           "reference_range_m": one.reference_range_m, "q": one.q,
           "centre_observation_m": centre.round(6).tolist(),
           "centre_blender_lidar_local_m": observation_to_blender(centre).round(6).tolist()}
    print_mapping(out, args.json, key_width=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
