"""Every output option of every command, found from the parsers themselves (the entry points),
and command lines that reach the output guard with one of them set (tests/test_outputs.py,
tests/test_fuzz.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from apcg_core.cli import build_parser, join_signed_values
from apcg_core.outputs import ANY, DIRECTORY, FILE, Output

# Every option of every command that takes a free string and is not declared as an output
# (apcg_core.outputs.add_output): what it is. "input" options name a path the command reads;
# the guard never lets the command replace them. A new string option fails
# test_every_option_that_takes_a_path_is_classified until it is declared or listed here.
INPUT, VALUE = "input", "value"
NOT_OUTPUTS = {
    ("ablation", "data"): INPUT, ("ablation", "encoder"): INPUT,
    ("catalog export", "name"): VALUE, ("catalog show", "names"): VALUE,
    ("catalog add", "file"): INPUT, ("catalog add", "name"): VALUE,
    ("catalog add", "forward"): VALUE, ("catalog add", "up"): VALUE,
    ("catalog add", "objects"): VALUE, ("catalog add", "category"): VALUE,
    ("catalog remove", "name"): VALUE,
    ("choose-tau", "model"): INPUT, ("choose-tau", "data"): INPUT,
    ("choose-tau", "taus"): VALUE,
    ("compare", "data"): INPUT, ("compare", "model"): INPUT,
    ("condition", "type"): VALUE, ("condition", "model"): INPUT,
    ("export", "data"): INPUT,
    ("dataset build", "config"): INPUT, ("dataset build", "shard"): VALUE,
    ("dataset build", "engine"): VALUE, ("dataset build", "address"): VALUE,
    ("dataset info", "directory"): INPUT,
    ("evaluate", "model"): INPUT, ("evaluate", "data"): INPUT,
    ("export", "run"): INPUT, ("export", "checkpoint"): INPUT,
    ("fd-depth train", "data"): INPUT,
    ("fd-depth score", "encoder"): INPUT, ("fd-depth score", "data"): INPUT,
    ("fd-depth score", "model"): INPUT,
    ("figure", "run"): INPUT, ("figure", "model"): INPUT, ("figure", "data"): INPUT,
    ("generate", "model"): INPUT, ("generate", "type"): VALUE,
    ("generate", "conditions"): INPUT,
    ("simulate", "type"): VALUE, ("simulate", "sensor"): INPUT,
    ("dataset build", "sensor"): INPUT, ("generate", "sensor"): INPUT,
    ("teach", "model"): INPUT, ("teach", "type"): VALUE,
    ("distill", "teacher"): INPUT, ("train", "init"): INPUT,
    ("scene scan", "scene"): INPUT, ("scene scan", "sensor"): INPUT,
    ("scene sequence", "scene"): INPUT, ("scene sequence", "sensor"): INPUT,
    ("scene sequence", "engine"): VALUE, ("scene sequence", "address"): VALUE,
    ("generate", "engine"): VALUE, ("generate", "address"): VALUE,
    ("scene scan", "generator"): INPUT, ("scene sequence", "generator"): INPUT,
    # --lidar PRESET|FILE (apcg_core/lidar_options.py), a lidar file read, never written
    ("simulate", "lidar"): INPUT, ("generate", "lidar"): INPUT,
    ("dataset build", "lidar"): INPUT, ("evaluate", "lidar"): INPUT,
    ("compare", "lidar"): INPUT, ("teach", "lidar"): INPUT, ("figure", "lidar"): INPUT,
    ("scene scan", "lidar"): INPUT, ("scene sequence", "lidar"): INPUT,
    ("train", "data"): INPUT,
    ("benchmark recognize", "source"): INPUT, ("benchmark recognize", "types"): VALUE,
    ("benchmark recognize", "sensor"): INPUT, ("benchmark recognize", "lidar"): INPUT,
}


def commands(parser=None) -> list[tuple[str, argparse.ArgumentParser]]:
    """("catalog add", parser) for every leaf command."""
    out = []

    def walk(p, words):
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        for a in subs:
            for name, sub in a.choices.items():
                walk(sub, [*words, name])
        if not subs and words:
            out.append((" ".join(words), p))
    walk(parser or build_parser(), [])
    return out


def takes_free_text(action) -> bool:
    """An option whose value could be a path (not a flag, a number or a choice)."""
    if isinstance(action, (argparse._HelpAction, argparse._VersionAction,
                           argparse._SubParsersAction)):
        return False
    return not (action.nargs == 0 or action.type in (int, float) or action.choices)


def unclassified(parser=None) -> list[str]:
    """Options that take free text and are neither declared outputs nor listed above."""
    return [f"apcg {cmd} {a.option_strings[-1] if a.option_strings else a.dest}"
            for cmd, p in commands(parser) for a in p._actions
            if takes_free_text(a) and not hasattr(a, "apcg_output")
            and (cmd, a.dest) not in NOT_OUTPUTS]


def outputs() -> list[tuple[str, argparse.ArgumentParser, argparse.Action, Output]]:
    return [(cmd, p, a, a.apcg_output) for cmd, p in commands() for a in p._actions
            if hasattr(a, "apcg_output")]


def inputs_of(cmd: str) -> list[str]:
    return [dest for (c, dest), what in NOT_OUTPUTS.items() if c == cmd and what == INPUT]


def _placeholder(action, tmp: Path) -> str:
    spec = getattr(action, "apcg_output", None)
    if spec is not None:  # another output the command requires: a fresh name of its format
        return str(tmp / (f"required{spec.suffixes[0] if spec.suffixes else '.x'}"
                          if spec.kind == FILE else "required-dir"))
    if action.choices:
        return str(next(iter(action.choices)))
    if action.type in (int, float):
        return "3000" if "range" in action.dest else "3"
    return {"type": "A320neo", "name": "guard-type", "names": "A320neo"}.get(
        action.dest, str(tmp / "nowhere"))


def argv_for(cmd: str, parser, tmp: Path, values: dict[str, str]) -> list[str]:
    """A command line of ``cmd`` with ``values`` (dest -> value) and placeholders for every
    other required argument."""
    argv, positionals = cmd.split(), []
    for a in parser._actions:
        if a.dest == "help" or isinstance(a, argparse._SubParsersAction):
            continue
        value = values.get(a.dest)
        if value is None and not (a.required or not a.option_strings):
            continue
        if value is None and not a.option_strings and a.nargs in ("*", "?"):
            continue
        value = _placeholder(a, tmp) if value is None else value
        if a.option_strings:
            argv += [a.option_strings[-1], value] if a.nargs != 0 else [a.option_strings[-1]]
        else:
            positionals.append(value)
    return argv + positionals


def parse(argv: list[str]) -> argparse.Namespace:
    args = build_parser().parse_args(join_signed_values(list(argv)))
    return args


def sample_value(spec: Output, tmp: Path) -> str:
    """A path for the output ``spec`` in ``tmp``, of an accepted format."""
    if spec.kind == FILE:
        return str(tmp / f"out{spec.suffixes[0] if spec.suffixes else '.x'}")
    return str(tmp / "outdir")


def planned_files(spec: Output, args) -> list[Path]:
    return [p for _, p in spec.planned(args)]


def named_files(spec: Output, args) -> bool:
    """Whether the output names the files it writes before it runs (not ANY)."""
    if spec.kind != DIRECTORY:
        return True
    names = spec.files(args) if callable(spec.files) else spec.files
    return names != ANY
