"""Where commands write: one guard for every file a command writes.

Declared: every output option is added with :func:`add_output`, which tags the argparse action
(``action.apcg_output``, an :class:`Output`) with its kind, formats and what is written beside
it (a figure's JSON) or inside it (a report directory's files). Every command that writes gets
``--force``. A test walks every parser and fails on an output option that is not declared.

Checked before any work (:func:`output_problems`): formats; a file given for a directory and
the reverse; two outputs of the command that are one file (``./a`` and ``a``, a symlink, a hard
link); an existing file among those the command will write is kept unless ``--force``, except
in the directory of a resumable job (a build, a training run) that the job made itself, and is
never replaced when it is an input of the same command (the model being taught, the dataset
being scored), ``--force`` or not.

Kept while the command runs (:class:`Guard`, installed by ``apcg_core.cli``): every file goes
through ``apcg_core.io.atomic`` (``atomic_path``, ``publish``), which asks the guard before a
file appears under its final name, by the same rule as above, so a file that no declaration
named is not replaced either. A command's outputs (those outside a resumable job's directory)
appear when the command has finished, together and with Ctrl-C / SIGTERM held for those few
renames: an interrupted command leaves its outputs whole or absent, and the same command run
again works. ``--force`` replaces files the command writes, one by one; no directory is ever
deleted.
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError
from .io.atomic import GUARDS, active, publish

FILE, DIRECTORY = "file", "directory"
# A directory output whose files are known only once the command has run (a model directory:
# its family says what it holds). Without --force it must be empty or absent.
ANY = "*"
# What matplotlib writes for the pictures (figures, contact sheets, previews).
PICTURE_SUFFIXES = (".png", ".pdf", ".svg")
_EXISTS = "; choose another name, or --force to replace it"


@dataclass(frozen=True)
class Output:
    """An output option: ``kind`` FILE or DIRECTORY; a file's accepted ``suffixes`` and its
    ``sidecars`` (suffixes of files written beside it: ``.json`` makes ``fig.png`` +
    ``fig.json``); a directory's ``files`` (names written inside it, a function of the parsed
    arguments, or ANY) and, for a resumable job, ``record`` (patterns of files whose presence
    says the directory is the job's own, from an earlier or a concurrent run)."""

    dest: str
    flag: str
    kind: str = FILE
    suffixes: tuple = ()
    sidecars: tuple = ()
    files: object = ()
    record: tuple = ()

    @property
    def resumable(self) -> bool:
        return bool(self.record)

    def planned(self, args) -> list[tuple[str, Path]]:
        """(label, path) of each file this output makes, for the messages."""
        value = getattr(args, self.dest, None)
        if not named(value):
            return []
        base = Path(value)
        if self.kind == FILE:
            out = [(f"{self.flag} {value}", base)]
            for s in self.sidecars:
                out.append((f"{base.with_suffix(s)} (written beside {self.flag} {value})",
                            base.with_suffix(s)))
            return out
        names = self.files(args) if callable(self.files) else self.files
        if names == ANY:
            return []
        return [(f"{base / n} (written into {self.flag} {value})", base / n) for n in names]


def named(value) -> bool:
    """Whether an output option's value names a path: not absent, not "-" (stdout), not empty
    (refused by :func:`output_problems`: ``Path("")`` would be the working directory)."""
    return value is not None and value != "-" and bool(str(value).strip())


def add_output(parser: argparse.ArgumentParser, *flags: str, kind: str = FILE,
               suffixes: tuple[str, ...] = (), sidecars: tuple[str, ...] = (), files=(),
               record: tuple[str, ...] = (), force_help: str | None = None, **kwargs):
    """``parser.add_argument(*flags, **kwargs)`` for a path the command writes (see
    :class:`Output`); adds ``--force`` to the parser unless it has one."""
    action = parser.add_argument(*flags, **kwargs)
    flag = action.option_strings[-1] if action.option_strings else action.dest
    spec = Output(action.dest, flag, kind, tuple(suffixes), tuple(sidecars),
                  files if callable(files) or files == ANY else tuple(files), tuple(record))
    action.apcg_output = spec  # the declaration a test finds on every output option
    parser.set_defaults(_outputs=(*(parser.get_default("_outputs") or ()), spec))
    # views kept for callers that list file outputs and their formats
    key = "_file_outputs" if kind == FILE else "_directory_outputs"
    parser.set_defaults(**{key: (*(parser.get_default(key) or ()), action.dest)})
    if suffixes:
        parser.set_defaults(_output_suffixes={**(parser.get_default("_output_suffixes") or {}),
                                              action.dest: tuple(suffixes)})
    if "--force" not in parser._option_string_actions:
        parser.add_argument("--force", action="store_true", help=force_help or (
            "replace output files that already exist (only the files this command writes; "
            "never a directory, never an input of the command)"))
    return action


def declared_outputs(args) -> tuple[Output, ...]:
    return tuple(getattr(args, "_outputs", None) or ())


# --- what a path is ------------------------------------------------------------------------

def real(path) -> str:
    """One name per file: absolute, symlinks resolved (also a last component that is a link),
    so ``./a``, ``a``, ``dir/../a`` and a link to ``a`` compare equal."""
    return os.path.realpath(os.path.abspath(os.fspath(path)))


def _inside(path: str, directory: str) -> bool:
    return path == directory or path.startswith(directory.rstrip(os.sep) + os.sep)


def _same_file(a: Path, b: Path) -> bool:
    """Hard links too: two names of one existing file."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def input_paths(args) -> list[str]:
    """Every existing path among the command's values that are not outputs: its inputs (a
    model, a dataset, a run, a mesh, a config). ``NAME=PATH`` values count by their path."""
    outputs = {o.dest for o in declared_outputs(args)}
    found = []
    for dest, value in vars(args).items():
        if dest in outputs or dest.startswith("_") or dest in ("func", "command"):
            continue
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(v, str) or not v:
                continue
            for candidate in {v, v.split("=", 1)[-1]}:
                if candidate and os.path.lexists(candidate):
                    found.append(real(candidate))
    return found


# --- the guard -----------------------------------------------------------------------------

class Guard:
    """The running command's outputs: what may be replaced, what is held until the end."""

    def __init__(self, args=None, force: bool = False):
        self.command = str(getattr(args, "command", "") or "")
        self.force = bool(getattr(args, "force", force)) if args is not None else force
        self.specs = declared_outputs(args) if args is not None else ()
        inputs = input_paths(args) if args is not None else []
        self.input_files = {p for p in inputs if not os.path.isdir(p)}
        self.input_dirs = [p for p in inputs if os.path.isdir(p)]
        self.file_outputs: set[str] = set()
        self.dir_outputs: list[tuple[str, Output]] = []
        self.dir_values: list[tuple[Output, str]] = []  # (declaration, value as given)
        for o in self.specs:
            value = getattr(args, o.dest, None)
            if not named(value):
                continue
            if o.kind == FILE:
                self.file_outputs.update(real(p) for _, p in o.planned(args))
            else:
                self.dir_outputs.append((real(value), o))
                self.dir_values.append((o, str(value)))
        self.written: set[str] = set()
        self.allowed: set[str] = set()
        self.pending: dict[str, str] = {}  # final name -> temporary name, until commit

    # which declaration a path falls under
    def _container(self, path: str) -> tuple[str, object] | None:
        """The innermost declared directory holding ``path``: ("input", dir) or ("output",
        spec); an input wins a tie (a directory both read and written)."""
        best = None
        for d in self.input_dirs:
            if _inside(path, d) and (best is None or len(d) >= len(best[1])):
                best = ("input", d, d)
        for d, spec in self.dir_outputs:
            if _inside(path, d) and (best is None or len(d) > len(best[1])):
                best = ("output", d, spec)
        return None if best is None else (best[0], best[1], best[2])

    def is_input(self, path: str) -> bool:
        if path in self.input_files:
            return True
        where = self._container(path)
        return where is not None and where[0] == "input"

    def owned(self, path: str) -> bool:
        """Inside a resumable job's directory that the job has made before (its record)."""
        where = self._container(path)
        if where is None or where[0] != "output" or not where[2].resumable:
            return False
        return _has_record(where[1], where[2].record)

    def defers(self, path: str) -> bool:
        """A command's own result (not a resumable job's file): held until the end."""
        if path in self.file_outputs:
            return True
        where = self._container(path)
        return where is not None and where[0] == "output" and not where[2].resumable

    def refusal(self, path, label: str | None = None) -> str | None:
        """Why the existing ``path`` may not be replaced (None: it may)."""
        r = real(path)
        label = label or str(path)
        if r in self.written or r in self.allowed:
            return None
        if os.path.isdir(r):
            return f"{label} is a directory; it is never replaced: give a file name"
        if self.is_input(r):
            return (f"{label} is an input of this command (or inside one); it is never "
                    "replaced, even with --force: choose another output")
        if self.owned(r) or self.force:
            return None
        return f"{label} already exists{_EXISTS}"

    def claim(self, path) -> bool:
        """Before a file appears under ``path``: refuse (InputError) what may not be replaced;
        True when it is to be held until the command ends."""
        r = real(path)
        if r not in self.written and os.path.lexists(path):
            message = self.refusal(path)
            if message:
                raise InputError(message)
        self.written.add(r)
        return self.defers(r)

    def scratch(self, path) -> None:
        """Before a temporary file is written at ``path`` (renamed or removed by the command):
        an input of the command, or anything already inside an input directory, is refused;
        anything else there is written over. A new name inside an input directory is fine
        (``choose-tau --model M -o M/tau_sweep.json`` writes M/tau_sweep.json.part)."""
        if os.path.lexists(path) and self.is_input(real(path)):
            raise InputError(f"{path} is an input of this command (or inside one), and this "
                             "command writes a temporary file of that name beside its output; "
                             "it is never replaced: choose another output name")

    def allow_update(self, path) -> None:
        """A file the command changes in place by design (``choose-tau --apply``: model.json)."""
        self.allowed.add(real(path))

    def hold(self, tmp, path) -> None:
        old = self.pending.get(str(path))
        if old is not None and old != str(tmp):
            Path(old).unlink(missing_ok=True)
        self.pending[str(path)] = str(tmp)
        from .testpoints import wait_point
        wait_point("output.held")

    def commit(self) -> None:
        """Every held output under its final name, Ctrl-C and SIGTERM held meanwhile."""
        if not self.pending:
            return
        from .testpoints import wait_point
        with _signals_held():
            wait_point("output.committing")
            while self.pending:
                final, tmp = next(iter(self.pending.items()))
                os.replace(tmp, final)
                del self.pending[final]

    def abort(self) -> None:
        for tmp in self.pending.values():
            Path(tmp).unlink(missing_ok=True)
        self.pending.clear()


