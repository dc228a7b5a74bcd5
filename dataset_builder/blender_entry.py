"""Run ``apcg simulate`` / ``apcg dataset ...`` inside a Blender binary, headless:

    blender -b --python-exit-code 1 -P dataset_builder/blender_entry.py -- \\
        dataset build --config demo -o DIR --backend blender

Blender runs this file as a script with its own Python; the project need not be installed into
it (only numpy, which Blender bundles or, for Debian's blender, python3-numpy provides): the
checkout this file sits in is put on the path. Exit status: 0, or 2 for a user error (Blender
exits 1 on an uncaught exception when given --python-exit-code 1).
"""

import os
import sys


def _main() -> int:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if root not in sys.path:
        sys.path.insert(0, root)
    import bpy

    from apcg_core.cli import main
    from dataset_builder.cli import register_dataset, register_simulate

    workers = _workers(argv)
    if workers is not None and workers != "1":
        command = " ".join(a for a in argv[:2] if not a.startswith("-"))
        print(f"apcg {command}: error: --workers {workers} not accepted inside a Blender "
              "binary: use --workers 1; for parallel builds run several `blender -b ... -- "
              "dataset build ... --shard I/N` processes, or `apcg dataset build --workers N` "
              "with the bpy module", file=sys.stderr)
        return 2
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return main(argv, registrars=[register_simulate, register_dataset])


def _workers(argv):
    """The value given to --workers (either spelling), None when not given or given without
    one (the command's own parser then names what is missing)."""
    for i, a in enumerate(argv):
        if a.startswith("--workers="):
            return a.split("=", 1)[1].strip()
        if a == "--workers" and i + 1 < len(argv):
            return argv[i + 1].strip()
    return None


code = _main()
sys.stdout.flush()
if code:
    sys.exit(code)
