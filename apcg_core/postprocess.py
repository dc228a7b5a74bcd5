"""Optional post-processing of standard clouds (SPEC section 8). Off by default; each step is
seeded and returns a new cloud.
"""

from __future__ import annotations

import numpy as np

from .cloud import PointCloud
from .frames import spherical_to_cartesian
from .lidar import LidarParams


def cell_jitter(cloud: PointCloud, elevation, lidar: LidarParams, seed: int = 0) -> PointCloud:
    """Each point moved uniformly within its resolution cell: azimuth and elevation within the
    cell's angular extent, range within its time bin (the paper's Fig. 19 "noised" clouds).

    ``elevation`` is beta0, one value, or one per sample when the cloud is a stacked batch."""
    rng = np.random.default_rng(seed)
    n = len(cloud)
    beta0 = np.asarray(elevation, dtype=np.float64)
    if beta0.ndim and cloud.sample is not None:
        beta0 = beta0[cloud.sample]
    alpha, beta = lidar.cell_centre_angles(cloud.cell_w, cloud.cell_h, beta0)
    alpha = alpha + (rng.random(n) - 0.5) * lidar.r_alpha
    beta = beta + (rng.random(n) - 0.5) * lidar.r_beta
    r = cloud.range_m + (rng.random(n) - 0.5) * lidar.r_r
    return PointCloud(spherical_to_cartesian(alpha, beta, r), r, cloud.cell_w, cloud.cell_h,
                      cloud.sample)
