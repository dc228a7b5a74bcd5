"""Contact sheet of catalog types: three shaded views per type (matplotlib, imported here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.atomic import atomic_path
from .mesh import Mesh

# (name, horizontal axis, vertical axis, depth axis toward the viewer, sign of depth)
VIEWS = (("top", 0, 1, 2), ("side", 0, 2, 1), ("front", 1, 2, 0))


def _draw(ax, mesh: Mesh, h: int, v: int, d: int, colour) -> None:
    from matplotlib.collections import PolyCollection

    tri = mesh.vertices[mesh.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-30
    facing = n[:, d] > 0  # faces turned toward the viewer on +d
    tri, n = tri[facing], n[facing]
    order = np.argsort(tri[:, :, d].mean(axis=1))  # far first (painter's algorithm)
    tri, n = tri[order], n[order]
    light = np.array([0.3, 0.4, 0.85])
    light /= np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.clip(np.abs(n @ light), 0, 1)
    col = np.clip(np.asarray(colour)[None, :3] * shade[:, None], 0, 1)
    ax.add_collection(PolyCollection(tri[:, :, [h, v]], facecolors=col, edgecolors=col,
                                     linewidths=0.2))
    lo, hi = mesh.bounds[:, [h, v]]
    pad = 0.05 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.axis("off")


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise InputError("drawing needs matplotlib: pip install 'apcg[io]'") from exc
    return plt


def _save(fig, out, dpi: int) -> Path:
    """Write through a temporary name: a PNG under its final name is complete."""
    import matplotlib.pyplot as plt

    out = Path(out)
    with atomic_path(out, ".part" + out.suffix) as tmp:  # matplotlib reads the format there
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out


SHEET_SUFFIXES = (".png", ".pdf", ".svg")


PREVIEW_LABELS = ("top: nose right, left wing up", "side: nose right, top up",
                  "front: seen from ahead, top up")


def three_views(mesh: Mesh, out: str | Path, title: str = "", colour=(0.55, 0.65, 0.85),
                dpi: int = 110) -> Path:
    """One model's top / side / front views in a PNG, labelled with the body axes, to check
    that an imported model's nose, span and up landed where they should."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    for j, (ax, (_, h, v, d)) in enumerate(zip(axes, VIEWS, strict=True)):
        m = mesh if j != 2 else mesh.transformed(np.diag([1.0, -1.0, 1.0]))
        _draw(ax, m, h, v, d, colour)
        ax.set_title(PREVIEW_LABELS[j], fontsize=9)
    ext = mesh.extents
    fig.suptitle(f"{title}  length {ext[0]:.3g} m, span {ext[1]:.3g} m, height {ext[2]:.3g} m",
                 fontsize=10)
    return _save(fig, out, dpi)


def contact_sheet(catalog, names=None, out: str | Path = "sheet.png", columns: int = 6,
                  dpi: int = 70) -> Path:
    """Draw top / side / front views of each type into one PNG; returns its path.

    Top view: nose right, left wing up. Side: nose right, up up. Front: seen from ahead
    (left wing on the right of the picture, as when facing the aircraft)."""
    plt = _pyplot()
    types = [catalog.get(n) for n in names] if names else list(catalog)
    if not types:
        raise InputError("no types to draw")
    rows = -(-len(types) // columns)
    fig = plt.figure(figsize=(columns * 4.2, rows * 1.35))
    gs = fig.add_gridspec(rows, columns * 3, wspace=0.05, hspace=0.35)
    colours = {"aircraft": (0.55, 0.65, 0.85), "drone": (0.85, 0.6, 0.4)}
    for k, t in enumerate(types):
        r, c = divmod(k, columns)
        mesh = catalog.mesh(t)
        for j, (_, h, v, d) in enumerate(VIEWS):
            ax = fig.add_subplot(gs[r, c * 3 + j])
            m = mesh if j != 2 else mesh.transformed(np.diag([1.0, -1.0, 1.0]))
            _draw(ax, m, h, v, d, colours.get(t.kind, (0.6, 0.6, 0.6)))
            if j == 0:
                ax.set_title(f"{t.index}: {t.name} ({t.length_m:g} m)", fontsize=7, loc="left")
    return _save(fig, out, dpi)
