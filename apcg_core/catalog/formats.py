"""Model files in: which reader takes which suffix, and what the file says of its unit and axes.

One table, :data:`FORMATS`. OFF has our own reader (ModelNet's files break others); OBJ, STL,
PLY, glTF and COLLADA go through trimesh (COLLADA with pycollada), in this process; FBX,
.blend, USD and Alembic go through Blender's own importers in a separate Blender process
(``blender_import.py``): the bpy module when this Python has it, else ``$APCG_BLENDER`` or a
``blender`` on PATH. Each reader returns the mesh as the file stores it, in file units and file
axes, with the unit and axes the file declares (None where it declares none).
"""

from __future__ import annotations

import fnmatch
import importlib.util
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .mesh import Mesh
from .polygons import triangulate_polygons, wrong_fans


@dataclass
class RawModel:
    """A file's surfaces as stored, with what the file declares."""

    mesh: Mesh
    unit_m: float | None = None  # metres per file unit, where the file declares it
    unit_note: str = "not declared by the file"
    up: str | None = None  # the axis the file declares as up (an AXES key)
    forward: str | None = None
    objects: list[str] = field(default_factory=list)  # the objects taken
    skipped: list[str] = field(default_factory=list)  # left out, with why
    # the largest coordinate the file stores as a 32-bit float (binary STL, glTF, PLY float),
    # None where it stores more digits: far from the file's origin float32 loses the shape
    float32_max: float | None = None
    stored_max: float = 0.0  # the largest coordinate as stored (before node transforms)


@dataclass(frozen=True)
class Format:
    name: str
    suffixes: tuple[str, ...]
    via: str  # what reads it, for the user
    read: object  # callable(path: Path, patterns: list[str]) -> RawModel
    # callable(path: Path) -> None: refuses a file whose structure is not whole (cut short,
    # a face naming a vertex the file lacks) before the reader, which may accept it quietly
    check: object = None


def _trimesh():
    try:
        import trimesh
    except ImportError as exc:
        raise InputError("importing and exporting models needs trimesh: "
                         "pip install 'apcg[sim]'") from exc
    return trimesh


def _match(name: str, patterns: list[str]) -> bool:
    return not patterns or any(fnmatch.fnmatchcase(name, p) for p in patterns)


