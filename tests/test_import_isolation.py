"""apcg_core must import with numpy alone: it runs inside Blender's bundled Python."""

import subprocess
import sys

BLOCKED = ["torch", "trimesh", "embreex", "bpy", "mathutils", "scipy", "matplotlib",
           "onnxruntime", "laspy", "tqdm", "dataset_builder", "training", "blender_addon"]

SCRIPT = r"""
import importlib, pkgutil, sys
BLOCKED = %r

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"blocked for this test: {name}")
        return None

sys.meta_path.insert(0, Block())
import apcg_core
# apcg_core.nn is the torch part of the core (DESIGN: "nn/ ... import torch"); everything
# else, the generation pipeline included, must load without it.
mods = [m.name for m in pkgutil.walk_packages(apcg_core.__path__, "apcg_core.")
        if not m.name.startswith("apcg_core.nn")]
for m in mods:
    importlib.import_module(m)
loaded = sorted(n for n in sys.modules if n.split(".")[0] in BLOCKED)
assert not loaded, loaded
print(len(mods))
"""


def test_apcg_core_imports_with_numpy_alone():
    out = subprocess.run([sys.executable, "-c", SCRIPT % BLOCKED], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) >= 12  # every module of the package was imported


def test_the_block_really_blocks():
    # the guard itself must be able to fail: importing a blocked module inside it errors
    script = SCRIPT % BLOCKED + "\nimport torch\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode != 0 and "blocked for this test: torch" in out.stderr


# The heavy packages a command may need, loaded by the command's run, never by the parser:
# building `apcg`'s parser (every installed subcommand registered) must load none of them,
# or every command, `apcg --help` included, pays their start-up (torch alone ~1.3 s here).
HEAVY = ["torch", "onnxruntime", "trimesh", "embreex", "bpy", "scipy", "matplotlib", "numba",
         "dask", "onnx", "tensorboard"]

PARSER_SCRIPT = r"""
import sys
from apcg_core.cli import build_parser
parser = build_parser()
names = sorted(parser._subparsers._group_actions[0].choices)
loaded = sorted({n.split(".")[0] for n in sys.modules} & set(%r))
print(len(names), " ".join(loaded))
"""


def test_building_the_command_line_loads_no_heavy_package():
    out = subprocess.run([sys.executable, "-c", PARSER_SCRIPT % HEAVY], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    n, _, loaded = out.stdout.strip().partition(" ")
    assert int(n) >= 15  # the installed subcommands were registered
    assert loaded == "", f"building the parser loaded {loaded}"
