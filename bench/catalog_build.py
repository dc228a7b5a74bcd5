"""Time to build the whole built-in catalog from nothing, in a fresh process.

Run: .venv/bin/python bench/catalog_build.py [--repeat 3]
Prints one line per run: wall time of `Catalog()` + every type's mesh, and the totals.
"""

import argparse
import json
import subprocess
import sys

CHILD = r"""
import time, json
t0 = time.perf_counter()
from apcg_core.catalog import Catalog
cat = Catalog(include_user=False)
faces = sum(len(cat.mesh(t).faces) for t in cat)
print(json.dumps({"seconds": time.perf_counter() - t0, "types": len(cat), "faces": faces}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    runs = []
    for _ in range(args.repeat):
        out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                             check=True)
        runs.append(json.loads(out.stdout))
        print(runs[-1])
    best = min(r["seconds"] for r in runs)
    print(f"catalog build from nothing: best {best:.2f} s over {args.repeat} fresh processes "
          f"({runs[0]['types']} types, {runs[0]['faces']} triangles)")


if __name__ == "__main__":
    main()
