"""Standard point clouds in files: PLY (binary), NPZ and LAS, observation frame, metres.

Every format carries the per-point attributes range_m (float64), cell_w and cell_h (centred cell
indices), and, for stacked clouds, sample. Files are written through a ``.part`` file and
renamed, so a file with its final name is complete.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..cloud import PointCloud
from ..errors import InputError

FORMATS = (".ply", ".npz", ".las")
_PLY_PROPS = [("x", "f8"), ("y", "f8"), ("z", "f8"), ("range_m", "f8"), ("cell_w", "i4"),
              ("cell_h", "i4"), ("sample", "i4")]
_PLY_TYPES = {"f8": "double", "i4": "int", "f4": "float", "u1": "uchar", "i2": "short",
              "u2": "ushort", "u4": "uint", "i1": "char"}
_PLY_NAMES = {v: k for k, v in _PLY_TYPES.items()} | {"float64": "f8", "float32": "f4",
                                                       "int32": "i4", "uint8": "u1"}


def _fmt(path) -> str:
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise InputError(f"unsupported point cloud format {ext!r} for {path}; accepted: "
                         f"{', '.join(FORMATS)}")
    return ext


def _replace(tmp: Path, path: Path) -> None:
    os.replace(tmp, path)


def write_cloud(path, cloud: PointCloud, meta: dict | None = None) -> Path:
    """Write ``cloud`` to ``path`` (.ply / .npz / .las); ``meta`` (JSON-able) goes in the header."""
    path = Path(path)
    ext = _fmt(path)
    meta = meta or {}
    tmp = path.with_name(path.name + ".part")
    sample = cloud.sample if cloud.sample is not None else np.zeros(len(cloud), np.int64)
    if ext == ".npz":
        with open(tmp, "wb") as f:
            np.savez(f, xyz=cloud.xyz, range_m=cloud.range_m, cell_w=cloud.cell_w,
                     cell_h=cloud.cell_h, sample=sample, meta=np.array(json.dumps(meta)))
    elif ext == ".ply":
        rec = np.empty(len(cloud), dtype=[(n, "<" + t) for n, t in _PLY_PROPS])
        rec["x"], rec["y"], rec["z"] = cloud.xyz.T
        rec["range_m"], rec["cell_w"], rec["cell_h"] = cloud.range_m, cloud.cell_w, cloud.cell_h
        rec["sample"] = sample
        comment = json.dumps(meta).replace("\n", " ")
        head = ["ply", "format binary_little_endian 1.0",
                "comment APCG standard point cloud: observation frame, metres",
                f"comment meta {comment}", f"element vertex {len(cloud)}"]
        head += [f"property {_PLY_TYPES[t]} {n}" for n, t in _PLY_PROPS] + ["end_header"]
        with open(tmp, "wb") as f:
            f.write(("\n".join(head) + "\n").encode())
            f.write(rec.tobytes())
    else:
        _write_las(tmp, cloud, sample, meta)
    _replace(tmp, path)
    return path


def _write_las(tmp: Path, cloud: PointCloud, sample, meta: dict) -> None:
    try:
        import laspy
    except ImportError as exc:
        raise InputError("LAS files need laspy: pip install 'apcg[io]'") from exc
    header = laspy.LasHeader(point_format=6, version="1.4")
    # LAS stores scaled int32 coordinates: 0.1 mm steps around the cloud's centre.
    centre = cloud.xyz.mean(axis=0) if len(cloud) else np.zeros(3)
    header.offsets = np.round(centre, 3)
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.add_extra_dims([laspy.ExtraBytesParams("range_m", np.float64),
                           laspy.ExtraBytesParams("cell_w", np.int32),
                           laspy.ExtraBytesParams("cell_h", np.int32),
                           laspy.ExtraBytesParams("sample", np.int32)])
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    las.range_m = cloud.range_m
    las.cell_w, las.cell_h, las.sample = cloud.cell_w, cloud.cell_h, sample.astype(np.int32)
    las.header.vlrs.append(laspy.VLR(user_id="APCG", record_id=1, description="meta",
                                     record_data=json.dumps(meta).encode()))
    with open(tmp, "wb") as f:
        las.write(f)


def read_cloud(path) -> tuple[PointCloud, dict]:
    """Read a cloud written by :func:`write_cloud` (PLY also: any binary/ascii PLY with x y z)."""
    path = Path(path)
    ext = _fmt(path)
    if not path.exists():
        raise InputError(f"no such point cloud file: {path}")
    try:
        if ext == ".npz":
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
                n = len(z["xyz"])
                get = {k: (z[k] if k in z.files else None) for k in
                       ("range_m", "cell_w", "cell_h", "sample")}
                xyz = z["xyz"]
        elif ext == ".ply":
            xyz, get, meta = _read_ply(path)
            n = len(xyz)
        else:
            import laspy
            las = laspy.read(path)
            xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], 1)
            n = len(xyz)
            names = set(las.point_format.dimension_names)
            get = {k: (np.asarray(las[k]) if k in names else None)
                   for k in ("range_m", "cell_w", "cell_h", "sample")}
            meta = {}
            for v in las.header.vlrs:
                if v.user_id == "APCG":
                    meta = json.loads(bytes(v.record_data).decode())
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any parse failure is a broken file to the user
        raise InputError(f"cannot read point cloud {path}: {exc}") from exc
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    r = get["range_m"] if get["range_m"] is not None else np.linalg.norm(xyz, axis=1)
    zeros = np.zeros(n, np.int32)
    cloud = PointCloud(xyz, r, get["cell_w"] if get["cell_w"] is not None else zeros,
                       get["cell_h"] if get["cell_h"] is not None else zeros,
                       get["sample"] if get["sample"] is not None else None)
    return cloud, meta


def _read_ply(path: Path):
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path} is not a PLY file")
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt, n, props, meta = None, None, [], {}
    in_vertex = False
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "comment" and len(parts) > 2 and parts[1] == "meta":
            meta = json.loads(line.split("meta", 1)[1])
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list":
                raise InputError(f"{path}: list properties on vertices are not supported")
            props.append((parts[2], _PLY_NAMES.get(parts[1], None)))
    if n is None or any(t is None for _, t in props):
        raise InputError(f"{path}: PLY header lacks a vertex element or uses unknown types")
    names = [p for p, _ in props]
    if fmt == "ascii":
        rows = np.array(data[body_start:].split(), dtype=np.float64)[: n * len(props)]
        rec = rows.reshape(n, len(props))
        col = {p: rec[:, i] for i, p in enumerate(names)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(p, endian + t) for p, t in props])
        if len(data) - body_start < n * dt.itemsize:
            raise InputError(f"{path} is truncated: {n} vertices announced, fewer stored")
        rec = np.frombuffer(data, dtype=dt, count=n, offset=body_start)
        col = {p: rec[p] for p in names}
    if not {"x", "y", "z"} <= set(col):
        raise InputError(f"{path}: vertices have no x, y, z")
    xyz = np.stack([col["x"], col["y"], col["z"]], 1)
    return xyz, {k: col.get(k) for k in ("range_m", "cell_w", "cell_h", "sample")}, meta
