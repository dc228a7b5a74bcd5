"""Every file a bench writes goes through bench/bench_output.py (atomic: a temporary beside the
final name, renamed when complete; a user-named output refused before any work unless --force).

``test_every_bench_writes_through_bench_output`` reads every bench/*.py with ``ast`` and names
file:line of any direct write (``.write_text(``, ``.write_bytes(``, ``savefig(``, ``np.save*``,
``json.dump(``, ``open(`` with a write mode, ...) outside bench/bench_output.py, so a new bench,
or a new output of an old one, cannot bypass it. The finder is itself checked on a source that
holds every kind of write it knows (``test_the_finder_sees_every_kind_of_write``)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
HELPER = "bench_output.py"

# Calls that write a file whatever they are called on (a Path, a figure, an array, a frame).
WRITING_METHODS = {"write_text", "write_bytes", "savefig", "tofile", "to_csv"}
# Module functions that write a file (the module as imported, aliases resolved).
WRITING_FUNCTIONS = {"numpy.save", "numpy.savez", "numpy.savez_compressed", "numpy.savetxt",
                     "json.dump", "pickle.dump", "torch.save", "shutil.copy", "shutil.copy2",
                     "shutil.copyfile", "shutil.copytree", "matplotlib.pyplot.savefig"}
# open(path, mode) of these modules; Path(...).open(mode) otherwise.
OPEN_MODULES = {"builtins", "io", "codecs", "gzip", "bz2", "lzma", "tarfile"}
OS_WRITE_FLAGS = {"O_WRONLY", "O_RDWR", "O_CREAT", "O_APPEND", "O_TRUNC"}


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Local name -> the dotted name it was imported as (``np`` -> ``numpy``)."""
    names: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                names[a.asname or a.name.split(".")[0]] = a.name if a.asname else \
                    a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
    return names


def _dotted(func: ast.expr, aliases: dict[str, str]) -> str | None:
    parts = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if not isinstance(func, ast.Name):
        return None
    parts.append(aliases.get(func.id, "builtins." + func.id if func.id == "open" else func.id))
    return ".".join(reversed(parts))


def _arg(call: ast.Call, index: int, keyword: str):
    for kw in call.keywords:
        if kw.arg == keyword:
            return kw.value
    return call.args[index] if len(call.args) > index else None


def _writing_mode(mode) -> bool:
    """An open mode that may write: a literal with w, a, x or +, or one not known here."""
    if mode is None:
        return False
    if isinstance(mode, ast.Constant) and isinstance(mode.value, str):
        return any(c in mode.value for c in "wax+")
    return True


def _kernel_control(path) -> bool:
    """A literal /proc/ path (``/proc/self/clear_refs``): the kernel's control, not a file a
    bench makes; there is nothing to make atomic and no rename into /proc."""
    return isinstance(path, ast.Constant) and str(path.value).startswith("/proc/")


def direct_writes(source: str, filename: str = "<source>") -> list[tuple[int, str]]:
    """(line, what) of every call in ``source`` that writes a file itself."""
    tree = ast.parse(source, filename)
    aliases = _aliases(tree)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = _dotted(func, aliases) or ""
        attr = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        what = None
        if name in WRITING_FUNCTIONS:
            what = name
        elif isinstance(func, ast.Attribute) and attr in WRITING_METHODS:
            what = f".{attr}("
        elif attr == "savefig":
            what = "savefig("
        elif name == "os.open":
            flags = [n.attr if isinstance(n, ast.Attribute) else n.id
                     for n in ast.walk(_arg(node, 1, "flags") or ast.Constant(None))
                     if isinstance(n, ast.Attribute | ast.Name)]
            # writing flags, or none known here (a variable): taken as a write
            if set(flags) & OS_WRITE_FLAGS or not any(f.startswith("O_") for f in flags):
                what = "os.open( for writing"
        elif attr == "open":
            module = name.rsplit(".", 1)[0] if "." in name else ""
            if module in OPEN_MODULES or name == "builtins.open":
                path, mode = _arg(node, 0, "file"), _arg(node, 1, "mode")
            else:  # Path.open(mode)
                path, mode = None, _arg(node, 0, "mode")
            if _writing_mode(mode) and not _kernel_control(path):
                what = "open( with a write mode"
        if what:
            found.append((node.lineno, what))
    return sorted(found)


def bench_writes() -> list[str]:
    """``bench/NAME.py:LINE: what`` of every direct write in a bench but bench_output.py."""
    out = []
    for path in sorted(BENCH.glob("*.py")):
        if path.name == HELPER:
            continue
        for line, what in direct_writes(path.read_text(), str(path)):
            out.append(f"{path.relative_to(ROOT)}:{line}: {what}")
    return out


def test_every_bench_writes_through_bench_output():
    offenders = bench_writes()
    assert not offenders, ("these benches write a file themselves; use bench_output.write_text / "
                           "save_figure / emit / append_line (and refuse before any work):\n"
                           + "\n".join(offenders))