def read_off(path: Path, patterns=()) -> RawModel:
    """ModelNet-tolerant OFF reader (polygons are triangulated in their plane:
    :func:`triangulate_polygons`)."""
    text = path.read_bytes().decode("utf-8", errors="replace").replace("\r", "")
    tokens_lines = [ln.split("#")[0].strip() for ln in text.split("\n")]
    lines = [ln for ln in tokens_lines if ln]
    if not lines or not lines[0].upper().startswith("OFF"):
        raise InputError(f"{path}: not an OFF file (the first line does not start with 'OFF')")
    head = lines[0][3:].split()  # "OFF490 518 0" keeps its counts on the first line
    body = lines[1:]
    if not head:
        head, body = body[0].split(), body[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
    except (ValueError, IndexError):
        raise InputError(f"{path}: corrupt OFF file (its counts line {' '.join(head)!r} is "
                         "not 'VERTICES FACES EDGES')") from None
    if len(body) < nv + nf:
        held_v, held_f = min(len(body), nv), max(0, len(body) - nv)
        raise InputError(f"{path}: the header declares {nv} vertices and {nf} faces, the file "
                         f"holds {held_v} and {held_f} (truncated: the file is cut short)")
    try:
        verts = np.array([ln.split()[:3] for ln in body[:nv]], dtype=np.float64)
        if verts.shape != (nv, 3):
            raise ValueError("a vertex line holds fewer than 3 coordinates")
        polys = []
        for ln in body[nv:nv + nf]:
            idx = [int(v) for v in ln.split()]
            k = idx[0]
            poly = idx[1:1 + k]
            if len(poly) < k:
                raise ValueError(f"the face line {ln!r} holds fewer than its {k} indices")
            if k >= 3:
                polys.append(poly)
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: corrupt OFF file ({exc})") from exc
    if not polys:
        raise InputError(f"{path}: corrupt OFF file (its {nf} faces hold no triangle)")
    check_indices(np.array([i for p in polys for i in p], np.int64), nv, path, base=0)
    faces = triangulate_polygons(verts, polys)
    return RawModel(Mesh(verts, faces), objects=[path.stem])


def check_indices(faces: np.ndarray, n_vertices: int, path, base: int = 1,
                  where: str = "") -> None:
    """Refuse a face that names a vertex the file does not hold, in the file's own numbering
    (``base``: 1 for OBJ's, 0 for OFF's and PLY's)."""
    faces = np.asarray(faces)
    if faces.size == 0:
        return
    bad = (faces < 0) | (faces >= n_vertices)
    if bad.any():
        k = int(faces.ravel()[np.argmax(bad.ravel())])
        raise InputError(f"{path}: a face{where} refers to vertex {k + base}, but the file "
                         f"holds {n_vertices} vertices (numbered {base}..{n_vertices - 1 + base})"
                         )


_TRUNCATED = "truncated: the file is cut short"


def check_obj(path: Path) -> None:
    """An OBJ's ``v`` and ``f`` lines whole: a vertex has 3 numbers, a face 3 or more vertex
    numbers, each naming a vertex the file holds (negative: counted back from the last one
    read); a line that breaks off where the file ends is named as truncation."""
    data = path.read_bytes()
    lines = data.decode("utf-8", errors="replace").split("\n")
    ends_cut = not data.endswith(b"\n")
    n_v = 0
    late = []  # (line number, index) of positive indices beyond the vertices read so far
    for no, line in enumerate(lines, start=1):
        tokens = line.split("#", 1)[0].split()
        if not tokens or tokens[0] not in ("v", "f"):
            continue
        last = no == len(lines) and ends_cut

        def bad(why, no=no, line=line, last=last):
            if last:
                return InputError(f"{path}: the file ends in the middle of line {no} "
                                  f"({line.strip()[:60]!r}: {why}); {_TRUNCATED}")
            return InputError(f"{path}, line {no}: {line.strip()[:60]!r}: {why}")
        if tokens[0] == "v":
            try:
                [float(t) for t in tokens[1:4]]
            except ValueError:
                raise bad("a vertex coordinate is not a number") from None
            if len(tokens) < 4:
                raise bad(f"a vertex with {len(tokens) - 1} coordinates (it needs 3)")
            n_v += 1
            continue
        if len(tokens) < 4:
            raise bad(f"a face with {len(tokens) - 1} vertices (a face needs 3 or more)")
        for t in tokens[1:]:
            try:
                k = int(t.split("/", 1)[0])
            except ValueError:
                raise bad(f"{t!r} is not a vertex number") from None
            if k == 0 or -k > n_v:
                raise bad(f"vertex {k} does not exist (the file has {n_v} vertices before "
                          "this line; numbers start at 1, negative ones count back)")
            if k > n_v:
                late.append((no, k))
    if not any(t[:1] == ["f"] for t in (ln.split("#", 1)[0].split()[:1] for ln in lines)):
        raise InputError(f"{path}: " + (f"{n_v} vertices ('v' lines) but no faces ('f' lines): "
                                        "no surface to import" if n_v else
                                        "not an OBJ file: no 'v' (vertex) or 'f' (face) lines")
                         )
    for no, k in late:
        if k > n_v:
            raise InputError(f"{path}, line {no}: a face refers to vertex {k}, but the file "
                             f"holds {n_v} vertices (numbered 1..{n_v})")


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2,
              "int16": 2, "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4,
              "float": 4, "float32": 4, "double": 8, "float64": 8}


def _ply_header(path: Path, data: bytes):
    """(format, [(element, count, [property: (name, is_list)])], header bytes) of a PLY."""
    from ..io.clouds import ply_header_end
    end = ply_header_end(data)  # a line of its own: a comment may hold the words
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header)")
    eol = data.find(b"\n", end)
    head_len = len(data) if eol < 0 else eol + 1
    fmt, elements = None, []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) > 1:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append((words[1], int(words[2]), []))
            except ValueError:
                raise InputError(f"{path}: PLY header line {line.strip()!r}: the count is not "
                                 "a whole number") from None
        elif words[0] == "property" and elements:
            elements[-1][2].append((words[-1], len(words) > 1 and words[1] == "list"))
    return fmt, elements, head_len


