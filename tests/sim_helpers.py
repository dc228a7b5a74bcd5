"""Meshes with closed-form geometry for the simulator tests (body frame, metres)."""

import numpy as np

from apcg_core.catalog.mesh import Mesh


def grid_mesh(points: np.ndarray) -> Mesh:
    """Triangulate a (nu, nv, 3) grid of points; each quad split along its (i,j)-(i+1,j+1)
    diagonal, both triangles wound the same way."""
    nu, nv = points.shape[:2]
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(points.reshape(-1, 3), faces)


def rectangle(half_y: float, half_z: float) -> Mesh:
    """A flat rectangle in the body plane x = 0 (facing the lidar at zero attitude)."""
    y, z = np.meshgrid([-half_y, half_y], [-half_z, half_z], indexing="ij")
    return grid_mesh(np.stack([np.zeros_like(y), y, z], -1))


def uv_sphere(radius: float, n_lon: int, n_lat: int) -> Mesh:
    """A closed UV sphere about the origin."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ring = radius * np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
    verts = np.concatenate([ring.reshape(-1, 3), [[0, 0, -radius], [0, 0, radius]]])
    n_r = len(lat)
    south, north = n_r * n_lon, n_r * n_lon + 1
    faces = []
    for i in range(n_r - 1):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            faces += [[a, b, d], [a, d, c]]
    for j in range(n_lon):
        faces.append([south, (j + 1) % n_lon, j])
        top = (n_r - 1) * n_lon
        faces.append([north, top + j, top + (j + 1) % n_lon])
    return Mesh(verts, np.array(faces))
