"""How much of the recognition lost on the generator's photon clouds is the photon path's, and
how much the network's (issue 35)?

``apcg benchmark recognize`` with one more training source, ``exact-path``: the exact
simulator's own clouds drawn at the 3-times finer lidar (embree, one ray per finer cell,
unquantized) and sent through the path a generated cloud's photons take
(``apcg_core.sensor.generated.sub_rays_of_fine_cloud``: 3 x 3 sub-reads, the incidence off the
range slope), beside any ``--source``. Perfect geometry through the generator's path: its TSTR
is what the path alone costs. Everything else is the benchmark's own (arguments passed on).

    .venv/bin/python bench/recognize_photon_path.py --source apcg_core/models/default \
        --sensor 1550nm-day --threads 1 -o /tmp/rec_path_day
"""

from __future__ import annotations

import sys
import types as _types

import numpy as np

from apcg_core.cloud import PointCloud
from training import recognize as R

EXACT_PATH = "exact-path"


class ExactAtAnyLidar:
    """The exact simulator behind the few parts of a model the photon path uses: it draws at
    any lidar (``ANY_LIDAR``), the finer one included, unquantized when asked."""

    ANY_LIDAR = True
    family = EXACT_PATH

    def __init__(self, lidar) -> None:
        self.lidar = lidar
        self.quantize = True
        self.directory = EXACT_PATH

    def conditions(self, names, rows):
        return _types.SimpleNamespace(names=list(names), rows=np.asarray(rows, np.float64))

    def generate(self, cond, count: int = 1, seed: int = 0):
        from apcg_core.catalog import default_catalog
        from dataset_builder.simulate import Simulator
        cat = default_catalog()
        table = np.concatenate([np.zeros((len(cond.rows), 1)), cond.rows], axis=1)
        names = np.asarray(cond.names)
        parts = []
        with Simulator("embree", self.lidar, quantize=self.quantize) as sim:
            for name in dict.fromkeys(cond.names):
                sel = np.flatnonzero(names == name)
                c = sim.simulate_type(cat, name, table[sel]).cloud
                parts.append((sel[c.sample], c))
        sample = np.concatenate([p[0] for p in parts])
        order = np.argsort(sample, kind="stable")
        cloud = PointCloud(*(np.concatenate([getattr(p[1], f) for p in parts])[order]
                             for f in ("xyz", "range_m", "cell_w", "cell_h")), sample[order])
        return _types.SimpleNamespace(cloud=cloud, table=table, conditions=cond)


class Source(R.Source):
    def __init__(self, name, sensor=None, lidar=None, warn=None):
        if name != EXACT_PATH:
            super().__init__(name, sensor, lidar, warn)
            return
        super().__init__("exact", sensor, lidar, warn)
        self.name = EXACT_PATH
        self.model = ExactAtAnyLidar(self.lidar)

    def record(self) -> dict:
        if self.name != EXACT_PATH:
            return super().record()
        return {"source": EXACT_PATH, "kind": "exact through the generated photon path",
                "sensor": None if self.sensor is None else self.sensor.to_dict()}


def main() -> int:
    R.Source = Source  # the benchmark builds its sources by this name
    from apcg_core.cli import main as apcg
    return apcg(["benchmark", "recognize", "--source", EXACT_PATH, *sys.argv[1:]])


if __name__ == "__main__":
    sys.exit(main())
