"""Build the Blender add-on: the extension (Blender 4.2+, one zip per platform) and the legacy
add-on zip (older Blender), into dist/.

    python tools/build_addon.py [--out dist] [--blender-ext PATH] [--platforms ...]

The extension bundles its Python dependencies as wheels, as the extensions platform does: the
apcg wheel itself (pure Python: apcg_core and dataset_builder) and onnxruntime for each platform
whose wheel pip can fetch (numpy comes with Blender). It is built and validated with the
extension tool that ships inside the bpy wheel (blender_ext.py). The legacy zip holds the
add-on folder and, under modules/, the pure-Python packages it imports: Blender puts
scripts/addons/modules on sys.path, so nothing edits sys.path at run time.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "blender_addon"
ONNXRUNTIME = "onnxruntime==1.31.1"
# pip platform tag -> Blender platform
PLATFORMS = {"manylinux_2_28_x86_64": "linux-x64", "win_amd64": "windows-x64",
             "macosx_13_0_arm64": "macos-arm64"}


def find_blender_ext() -> Path:
    import importlib.util
    spec = importlib.util.find_spec("bpy")  # locate the wheel without starting Blender
    base = Path(spec.origin).parent if spec and spec.origin else Path(sys.prefix)
    hits = sorted(base.rglob("bl_pkg/cli/blender_ext.py"))
    if not hits:
        raise SystemExit("blender_ext.py not found: install the bpy wheel "
                         "(pip install 'apcg[blender]') or pass --blender-ext")
    return hits[0]


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    print("+", " ".join(map(str, cmd)), flush=True)
    return subprocess.run(list(map(str, cmd)), check=False, **kw)


def stage_extension(stage: Path, platforms: list[str]) -> list[str]:
    """Copies the add-on and its wheels into ``stage``; returns the Blender platforms built."""
    for f in ADDON.iterdir():
        if f.suffix in (".py", ".toml"):
            shutil.copy(f, stage / f.name)
    wheels = stage / "wheels"
    wheels.mkdir()
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
              "-q", "-w", wheels, ROOT])
    if r.returncode:
        raise SystemExit("building the apcg wheel failed")
    got = []
    for tag in platforms:
        r = _run([sys.executable, "-m", "pip", "download", ONNXRUNTIME, "--no-deps", "-q",
                  "--only-binary=:all:", "--python-version", "3.11", "--platform", tag,
                  "-d", wheels])
        if r.returncode == 0:
            got.append(PLATFORMS[tag])
        else:
            print(f"warning: no {ONNXRUNTIME} wheel for {tag} (offline?): that platform's "
                  "package is not built", file=sys.stderr)
    if not got:
        raise SystemExit("no onnxruntime wheel could be fetched for any platform")
    names = sorted(p.name for p in wheels.glob("*.whl"))
    manifest = (stage / "blender_manifest.toml").read_text()
    generated = "platforms = [{}]\nwheels = [\n{}]\n\n".format(
        ", ".join(f'"{p}"' for p in got), "".join(f'  "./wheels/{n}",\n' for n in names))
    # top-level keys go before the first table
    manifest = manifest.replace("[permissions]", generated + "[permissions]", 1)
    (stage / "blender_manifest.toml").write_text(manifest)
    return got


def build_legacy(out: Path, version: str) -> Path:
    path = out / f"apcg-legacy-{version}.zip"
    tmp = path.with_suffix(".zip.part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(ADDON.glob("*.py")):
            z.write(f, f"apcg_blender/{f.name}")
        for pkg in ("apcg_core", "dataset_builder"):
            for f in sorted((ROOT / pkg).rglob("*")):
                if f.is_file() and "__pycache__" not in f.parts and f.suffix != ".pyc":
                    # addons/modules is on Blender's sys.path and is not scanned for add-ons
                    z.write(f, "modules/" + f.relative_to(ROOT).as_posix())
    tmp.replace(path)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "dist"))
    ap.add_argument("--blender-ext", help="path of blender_ext.py (default: the bpy wheel's)")
    ap.add_argument("--platforms", nargs="+", default=list(PLATFORMS), choices=list(PLATFORMS))
    ap.add_argument("--legacy-only", action="store_true",
                    help="only the legacy add-on zip (no bpy wheel or pip needed)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    version = next(line.split('"')[1] for line in (ADDON / "blender_manifest.toml")
                   .read_text().splitlines() if line.startswith("version"))
    if args.legacy_only:
        print("built:", build_legacy(out, version))
        return 0
    ext = Path(args.blender_ext) if args.blender_ext else find_blender_ext()
    for old in out.glob(f"apcg-{version}-*.zip"):  # no stale platform packages in the list
        old.unlink()
    with tempfile.TemporaryDirectory() as tmp:
        stage = Path(tmp) / "apcg"
        stage.mkdir()
        platforms = stage_extension(stage, args.platforms)
        r = _run([sys.executable, ext, "build", "--source-dir", stage, "--output-dir", out,
                  "--split-platforms"])
        if r.returncode:
            raise SystemExit("blender_ext.py build failed")
    built = sorted(out.glob(f"apcg-{version}-*.zip"))
    for z in built:
        r = _run([sys.executable, ext, "validate", z])
        if r.returncode:
            raise SystemExit(f"blender_ext.py validate failed for {z}")
    legacy = build_legacy(out, version)
    print("built:", *[str(p) for p in built], str(legacy), sep="\n  ")
    print("platforms:", ", ".join(platforms))
    return 0


if __name__ == "__main__":
    sys.exit(main())