def _has_record(directory: str, patterns: tuple) -> bool:
    """Whether a file matching one of ``patterns`` (relative paths whose every part may hold
    wildcards: ``*/train_config.json`` is a run's record in any subdirectory) is in
    ``directory``."""
    return any(_matches(Path(directory), Path(pattern).parts) for pattern in patterns)


def _matches(base: Path, parts: tuple) -> bool:
    """Whether ``base`` holds a path whose components match ``parts`` one by one (fnmatch;
    names starting with a dot included, as ``os.listdir`` lists them)."""
    head, rest = parts[0], parts[1:]
    try:
        names = os.listdir(base)
    except OSError:
        return False
    for name in names:
        if not fnmatch.fnmatch(name, head):
            continue
        if not rest or (os.path.isdir(base / name) and _matches(base / name, rest)):
            return True
    return False


@contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM wait until the block ends (a few renames); then the command, being
    done, ends as it would have."""
    import signal
    import threading
    olds = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]
    if threading.current_thread() is not threading.main_thread() or None in olds:
        yield  # not ours to change (another thread; a handler set outside Python: Blender)
        return
    caught = []
    old = {s: signal.signal(s, lambda n, f: caught.append(n))
           for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def guarding(args):
    """Run a command under its guard: held outputs appear when it returns, none on failure."""
    guard = Guard(args)
    GUARDS.append(guard)
    try:
        yield guard
        guard.commit()
    except BaseException:
        guard.abort()
        raise
    finally:
        GUARDS.remove(guard)


def allow_update(path) -> None:
    """See :meth:`Guard.allow_update` (nothing to do outside a command)."""
    if (g := active()) is not None:
        g.allow_update(path)


# --- before the command runs ---------------------------------------------------------------

def where_inputs(flag: str, value, inputs) -> str | None:
    """Why the directory output ``flag value`` may not be written as it is, given the
    command's ``inputs`` (real paths, files or directories): it is one of them, or lies inside
    one (the dataset, model or run the command reads would change under it). The one rule
    of every directory output, checked before any work; a file output may be a new name
    inside an input directory (``choose-tau --model M -o M/tau.json``), never an input."""
    r = real(value)
    for i in inputs:
        if r == i:
            return (f"{flag} {value} is an input of this command; it is never written into, "
                    "even with --force: choose another directory")
        if _inside(r, i):
            return (f"{flag} {value} is inside {i}, an input of this command; it is never "
                    "written into, even with --force: choose a directory outside it")
    return None


def add_inputs(paths, what: str = "an input of this command") -> None:
    """Inputs a command learns of only as it runs (the dataset a run trained on, the model a
    run was initialised from): the running command's directory outputs are checked against
    them by the rule of :func:`where_inputs` (InputError), and its guard keeps them as it
    keeps the inputs it was given. Nothing to do outside a command."""
    g = active()
    if g is None:
        return
    found = [real(p) for p in paths if p and os.path.lexists(p)]
    for spec, value in g.dir_values:
        if (why := where_inputs(spec.flag, value, found)) is not None:
            raise InputError(why.replace("an input of this command", what))
    g.input_files.update(p for p in found if not os.path.isdir(p))
    g.input_dirs.extend(p for p in found if os.path.isdir(p))


def output_problems(args: argparse.Namespace) -> list[str]:
    """Messages for output paths the command must not write to as they are (the first is the
    one shown: one line per refusal)."""
    out = []
    guard = Guard(args)
    inputs = [*guard.input_dirs, *guard.input_files]
    planned: list[tuple[str, Path]] = []
    dirs: list[tuple[str, str, str]] = []  # (real, flag, value) of each directory output
    for o in declared_outputs(args):
        value = getattr(args, o.dest, None)
        if value is None or value == "-":
            continue
        if not str(value).strip():  # Path("") is ".": the working directory, never meant
            out.append(f"{o.flag} {value!r}: an empty name; give a "
                       f"{'file name' if o.kind == FILE else 'directory'}")
            continue
        path = Path(value)
        if o.kind != FILE:
            if (why := where_inputs(o.flag, value, inputs)) is not None:
                out.append(why)
                continue
            other = next((d for d in dirs if _inside(real(value), d[0])
                          or _inside(d[0], real(value))), None)
            if other is not None:
                out.append(f"{other[1]} {other[2]} and {o.flag} {value} are one directory "
                           "or one inside the other; give each output its own directory")
                continue
            dirs.append((real(value), o.flag, str(value)))
        if o.kind == FILE:
            if path.is_dir():
                out.append(f"{o.flag} {value} is a directory; give a file name")
                continue
            if o.suffixes and path.suffix.lower() not in o.suffixes:
                out.append(f"{o.flag} {value}: unsupported format "
                           f"{path.suffix.lower() or '(no suffix)'!r}; accepted: "
                           f"{', '.join(o.suffixes)}")
                continue
            if (blocker := _file_on_the_way(path)) is not None:
                out.append(f"{o.flag} {value}: {blocker} is a file, not a directory")
                continue
        else:
            if path.is_file() or _file_on_the_way(path):
                out.append(f"{o.flag} {value} is a file; give a directory")
                continue
            names = o.files(args) if callable(o.files) else o.files
            if names == ANY and path.is_dir():
                if any(path.iterdir()) and not guard.force:
                    out.append(f"{o.flag} {value} already holds files; choose a new "
                               "directory, or --force to write into it (files of the same "
                               "names are replaced, others kept)")
        planned += o.planned(args)
    seen: dict[str, tuple[str, Path]] = {}
    existing: list[str] = []  # files kept without --force: named in one line
    for label, path in planned:
        key = real(path)
        other = seen.get(key) or next((s for s in seen.values()
                                       if path.exists() and _same_file(s[1], path)), None)
        if other is not None:
            out.append(f"{other[0]} and {label} are the same file; give each output its own "
                       "name")
            continue
        seen[key] = (label, path)
        if os.path.lexists(path) and (message := guard.refusal(path, label)):
            if message.endswith(_EXISTS):
                existing.append(label)
            else:
                out.append(message)
    if existing:
        out.append(f"{', '.join(existing)} already exist{'s' if len(existing) == 1 else ''}"
                   f"{_EXISTS}")
    return out


def _file_on_the_way(path: Path) -> Path | None:
    """The first existing parent of ``path`` that is a file (so nothing can be made below)."""
    for parent in path.absolute().parents:
        if parent.exists():
            return parent if not parent.is_dir() else None
    return None


# --- a directory written whole, then published file by file ------------------------------

@contextmanager
def staged_directory(out):
    """A hidden directory beside ``out`` to write a result into (and read it back); when the
    block ends without error its files are published into ``out`` one by one through the
    guard (``out`` is never removed, files of other names in it are kept); the staging
    directory is removed whatever happens."""
    out = Path(os.path.abspath(out))
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.with_name(f".{out.name}.staging-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        yield staging
        for f in sorted(p for p in staging.rglob("*") if p.is_file() or p.is_symlink()):
            publish(f, out / f.relative_to(staging))
    finally:
        shutil.rmtree(staging, ignore_errors=True)