def test_the_finder_sees_every_kind_of_write():
    source = """
import json, pickle, shutil, os
import numpy as np
import matplotlib.pyplot as plt
from pathlib import Path
from numpy import savez as keep
p = Path("x")
p.write_text("a")
p.write_bytes(b"a")
fig.savefig("a.png")
plt.savefig("a.png")
np.save("a.npy", x)
keep("a.npz", x=x)
np.savetxt("a.txt", x)
json.dump({}, f)
pickle.dump({}, f)
open("a", "w")
open("a", mode="ab")
open("a", "r+")
open("a", m)
p.open("w")
shutil.copy("a", "b")
x.tofile("a")
os.open("a", os.O_WRONLY | os.O_CREAT)
"""
    lines = [line for line, _ in direct_writes(source)]
    assert lines == list(range(8, 25)), direct_writes(source)
    harmless = """
import json
from pathlib import Path
json.dumps({})
open("a")
open("a", "rb")
Path("a").open()
Path("a").read_text()
open("/proc/self/clear_refs", "w")
fig.savefig_later = 1
"""
    assert direct_writes(harmless) == []


def test_save_figure_writes_a_complete_picture_and_leaves_no_temporary(tmp_path, monkeypatch):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    monkeypatch.syspath_prepend(str(BENCH))
    from bench_output import save_figure
    fig, ax = plt.subplots(figsize=(2, 2))
    ax.plot([0, 1], [1, 0])
    png, svg = tmp_path / "sub" / "fig.png", tmp_path / "fig.svg"
    save_figure(fig, png, dpi=50)
    save_figure(fig, svg)  # the format from the final name's suffix, as savefig infers it
    assert png.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert b"<svg" in svg.read_bytes()[:1000]
    png.write_bytes(b"old")
    save_figure(fig, png)  # replaced
    assert png.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["fig.png", "fig.svg"]

    def fails(path, **kw):  # a picture broken off half-written (a full disk, Ctrl-C)
        Path(path).write_bytes(b"\x89PNG half")
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(fig, "savefig", fails)
    with pytest.raises(OSError):
        save_figure(fig, tmp_path / "broken.png")
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["fig.png", "fig.svg"]
    plt.close(fig)


def _bench(args, cwd):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)


def test_a_bench_refuses_an_existing_output_before_any_work(tmp_path):
    """photons_generated.py with OUT/photons_generated.json there: exit 2, one line naming it,
    the file kept (the refusal comes before the model is loaded: no work)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "photons_generated.json").write_text("kept\n")
    p = _bench([str(BENCH / "photons_generated.py"), "-o", str(out), "--per-band", "1",
                "--sensors", "1550nm-day"], tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip() == (f"photons_generated.py: {out / 'photons_generated.json'} exists;"
                                " --force replaces it")
    assert (out / "photons_generated.json").read_text() == "kept\n"
    assert sorted(x.name for x in out.iterdir()) == ["photons_generated.json"]


@pytest.mark.parametrize("bench,args,existing", [
    ("speed_error.py", ["--data", "no-data", "--plot", "{tmp}/plot.png"], "plot.png"),
    ("speed_error.py", ["--data", "no-data", "--markdown", "{tmp}/t.md"], "t.md"),
    ("train_memory.py", ["--data", "no-data", "--plot", "{tmp}/plot.png"], "plot.png"),
    ("recognize_clouds.py", ["--plot", "{tmp}/plot.png"], "plot.png"),
    ("plus_ablation.py", ["--data", "no-data", "-o", "{tmp}"], "ablation.json"),
    ("lidar_heldout.py", ["-o", "{tmp}", "--work", "{tmp}/work"], "heldout.md"),
])
def test_each_bench_refuses_an_existing_output(tmp_path, bench, args, existing):
    """Each bench asked for a file beside its JSON refuses an existing one before any work
    (its --data here does not exist: reaching the work would fail otherwise)."""
    out = tmp_path / existing
    out.write_bytes(b"kept")
    p = _bench([str(BENCH / bench), *(a.format(tmp=tmp_path) for a in args)], tmp_path)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip() == f"{bench}: {out} exists; --force replaces it"
    assert out.read_bytes() == b"kept"
    assert sorted(x.name for x in tmp_path.iterdir()) == [existing]


def test_refuse_never_replaces_an_input(tmp_path):
    """refuse: an output that is one of the inputs stops the run even with --force."""
    same = tmp_path / "data.json"
    same.write_text("{}")
    code = ("import sys; sys.path.insert(0, sys.argv[1]); from bench_output import refuse; "
            "refuse([sys.argv[2]], True, [sys.argv[2]]); print('went on')")
    p = _bench(["-c", code, str(BENCH), str(same)], tmp_path)
    assert p.returncode == 2 and "went on" not in p.stdout
    assert p.stderr.strip() == f"-c: {same}: is also an input of this run; it is never replaced"
