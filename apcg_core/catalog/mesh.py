"""A triangle mesh in plain numpy, with the checks the catalog promises (closed, wound outward,
no degenerate faces) and the volume centroid used as the centre of mass."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass
class MeshReport:
    n_vertices: int
    n_faces: int
    watertight: bool  # every edge shared by exactly two faces
    winding_consistent: bool  # neighbouring faces traverse their shared edge in opposite order
    n_degenerate: int  # faces with (near) zero area
    volume: float  # signed; > 0 when wound outward
    n_bodies: int  # connected components (by shared vertices)


@dataclass
class Mesh:
    vertices: np.ndarray  # (V, 3) float64, metres
    faces: np.ndarray  # (F, 3) int64, counter-clockwise seen from outside

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise InputError("mesh faces index vertices that do not exist")

    # --- measures --------------------------------------------------------------------------
    def _tetra(self):
        """The faces' corners relative to the bounding-box centre ``c``, and the signed
        volume of each face's tetrahedron against ``c``: a model stored kilometres from its
        file's origin (georeferenced) loses no digits to the offset (against the file's origin,
        1e6 m put the centroid 540 m off)."""
        c = (self.vertices.min(axis=0) + self.vertices.max(axis=0)) / 2 \
            if len(self.vertices) else np.zeros(3)
        v0, v1, v2 = (self.vertices[self.faces[:, i]] - c for i in range(3))
        return c, v0, v1, v2, np.einsum("ij,ij->i", v0, np.cross(v1, v2)) / 6.0

    @property
    def volume(self) -> float:
        return float(self._tetra()[4].sum())

    @property
    def centroid(self) -> np.ndarray:
        """Volume centroid (signed tetrahedra against the bounding-box centre); closed meshes
        only."""
        c, v0, v1, v2, vol = self._tetra()
        total = vol.sum()
        if abs(total) < 1e-18:
            raise InputError("the mesh encloses no volume; use the bounding-box centre")
        return c + ((v0 + v1 + v2) * vol[:, None]).sum(axis=0) / (4.0 * total)

    @property
    def face_areas(self) -> np.ndarray:
        v0, v1, v2 = (self.vertices[self.faces[:, i]] for i in range(3))
        return 0.5 * np.linalg.norm(np.cross(v1 - v0, v2 - v0), axis=1)

    @property
    def bounds(self) -> np.ndarray:
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extents(self) -> np.ndarray:
        b = self.bounds
        return b[1] - b[0]

    # --- transforms ------------------------------------------------------------------------
    def transformed(self, matrix=None, offset=None) -> Mesh:
        """x -> matrix @ x + offset; faces are flipped when the matrix mirrors (det < 0)."""
        v = self.vertices
        f = self.faces
        if matrix is not None:
            m = np.asarray(matrix, dtype=np.float64)
            v = v @ m.T
            if np.linalg.det(m) < 0:
                f = f[:, ::-1]
        if offset is not None:
            v = v + np.asarray(offset, dtype=np.float64)
        return Mesh(v, f.copy())

    def flipped(self) -> Mesh:
        return Mesh(self.vertices.copy(), self.faces[:, ::-1].copy())

    def outward(self) -> Mesh:
        """Same surface, wound so that the enclosed volume is positive."""
        return self if self.volume >= 0 else self.flipped()

    def bodies_outward(self) -> tuple[Mesh, int]:
        """Same surface, each body (connected part) wound so that its own volume is positive,
        and how many were turned: a closed part wound inward (a separate nacelle or pod the
        modeller flipped) would otherwise subtract its volume from the model's and move its
        centroid."""
        label = self.vertex_labels()
        if not len(self.faces):
            return self, 0
        body = label[self.faces[:, 0]]
        _, _, _, _, vol = self._tetra()
        per_body = np.bincount(np.unique(body, return_inverse=True)[1], weights=vol)
        ids = np.unique(body)
        inward = ids[per_body < 0]
        if not len(inward):
            return self, 0
        faces = self.faces.copy()
        turn = np.isin(body, inward)
        faces[turn] = faces[turn][:, ::-1]
        return Mesh(self.vertices.copy(), faces), int(len(inward))

    @staticmethod
    def concat(meshes: list[Mesh]) -> Mesh:
        verts, faces, n = [], [], 0
        for m in meshes:
            verts.append(m.vertices)
            faces.append(m.faces + n)
            n += len(m.vertices)
        return Mesh(np.concatenate(verts), np.concatenate(faces))

    # --- checks ----------------------------------------------------------------------------
    def is_watertight(self) -> bool:
        """Every edge (either direction) in exactly two faces."""
        f = self.faces
        if not len(f):
            return False
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(e[:, 0] * len(self.vertices) + e[:, 1], return_counts=True)
        return bool((counts == 2).all())

    def report(self, area_eps: float = 1e-12) -> MeshReport:
        f = self.faces
        nv = len(self.vertices)
        directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        key = directed[:, 0] * nv + directed[:, 1]
        rev = directed[:, 1] * nv + directed[:, 0]
        uk, counts = np.unique(key, return_counts=True)
        undirected = np.minimum(key, rev)
        _, ucounts = np.unique(undirected, return_counts=True)
        watertight = bool(len(f)) and bool((ucounts == 2).all())
        consistent = watertight and bool((counts == 1).all()) and bool(
            np.isin(rev, uk, assume_unique=False).all())
        scale = max(float(np.max(self.extents)) if nv else 1.0, 1e-9)  # the model's size
        degenerate = int((self.face_areas <= area_eps * scale * scale).sum())
        return MeshReport(nv, len(f), watertight, consistent, degenerate,
                          self.volume if len(f) else 0.0, self.n_bodies())

    def n_bodies(self) -> int:
        """Connected components over shared vertex indices."""
        if len(self.vertices) == 0:
            return 0
        label = self.vertex_labels()
        used = np.unique(self.faces)
        return int(len(np.unique(label[used])))

    def vertex_labels(self) -> np.ndarray:
        """Per vertex, the smallest vertex index of its connected component (union-find over
        shared vertex indices, vectorised passes)."""
        nv = len(self.vertices)
        label = np.arange(nv)
        edges = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]]])
        while True:
            lo = np.minimum(label[edges[:, 0]], label[edges[:, 1]])
            new = label.copy()
            np.minimum.at(new, edges[:, 0], lo)
            np.minimum.at(new, edges[:, 1], lo)
            new = new[new]  # pointer jumping
            if np.array_equal(new, label):
                break
            label = new
        return label


def sample_surface(mesh: Mesh, n: int, seed: int = 0, return_faces: bool = False):
    """n points uniformly on the surface (faces chosen by area, uniform barycentrics);
    with ``return_faces`` also the face each point lies on."""
    rng = np.random.default_rng(seed)
    areas = mesh.face_areas
    total = float(areas.sum()) if len(areas) else 0.0
    if not (np.isfinite(total) and total > 0):
        raise InputError(f"the mesh's {len(areas)} faces have {'no' if total == 0 else 'no finite'}"
                         " area (every face degenerate, or vertices not finite): a lidar "
                         "would see nothing of it")
    face = rng.choice(len(areas), size=n, p=areas / total)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = mesh.vertices[mesh.faces[face]]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return (pts, face) if return_faces else pts