def check_ply(path: Path) -> None:
    """An ASCII PLY holds the elements its header declares: as many lines as each count, the
    last one whole, every face's vertices among the file's. (trimesh refuses a binary one cut
    short itself.)"""
    data = path.read_bytes()
    fmt, elements, head_len = _ply_header(path, data)
    if fmt != "ascii":
        return
    lines = [ln for ln in data[head_len:].decode("utf-8", errors="replace").splitlines()
             if ln.strip()]
    start = 0
    counts = {name: count for name, count, _ in elements}
    whole = len(lines) - (not data.endswith((b"\n", b"\r")))  # a last line without its end
    for name, count, props in elements:
        held = max(0, min(count, whole - start))
        if len(lines) - start >= count:
            held = count  # a last line without its end is whole when the counts add up
        if held < count:
            raise InputError(f"{path}: the header declares {count} {_plural(name)}, the file "
                             f"holds {held} ({_TRUNCATED})")
        rows = lines[start:start + count]
        start += count
        cut = start == len(lines) and not data.endswith((b"\n", b"\r"))
        faces = []
        for i, row in enumerate(rows):
            tokens = row.split()
            need, j, idx = 0, 0, None
            try:
                for pname, is_list in props:
                    if is_list:
                        k = int(tokens[j])
                        if pname in ("vertex_indices", "vertex_index") and \
                                name == "face":
                            idx = tokens[j + 1:j + 1 + k]
                        need, j = j + 1 + k, j + 1 + k
                    else:
                        need, j = j + 1, j + 1
            except (ValueError, IndexError):
                need = j + 2
            if len(tokens) < need:
                what = f"{name} {i + 1} of {count}"
                if cut and i == len(rows) - 1:
                    raise InputError(f"{path}: the file ends in the middle of {what} "
                                     f"({row.strip()[:60]!r}); {_TRUNCATED}")
                raise InputError(f"{path}: {what} ({row.strip()[:60]!r}) holds fewer values "
                                 "than the header's properties")
            if idx is not None:
                faces.append(idx)
        if faces:
            try:
                flat = np.array([int(t) for f in faces for t in f], np.int64)
            except ValueError:
                raise InputError(f"{path}: a face's vertex number is not a whole number"
                                 ) from None
            check_indices(flat, counts.get("vertex", 0), path, base=0)


