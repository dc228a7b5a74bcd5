"""Draw a point cloud file as the lidar sees it (observation frame, coloured by range) into a PNG.

    .venv/bin/python tools/draw_cloud.py scan.ply -o scan.png [--title TEXT]

For the docs: the README's picture of an imported model's scan was made with it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from apcg_core.io.clouds import read_cloud  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cloud")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--title", default="")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cloud, _ = read_cloud(args.cloud)
    if len(cloud) == 0:
        print(f"{args.cloud}: the cloud is empty; nothing to draw", file=sys.stderr)
        return 2
    x, y, z = cloud.xyz.T
    fig, (front, top) = plt.subplots(1, 2, figsize=(10, 3.6))
    r = cloud.range_m
    # Seen from the lidar: x right, y up (the observation frame looks along +z).
    sc = front.scatter(x, y, c=r, s=3, cmap="viridis")
    front.set(title="seen from the lidar", xlabel="x (m)", ylabel="y (m)", aspect="equal")
    top.scatter(x, z, c=r, s=3, cmap="viridis")
    top.set(title="from above: depth along the line of sight", xlabel="x (m)",
            ylabel="z (m)", aspect="equal")
    fig.colorbar(sc, ax=[front, top], label="range (m)")
    fig.suptitle(args.title or f"{Path(args.cloud).name}: {len(cloud)} points", fontsize=10)
    out = Path(args.output)
    tmp = out.with_name(out.name + ".part.png")
    fig.savefig(tmp, dpi=100, bbox_inches="tight")
    tmp.replace(out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