def check_stl(path: Path) -> None:
    """A binary STL is 84 bytes and 50 a triangle, as many as its header says; an ASCII one
    ends with 'endsolid'."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    if len(head) >= 84:
        n = int.from_bytes(head[80:84], "little")
        if size == 84 + 50 * n:
            return  # a whole binary STL
    else:
        n = None
    if head.lstrip()[:5].lower() == b"solid":  # ASCII
        with open(path, "rb") as f:
            f.seek(max(0, size - 4096))
            tail = f.read().lower()
        if b"endsolid" in tail:
            return
        raise InputError(f"{path}: an ASCII STL without its closing 'endsolid' line "
                         f"({_TRUNCATED})")
    if _is_text(head):  # neither 'solid ...' nor a binary header with its count
        raise InputError(f"{path}: not an STL file: text that does not start with 'solid' "
                         "(an ASCII STL), and not a binary STL (an 80-byte header, a triangle "
                         "count and 50 bytes a triangle)")
    if n is None:
        raise InputError(f"{path}: {size} bytes: shorter than a binary STL's 84-byte header "
                         f"({_TRUNCATED})")
    held = (size - 84) // 50
    if size < 84 + 50 * n:
        raise InputError(f"{path}: the header declares {n} triangles, the file holds {held} "
                         f"({size} bytes, {84 + 50 * n} needed; {_TRUNCATED})")
    raise InputError(f"{path}: the header declares {n} triangles ({84 + 50 * n} bytes), the "
                     f"file has {size} bytes: not a whole binary STL")


def _is_text(data: bytes) -> bool:
    """Printable ASCII and white space only (a binary STL's triangle count is not)."""
    return bool(data) and all(32 <= b < 127 or b in (9, 10, 13) for b in data)


def check_gltf(path: Path) -> None:
    """A .gltf is JSON; a .glb starts with 'glTF' and is as long as its header says (trimesh
    otherwise names a JSON parser's or a missing 'model.gltf's error)."""
    data = path.read_bytes()
    if path.suffix.lower() == ".gltf":
        try:
            doc = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise InputError(f"{path}: not a glTF file: a .gltf is JSON text, and this is not "
                             f"({str(exc)[:80]})") from None
        if not isinstance(doc, dict) or "asset" not in doc:
            raise InputError(f"{path}: not a glTF file: JSON without the glTF 'asset' object")
        return
    if data[:4] != b"glTF":
        raise InputError(f"{path}: not a binary glTF (GLB) file: it does not start with "
                         "'glTF'")
    declared = int.from_bytes(data[8:12], "little") if len(data) >= 12 else None
    if declared is None or len(data) < declared:
        raise InputError(f"{path}: a GLB file cut short ({len(data)} of "
                         f"{declared if declared is not None else 'its header 12'} bytes; "
                         f"{_TRUNCATED})")


def _plural(name: str) -> str:
    return {"vertex": "vertices", "face": "faces"}.get(name, f"'{name}' elements")


def _scene_meshes(scene, patterns, path: Path) -> RawModel:
    """Join a trimesh scene's geometry, each instance moved by its node's world transform."""
    trimesh = _trimesh()
    verts, faces, taken, skipped, offset, stored = [], [], [], [], 0, 0.0
    for node in scene.graph.nodes_geometry:
        matrix, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        name = str(node)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            skipped.append(f"{name} (no faces)")
            continue
        if not (_match(name, patterns) or _match(str(geom_name), patterns)):
            skipped.append(f"{name} (not matched)")
            continue
        v = np.asarray(geom.vertices, np.float64)
        stored = max(stored, _max_abs(v))
        m = np.asarray(matrix, np.float64)
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite: named by read_model
            verts.append(v @ m[:3, :3].T + m[:3, 3])
        check_indices(np.asarray(geom.faces, np.int64), len(v), path, base=0,
                      where=f" of {name}")
        faces.append(np.asarray(geom.faces, np.int64) + offset)
        offset += len(v)
        taken.append(name)
    if not taken:
        raise InputError(f"{path}: no surface to take; objects: {', '.join(skipped) or 'none'}"
                         + (f" (--objects {','.join(patterns)})" if patterns else ""))
    return RawModel(Mesh(np.concatenate(verts), np.concatenate(faces)), objects=taken,
                    skipped=skipped, stored_max=stored)


def _max_abs(v: np.ndarray) -> float:
    with np.errstate(invalid="ignore"):
        a = np.abs(v[np.isfinite(v).all(axis=1)]) if len(v) else v
        return float(a.max()) if len(a) else 0.0


def _trimesh_scene(path: Path, text: str | None = None, **kwargs):
    """The file as a trimesh scene; ``text``: the OBJ's text to read in place of the file's
    (with its indices made absolute, its concave polygons cut: :func:`_obj_text`)."""
    trimesh = _trimesh()
    try:
        if text is not None:  # the resolver still finds the .mtl beside the file
            return trimesh.load(io.BytesIO(text.encode("utf-8")), file_type="obj",
                                resolver=trimesh.resolvers.FilePathResolver(str(path)),
                                process=False, force="scene", **kwargs)
        return trimesh.load(str(path), process=False, force="scene", **kwargs)
    except InputError:
        raise
    except Exception as exc:  # trimesh and its parsers raise many types on bad files
        raise InputError(f"{path}: cannot read the file ({type(exc).__name__}: {exc})") from exc


def _obj_ref(token: str, counts: tuple[int, int, int]) -> str:
    """An OBJ face corner ``v/vt/vn`` with negative numbers made absolute: counted back from
    the last vertex (texture, normal) read before the face, as OBJ defines them (trimesh
    counts them back from the file's last vertex, so a file of several objects each written
    with -8..-1 would get the last object's vertices for all of them)."""
    parts = token.split("/")
    return "/".join(str(n + int(t) + 1) if t.startswith("-") else t
                    for t, n in zip(parts, counts, strict=False))


def _obj_text(path: Path) -> str | None:
    """The OBJ's text as trimesh must read it, or None where the file reads right as it is:
    negative indices made absolute (:func:`_obj_ref`), and each concave polygon replaced by
    its ear-clipped triangles (trimesh fans it, laying triangles over its notch)."""
    lines = path.read_bytes().decode("utf-8", errors="replace").split("\n")
    counts = {"v": 0, "vt": 0, "vn": 0}
    coords, polys, changed = [], [], False
    for no, line in enumerate(lines):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        if tokens[0] in counts:
            counts[tokens[0]] += 1
            if tokens[0] == "v":
                coords.append(tokens[1:4])
        elif tokens[0] == "f":
            refs = tokens[1:]
            if any("-" in t for t in refs):
                refs = [_obj_ref(t, tuple(counts.values())) for t in refs]
                lines[no] = "f " + " ".join(refs)
                changed = True
            if len(refs) > 3:
                polys.append((no, refs))
    if polys:
        verts = np.array(coords, np.float64)
        corners = [[int(t.split("/", 1)[0]) - 1 for t in refs] for _, refs in polys]
        if wrong_fans(verts, corners):
            for (no, refs), poly in zip(polys, corners, strict=True):
                if wrong_fans(verts, [poly]):  # its triangles, by corner number
                    tris = triangulate_polygons(verts[poly], [list(range(len(poly)))])
                    lines[no] = "\n".join("f " + " ".join(refs[i] for i in t) for t in tris)
            changed = True
    return "\n".join(lines) if changed else None


def read_obj(path: Path, patterns=()) -> RawModel:
    """OBJ through trimesh, its negative indices and concave polygons made right first; with
    ``patterns`` each ``o`` object and ``g`` group is an object of its own to pick."""
    split = {"split_objects": True, "split_groups": True} if patterns else {}
    scene = _trimesh_scene(path, _obj_text(path), **split)
    return _scene_meshes(scene, list(patterns), path)


def _ply_faces(path: Path):
    """A PLY's faces as stored (lists of vertex numbers), read by trimesh's own parser."""
    from trimesh.exchange import ply
    with open(path, "rb") as f:
        elements, is_ascii, _ = ply._parse_header(f)
        (ply._ply_ascii if is_ascii else ply._ply_binary)(elements, f)
    face = elements.get("face", {}).get("data")
    if face is None:
        return []
    data = face[next(iter(face.dtype.names))] if hasattr(face, "dtype") and face.dtype.names \
        else next(iter(face.values()))
    if getattr(data, "dtype", None) is not None and data.dtype.names:  # (count, indices)
        data = data[data.dtype.names[1]]
    if getattr(data, "dtype", None) is not None and data.dtype != object and data.ndim == 2:
        return [] if data.shape[1] <= 3 else data.tolist()  # triangles: trimesh's are right
    return [np.asarray(p).ravel().tolist() for p in data]


def read_ply(path: Path, patterns=()) -> RawModel:
    """PLY through trimesh; its polygons that trimesh fans outside themselves (concave ones)
    triangulated again from the faces as stored; float32 vertices noted."""
    try:
        raw = read_trimesh(path, patterns)
    except InputError as exc:  # a binary PLY shorter than its header's counts
        if "unexpected length" not in str(exc):
            raise
        _, elements, _ = _ply_header(path, path.read_bytes())
        counts = " and ".join(f"{n} {_plural(e)}" for e, n, _ in elements)
        raise InputError(f"{path}: a binary PLY cut short: its {path.stat().st_size} bytes "
                         f"hold less than the header's {counts} ({_TRUNCATED})") from None
    data = path.read_bytes()[:4096]
    from ..io.clouds import ply_header_end
    head = data[:max(ply_header_end(data), 0)].decode("ascii", errors="replace")
    # polygons, if trimesh made more triangles than the file has faces (each of a file of
    # triangles is one: no second parse of it)
    declared = re.search(r"\n\s*element\s+face\s+(\d+)\s*\n", head)
    polygons = re.search(r"property\s+list\s+\S+\s+\S+\s+vertex_ind", head) and \
        declared is not None and int(declared.group(1)) != len(raw.mesh.faces)
    if polygons and len(raw.objects) == 1:
        try:
            polys = _ply_faces(path)
            if max(map(len, polys), default=3) > 3 and max(map(max, polys)) >= len(
                    raw.mesh.vertices):
                polys = []  # not the vertices trimesh read: keep its faces
        except Exception:  # a PLY trimesh read but its parser, called alone, does not
            polys = []
        if any(len(p) > 3 for p in polys) and wrong_fans(raw.mesh.vertices, polys):
            raw.mesh = Mesh(raw.mesh.vertices, triangulate_polygons(raw.mesh.vertices, polys))
    if re.search(r"property\s+(float|float32)\s+x\b", head):
        raw.float32_max = raw.stored_max
    return raw


def read_stl(path: Path, patterns=()) -> RawModel:
    """STL through trimesh; a binary STL's coordinates are float32."""
    raw = read_trimesh(path, patterns)
    if _stl_binary(path):
        raw.float32_max = raw.stored_max
    return raw


def _stl_binary(path: Path) -> bool:
    """A whole binary STL: 84 bytes and 50 a triangle (check_stl refused any other non-ASCII)."""
    with open(path, "rb") as f:
        head = f.read(84)
    return len(head) == 84 and path.stat().st_size == 84 + 50 * int.from_bytes(head[80:],
                                                                                "little")


def read_trimesh(path: Path, patterns=()) -> RawModel:
    """OBJ, STL, PLY: no unit, no axes declared."""
    return _scene_meshes(_trimesh_scene(path), list(patterns), path)


def read_gltf(path: Path, patterns=()) -> RawModel:
    """glTF 2.0 declares metres, +Y up and the asset's front facing +Z (its section 3.4);
    its vertex positions are float32 (the node transforms, applied here, are not)."""
    raw = _scene_meshes(_trimesh_scene(path), list(patterns), path)
    raw.unit_m, raw.unit_note = 1.0, "glTF: metres by its specification"
    raw.up, raw.forward = "Y", "Z"
    raw.float32_max = raw.stored_max
    return raw


_COLLADA_UP = {"X_UP": "X", "Y_UP": "Y", "Z_UP": "Z"}


def collada_asset(path: Path) -> tuple[float | None, str, str]:
    """(metres per unit, unit name, up axis) from a COLLADA file's top ``<asset>``."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise InputError(f"{path}: not a readable COLLADA (XML) file: {exc}") from exc
    ns = re.match(r"\{[^}]*\}", root.tag)
    ns = ns.group(0) if ns else ""
    asset = root.find(f"{ns}asset")
    unit_m, unit_name, up = None, "", "Y"  # COLLADA's defaults: metre, Y_UP
    if asset is not None:
        unit = asset.find(f"{ns}unit")
        if unit is not None:
            try:
                unit_m = float(unit.get("meter", "1"))
            except ValueError as exc:
                raise InputError(f"{path}: <unit meter={unit.get('meter')!r}> is not a "
                                 "number") from exc
            if not np.isfinite(unit_m) or unit_m <= 0:
                raise InputError(f"{path}: <unit meter={unit_m!r}> must be > 0")
            unit_name = unit.get("name", "")
        axis = asset.find(f"{ns}up_axis")
        if axis is not None and axis.text:
            key = axis.text.strip().upper()
            if key not in _COLLADA_UP:
                raise InputError(f"{path}: <up_axis>{axis.text}</up_axis> unknown; COLLADA "
                                 "accepts X_UP, Y_UP, Z_UP")
            up = _COLLADA_UP[key]
    return unit_m, unit_name, up


def read_collada(path: Path, patterns=()) -> RawModel:
    """COLLADA through trimesh + pycollada; unit and up axis from its ``<asset>``."""
    if importlib.util.find_spec("collada") is None:
        raise InputError(f"{path}: COLLADA files need pycollada: pip install 'apcg[sim]'")
    unit_m, unit_name, up = collada_asset(path)
    raw = _scene_meshes(_trimesh_scene(path), list(patterns), path)
    if unit_m is None:
        raw.unit_m, raw.unit_note = 1.0, "COLLADA: no <unit>, the format's default metre"
    else:
        raw.unit_m = unit_m
        raw.unit_note = f"COLLADA <unit meter=\"{unit_m:g}\" name=\"{unit_name}\">"
    raw.up = up
    return raw


def blender_command(script: str, args: list[str]) -> list[str]:
    """The command that runs ``script`` in Blender: this Python when it has bpy, else
    ``$APCG_BLENDER`` or ``blender`` on PATH."""
    exe = os.environ.get("APCG_BLENDER")
    if not exe and importlib.util.find_spec("bpy") is not None:
        return [sys.executable, script, *args]
    exe = exe or shutil.which("blender")
    if not exe:
        raise InputError("this format is read by Blender's importers: pip install "
                         "'apcg[blender]' (the bpy module), or put a blender on PATH or in "
                         "$APCG_BLENDER")
    return [exe, "-b", "--factory-startup", "--python-exit-code", "1", "-P", script, "--",
            *args]


BLENDER_TIMEOUT_ENV = "APCG_BLENDER_TIMEOUT_S"
BLENDER_TIMEOUT_S = 1800.0  # a large scene imports in minutes; a stuck Blender is stopped


def blender_timeout_s() -> float:
    """How long one Blender import may take: ``$APCG_BLENDER_TIMEOUT_S`` seconds, else 1800."""
    text = os.environ.get(BLENDER_TIMEOUT_ENV, "").strip()
    if not text:
        return BLENDER_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise InputError(f"${BLENDER_TIMEOUT_ENV} {text!r} not accepted: a number of seconds "
                         "> 0")
    return value


def read_blender(path: Path, patterns=()) -> RawModel:
    """FBX, .blend, USD, Alembic through Blender's importers, in metres, Blender's Z up."""
    script = str(Path(__file__).with_name("blender_import.py"))
    with tempfile.TemporaryDirectory(prefix="apcg-import-") as tmp:
        out = Path(tmp) / "mesh.npz"
        cmd = blender_command(script, [str(path.resolve()), str(out), ",".join(patterns)])
        limit = blender_timeout_s()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp, timeout=limit)
        except subprocess.TimeoutExpired:  # the child is killed: nothing waits for ever
            raise InputError(f"{path}: Blender did not finish importing it within {limit:g} s "
                             f"(${BLENDER_TIMEOUT_ENV}); allow more time there, or export it "
                             "from its own program as glTF or OBJ") from None
        if proc.returncode != 0 or not out.exists():
            lines = [ln for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
            said = [ln for ln in lines if "blender_import:" in ln or "Error" in ln]
            why = (said or lines or [f"exit code {proc.returncode}"])[-1]
            raise InputError(f"{path}: Blender could not import it: "
                             f"{why.replace('blender_import: ', '').strip()}")
        with np.load(out, allow_pickle=False) as z:
            info = json.loads(str(z["info"]))
            mesh = Mesh(z["vertices"], z["faces"])
    declared = not info["unit_note"].startswith("not declared")
    return RawModel(mesh, 1.0 if declared else None, info["unit_note"], up="Z",
                    objects=info["objects"], skipped=info["skipped"])


FORMATS = (
    Format("OFF", (".off",), "own reader", read_off),
    Format("Wavefront OBJ", (".obj",), "trimesh", read_obj, check_obj),
    Format("STL", (".stl",), "trimesh", read_stl, check_stl),
    Format("PLY", (".ply",), "trimesh", read_ply, check_ply),
    Format("glTF 2.0", (".glb", ".gltf"), "trimesh", read_gltf, check_gltf),
    Format("COLLADA", (".dae",), "trimesh + pycollada", read_collada),
    Format("FBX", (".fbx",), "Blender", read_blender),
    Format("Blender", (".blend",), "Blender", read_blender),
    Format("USD", (".usd", ".usda", ".usdc", ".usdz"), "Blender", read_blender),
    Format("Alembic", (".abc",), "Blender", read_blender),
)
SUFFIXES = tuple(s for f in FORMATS for s in f.suffixes)


def format_of(path) -> Format:
    suffix = Path(path).suffix.lower()
    for f in FORMATS:
        if suffix in f.suffixes:
            return f
    raise InputError(f"{path}: unsupported format {suffix!r}; accepted: {', '.join(SUFFIXES)}")


def read_model(path, objects: str | None = None) -> RawModel:
    """Read ``path`` as stored; ``objects``: comma-separated name patterns to keep."""
    path = Path(path)
    try:  # the readers (trimesh's among them) take file names as UTF-8 text
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise InputError(f"{shown}: the file name is not UTF-8 text; rename the file, or link "
                         "it under a UTF-8 name (ln -s)") from None
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a model file; accepted: a file "
                         f"ending {', '.join(SUFFIXES)}")
    fmt = format_of(path)
    if path.stat().st_size == 0:
        raise InputError(f"{path}: the file is empty")
    if fmt.check is not None:
        fmt.check(path)
    patterns = [p.strip() for p in (objects or "").split(",") if p.strip()]
    if fmt.read is read_off and patterns:
        raise InputError(f"{path}: an OFF file holds one object; --objects does not apply")
    try:
        raw = fmt.read(path, patterns)
    except InputError as exc:  # a reader's check that does not know the file (Mesh's own)
        if str(path) in str(exc):
            raise
        raise InputError(f"{path}: {exc}") from exc
    m = raw.mesh
    if len(m.faces) == 0:
        raise InputError(f"{path}: the file holds no triangles: there is no surface to import")
    bad = ~np.isfinite(m.vertices[np.unique(m.faces)]).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} vertices of its triangles have non-finite "
                         "coordinates (NaN or infinite); fix or remove them in a modeller")
    return raw
