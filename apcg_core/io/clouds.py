"""Standard point clouds in files: PLY (binary), NPZ and LAS / LAZ, observation frame, metres.

Every format carries the per-point attributes range_m (float64), cell_w and cell_h (centred cell
indices), and, for stacked clouds, sample; a photon cloud also its label, count (and pulse),
read back into the cloud wherever the file's meta names its sensor. LAS / LAZ headers carry
a fixed creation date (SOURCE_DATE_EPOCH's day when set, else LAS_CREATION_DATE), so the
same cloud gives the same bytes on any day. Files are written through a ``.part`` file and
renamed, so a file with its final name is complete. Files of other lidar tools (PLY ascii or
binary, LAS / LAZ of any point format) are read too, with all their per-point attributes.
"""

from __future__ import annotations

import copy
import datetime
import functools
import io
import json
import os
import re
from pathlib import Path

import numpy as np

from ..cloud import PHOTON_FIELDS, PointCloud, not_held
from ..errors import InputError
from .atomic import atomic_path, claim, name_the_file, publish, refuse_directory, scratch
from .crc import crc32

FORMATS = (".ply", ".npz", ".las", ".laz")
_OWN = ("range_m", "cell_w", "cell_h", "sample")
_PLY_PROPS = [("x", "f8"), ("y", "f8"), ("z", "f8"), ("range_m", "f8"), ("cell_w", "i4"),
              ("cell_h", "i4"), ("sample", "i4")]
# A photon cloud's extra properties (SPEC section 8); an ideal cloud's files have none of them.
_PHOTON_PROPS = {"label": "u1", "count": "i4", "pulse": "i4"}
# LAS classification of a photon cloud's points: the ASPRS codes 1 (unclassified: signal)
# and 7 (low point: noise).
LAS_CLASS = {1: 1, 0: 7}
# The creation date of every LAS / LAZ header without SOURCE_DATE_EPOCH: laspy would stamp
# the day of writing, and the same call would give other bytes tomorrow.
LAS_CREATION_DATE = datetime.date(2000, 1, 1)
# What each of the cloud's own integer columns is stored as (PointCloud's types): a file's
# value must fit, or it would wrap silently.
_STORED = {"cell_w": np.int32, "cell_h": np.int32, "sample": np.int64, **PHOTON_FIELDS}
_PLY_TYPES = {"f8": "double", "i4": "int", "f4": "float", "u1": "uchar", "i2": "short",
              "u2": "ushort", "u4": "uint", "i1": "char"}
_PLY_NAMES = {v: k for k, v in _PLY_TYPES.items()} | {
    "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4",
    "float32": "f4", "float64": "f8"}


def _fmt(path) -> str:
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise InputError(f"unsupported point cloud format {ext!r} for {path}; accepted: "
                         f"{', '.join(FORMATS)}")
    return ext


def _copy_member(zf, member, spill: Path, spill_crc: int, block: int) -> None:
    """The bytes of ``spill`` appended to the open zip ``member`` (stored, after its .npy
    header). Where zipfile keeps a member's size and CRC where :func:`_count_in` sets them
    (:meth:`_DirectMember.supported`), they are appended by :func:`_append_range` (the kernel's
    copy where it can) and the member's CRC (``spill_crc``, taken as they were spilled,
    combined with the header's) and size are set as its own writes would have set them: the
    same zip, byte for byte (tests/test_generate_stream.py), without reading the bytes back
    into Python. Elsewhere they go through ``member.write`` block by block."""
    from .crc import crc32_combine
    size = spill.stat().st_size
    with open(spill, "rb") as src:
        if _DirectMember.supported():
            _append_range(zf.fp, src.fileno(), 0, size, block)
            _count_in(member, crc32_combine(member._crc, spill_crc, size), size)
            return
        while data := src.read(block):
            member.write(data)


def _count_in(member, crc: int, added: int) -> None:
    """A zip member's CRC set to ``crc`` and ``added`` bytes written past it counted in its
    size, as zipfile's own writes would have done (its local header is rewritten from them
    when the member closes)."""
    member._crc = crc
    member._file_size += added
    member._compress_size += added


def _append_range(dst, src_fd: int, offset: int, count: int, block: int = 1 << 24) -> None:
    """``count`` bytes of the open file ``src_fd`` from ``offset`` appended at the current
    position of the open binary file ``dst``: copied by the kernel where it can
    (``os.copy_file_range``), else (or after a refusal part way, which is written over) read
    and written block by block."""
    import os
    dst.flush()
    start, done = dst.tell(), 0
    if count and hasattr(os, "copy_file_range"):
        try:
            while done < count and (k := os.copy_file_range(
                    src_fd, dst.fileno(), count - done, offset + done, start + done)):
                done += k
        except OSError:  # a file system that cannot
            done = 0
    if done == count:
        dst.seek(start + count)
        return
    dst.seek(start)
    done = 0
    while done < count:
        data = os.pread(src_fd, min(block, count - done), offset + done)
        if not data:
            raise OSError(f"the file ended {count - done} bytes early")
        dst.write(data)
        done += len(data)


def _npy_header(dtype, shape) -> bytes:
    """The version 1.0 .npy header np.save writes for a C-order array (128 bytes for any
    shape of this module's arrays: the dict is padded to 64-byte alignment)."""
    fmt = np.lib.format
    out = io.BytesIO()
    fmt.write_array_header_1_0(out, {"descr": fmt.dtype_to_descr(np.dtype(dtype)),
                                     "fortran_order": False, "shape": shape})
    return out.getvalue()


class _DirectMember:
    """A stored zip member whose bytes are written in place as they come, its .npy header
    (which holds the final shape) written over a placeholder of the same length at the end:
    the member np.savez writes, without a copy of its bytes. Its CRC is taken as the bytes
    pass and combined with the header's (:func:`apcg_core.io.crc.crc32_combine`), as
    :func:`_copy_member` does for a spilled one."""

    HEADER = 128  # bytes of every .npy header this writer makes (_npy_header)
    _PARTS = ("_fileobj", "_crc", "_file_size", "_compress_size")  # zipfile's, 3.11-3.13

    @staticmethod
    @functools.lru_cache(maxsize=1)
    def supported() -> bool:
        """Whether this Python's zipfile keeps a member's size and CRC where :func:`_count_in`
        sets them (else every member is spilled and written through zipfile)."""
        import zipfile
        with zipfile.ZipFile(io.BytesIO(), "w") as zf, zf.open("probe", "w") as member:
            return all(hasattr(member, k) for k in _DirectMember._PARTS)

    def __init__(self, zf, name: str) -> None:
        self.zf = zf
        self.member = zf.open(name, "w", force_zip64=True)  # its local header written now
        self.member.write(b"\0" * self.HEADER)  # where the header goes
        zf.fp.flush()
        self.start = zf.fp.tell() - self.HEADER
        self.crc = 0
        self.size = 0

    def write(self, data) -> None:
        self.member._fileobj.write(data)
        self.crc = crc32(data, self.crc)
        self.size += data.nbytes if isinstance(data, memoryview) else len(data)

    def append_range(self, src_fd: int, offset: int, count: int, crc: int) -> None:
        """``count`` bytes of ``src_fd`` from ``offset`` (their CRC ``crc``) appended."""
        from .crc import crc32_combine
        _append_range(self.zf.fp, src_fd, offset, count)
        self.crc = crc32_combine(self.crc, crc, count)
        self.size += count

    def close(self, header: bytes) -> None:
        from .crc import crc32_combine
        if len(header) != self.HEADER:
            raise AssertionError(f"a .npy header of {len(header)} bytes, not {self.HEADER}")
        fp, m = self.zf.fp, self.member
        end = fp.tell()
        fp.seek(self.start)
        fp.write(header)
        fp.seek(end)
        _count_in(m, crc32_combine(crc32(header), self.crc, self.size), self.size)
        m.close()  # the local header rewritten with the CRC and sizes


def _replace(tmp: Path, path: Path, held: bool | None = None) -> None:
    publish(tmp, path, held)


def write_cloud(path, cloud: PointCloud, meta: dict | None = None) -> Path:
    """Write ``cloud`` to ``path`` (.ply / .npz / .las / .laz); ``meta`` (JSON-able) goes in
    the header."""
    path = Path(path)
    ext = _fmt(path)
    cloud, text = _cloud_to_write(path, cloud), _meta_text(path, meta)
    records = _ply_records(path, cloud) if ext == ".ply" else None  # checked before any file
    with atomic_path(path) as tmp:
        if ext == ".npz":
            with open(tmp, "wb") as f:
                np.savez(f, xyz=cloud.xyz, range_m=cloud.range_m, cell_w=cloud.cell_w,
                         cell_h=cloud.cell_h, sample=_sample_of(cloud),
                         meta=np.array(text),
                         **{k: getattr(cloud, k) for k in cloud.photon_fields})
        elif ext == ".ply":
            with open(tmp, "wb") as f:
                f.write(_own_ply_header(text, str(len(cloud)), cloud.photon_fields))
                f.write(records)
        else:
            _write_las(path, tmp, cloud, text, compress=ext == ".laz")
    return path


def _cloud_to_write(path, cloud) -> PointCloud:
    """``cloud`` checked again before it is written (a field replaced since it was built would
    be broadcast or refused on reading), or an InputError naming the file."""
    if not isinstance(cloud, PointCloud):
        raise InputError(f"cannot write {path}: expected a PointCloud, got "
                         f"{type(cloud).__name__}")
    try:
        return cloud.checked()
    except InputError as exc:
        raise InputError(f"cannot write {path}: {exc}") from None


def _meta_text(path, meta) -> str:
    """``meta`` as the JSON text every format stores: a dict (None: empty) of JSON values,
    numpy numbers as the numbers they hold; anything else would not read back as given (a
    PLY file reads a non-dict meta as {}), so it is an InputError naming the file."""
    meta = {} if meta is None else meta
    if not isinstance(meta, dict):
        raise InputError(f"cannot write {path}: its meta must be a dict (a JSON object), got "
                         f"{type(meta).__name__}")
    try:
        return json.dumps(meta, default=_json_value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"cannot write {path}: its meta must hold JSON values (dicts, lists, "
                         f"text, numbers, booleans, None): {exc}") from None


def _json_value(v):
    """A numpy number or array in a meta as the JSON value it holds (json's ``default``)."""
    if isinstance(v, np.generic | np.ndarray):
        return v.tolist()
    raise TypeError(f"{type(v).__name__} {v!r} is not a JSON value")


def _sample_of(cloud: PointCloud) -> np.ndarray:
    """Each point's cloud index (0 for a single cloud)."""
    return cloud.sample if cloud.sample is not None else np.zeros(len(cloud), np.int64)


def _props(photon_fields) -> list[tuple[str, str]]:
    return _PLY_PROPS + [(k, _PHOTON_PROPS[k]) for k in photon_fields]


def _own_ply_header(meta_text: str, count: str, photon_fields=()) -> bytes:
    comment = meta_text.replace("\n", " ")
    head = ["ply", "format binary_little_endian 1.0",
            "comment APCG standard point cloud: observation frame, metres",
            f"comment meta {comment}", f"element vertex {count}"]
    head += [f"property {_PLY_TYPES[t]} {n}" for n, t in _props(photon_fields)]
    head += ["end_header"]
    return ("\n".join(head) + "\n").encode()


def _ply_records(path, cloud: PointCloud) -> bytes:
    rec = np.empty(len(cloud), dtype=[(n, "<" + t) for n, t in _props(cloud.photon_fields)])
    rec["x"], rec["y"], rec["z"] = cloud.xyz.T
    rec["range_m"], rec["cell_w"] = cloud.range_m, cloud.cell_w
    rec["cell_h"], rec["sample"] = cloud.cell_h, _sample_i4(path, cloud)
    for k in cloud.photon_fields:
        rec[k] = getattr(cloud, k)
    return rec.tobytes()


_I4 = np.iinfo(np.int32)


def _sample_i4(path, cloud: PointCloud) -> np.ndarray:
    """Each point's cloud index as PLY and LAS store it, in 32 bits: one that does not fit
    is refused, not wrapped (NPZ keeps the cloud's 64 bits)."""
    s = _sample_of(cloud)
    if len(s) and (s.min() < _I4.min or s.max() > _I4.max):
        i = int(np.argmax((s < _I4.min) | (s > _I4.max)))
        raise InputError(f"cannot write {path}: its sample value {int(s[i])} (point {i}) does "
                         f"not fit the format's 32-bit sample field; accepted: whole numbers "
                         f"from {_I4.min} to {_I4.max} (NPZ stores any)")
    return s


def _check_las_extent(path, header, xyz: np.ndarray) -> None:
    """LAS stores x, y, z as 32-bit integers of the header's scale around its offset: a point
    beyond that is an InputError naming the file (laspy's own test, which would raise a bare
    OverflowError), before anything of it is written."""
    if not len(xyz):
        return
    lo = _I4.min * header.scales + header.offsets
    hi = _I4.max * header.scales + header.offsets
    if (xyz.min(axis=0) < lo).any() or (xyz.max(axis=0) > hi).any():
        i = int(np.argmax(((xyz < lo) | (xyz > hi)).any(axis=1)))
        lo, hi = np.round(lo, 4).tolist(), np.round(hi, 4).tolist()  # as shown
        raise InputError(
            f"cannot write {path}: point {i} at {xyz[i].tolist()} m is outside what LAS / LAZ "
            f"can hold: x, y, z from {lo} to {hi} m (32-bit steps of {header.scales[0]:g} m "
            f"around {header.offsets.tolist()}, the first cloud's centre); write .ply or "
            ".npz, which hold any extent")


def _fill_las(path, las, cloud: PointCloud):
    _check_las_extent(path, las.header, cloud.xyz)
    las.x, las.y, las.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    las.range_m = cloud.range_m
    las.cell_w, las.cell_h = cloud.cell_w, cloud.cell_h
    las.sample = _sample_i4(path, cloud).astype(np.int32)
    if cloud.label is not None:
        las.classification = np.where(cloud.label == 1, LAS_CLASS[1], LAS_CLASS[0]).astype(
            np.uint8)
    for k in ("count", "pulse"):
        if getattr(cloud, k) is not None:
            setattr(las, k, getattr(cloud, k).astype(np.int32))
    return las


class CloudWriter:
    """Write a stacked cloud block by block, in bounded memory, into any format: PLY and
    LAS/LAZ stream to disk (the PLY vertex count is patched in at the end; laspy counts LAS
    points itself); an NPZ's first array (xyz) is written in place in the zip as blocks come,
    the others stream to spill files beside the output (``NAME.FIELD.part``), copied into the
    zip's members at the end (the same members, headers and bytes as ``np.savez`` writes for
    the whole cloud; memory flat in the number of clouds, half the data written twice). As
    with :func:`write_cloud`, the file appears under its final name only when complete, and no
    spill file is left.

        with CloudWriter("clouds.ply", meta) as w:
            for cloud in blocks:
                w.write(cloud)
    """

    STREAMING = (".ply", ".las", ".laz")
    _COUNT_DIGITS = 20  # the PLY vertex count, zero-padded so it can be patched in place

    def __init__(self, path, meta: dict | None = None, photon_fields=()) -> None:
        self.path = Path(path)
        self.ext = _fmt(self.path)
        self.meta = {} if meta is None else meta
        self._meta = _meta_text(self.path, self.meta)  # refused before any file is made
        # a photon cloud's attributes: fixed up front (a PLY header is written first)
        self.photon_fields = tuple(photon_fields)
        refuse_directory(self.path)
        self._held_output = claim(self.path)  # the guard first: a refusal costs no work
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = scratch(self.path.with_name(self.path.name + ".part"))
        self.n = 0
        self._file = None
        self._las = None
        self._spill: dict = {}  # NPZ: field -> (open spill file, path, dtype, row shape)
        self._crc: dict = {}  # NPZ: field -> CRC-32 of its spilled bytes
        self._zip = self._direct = None  # NPZ: the zip, its first member written in place
        if self.ext == ".npz":
            self._open_spill()
        if self.ext == ".ply":
            self._file = open(self.tmp, "wb")  # noqa: SIM115 - closed in close()
            head = _own_ply_header(self._meta, "0" * self._COUNT_DIGITS, self.photon_fields)
            self._count_at = head.index(b"element vertex ") + len(b"element vertex ")
            self._file.write(head)

    def write(self, cloud: PointCloud) -> None:
        cloud = _cloud_to_write(self.path, cloud)
        if tuple(cloud.photon_fields) != self.photon_fields:
            raise InputError(f"this writer takes clouds with {self.photon_fields or 'no'} "
                             f"photon attributes, got {cloud.photon_fields or 'none'}")
        if self.ext == ".npz":
            for k, (f, _, dtype, _) in self._spill.items():
                a = _sample_of(cloud) if k == "sample" else getattr(cloud, k)
                data = np.ascontiguousarray(a, dtype=dtype).data
                if f is None:  # the first member: straight into the zip
                    self._direct.write(data)
                else:
                    f.write(data)
                # the member's CRC, taken while the bytes are at hand: the zip at the end
                # then copies them in the kernel without reading them back
                self._crc[k] = crc32(data, self._crc.get(k, 0))
        elif self.ext == ".ply":
            self._file.write(_ply_records(self.path, cloud))
        else:
            laspy = _laspy(self.ext == ".laz")
            if self._las is None:
                header = _las_header(laspy, cloud, self._meta)
                # the writer counts its points in its header: each block starts from a copy
                self._template = copy.deepcopy(header)
                self._las = laspy.open(self.tmp, mode="w", header=header,
                                       do_compress=self.ext == ".laz")
            las = _fill_las(self.path, laspy.LasData(copy.deepcopy(self._template)), cloud)
            self._las.write_points(las.points)
        self.n += len(cloud)

    @property
    def fields(self) -> dict:
        """NPZ: each stored array's name -> (dtype, shape of one point's row)."""
        return {k: (dtype, row) for k, (_, _, dtype, row) in self._spill.items()}

    def write_ranges(self, src_fd: int, ranges: dict, n: int) -> None:
        """Append ``n`` points whose arrays lie as raw bytes in the open file ``src_fd``:
        ``ranges`` maps every field this writer stores to (offset, bytes, CRC-32 of those
        bytes), in the field's stored dtype (a part file's members, checked by the caller).
        NPZ only: the bytes go into the spill files and the zip's first member by the kernel,
        never through Python; the same file as :meth:`write` of those arrays makes."""
        from .crc import crc32_combine
        if self.ext != ".npz":
            raise ValueError("write_ranges writes NPZ files; use write() for other formats")
        if set(ranges) != set(self._spill):
            raise ValueError(f"write_ranges needs the fields {sorted(self._spill)}, got "
                             f"{sorted(ranges)}")
        for k, (f, _, dtype, row) in self._spill.items():
            offset, count, crc = ranges[k]
            if count != n * dtype.itemsize * int(np.prod(row, dtype=np.int64)):
                raise ValueError(f"{k}: {count} bytes are not {n} points of {dtype}{row}")
            if f is None:
                self._direct.append_range(src_fd, offset, count, crc)
            else:
                _append_range(f, src_fd, offset, count)
                self._crc[k] = crc32_combine(self._crc.get(k, 0), crc, count)
        self.n += n

    def close(self) -> Path:
        if self.ext == ".npz":
            self._write_npz()
            _replace(self.tmp, self.path, self._held_output)
            return self.path
        if self.ext == ".ply":
            self._file.seek(self._count_at)
            self._file.write(f"{self.n:0{self._COUNT_DIGITS}d}".encode())
            self._file.close()
        elif self._las is not None:
            self._las.close()
        else:  # nothing written: an empty LAS, as write_cloud makes it
            empty = PointCloud(np.zeros((0, 3)), [], [], [], np.zeros(0, np.int64),
                               **{k: [] for k in self.photon_fields})
            return write_cloud(self.path, empty, self.meta)
        _replace(self.tmp, self.path, self._held_output)
        return self.path

    def abort(self) -> None:
        """Drop what was written: nothing is left under either name."""
        if self._zip is not None:  # dropped whole: no central directory written, and none
            fp, self._zip.fp = self._zip.fp, None  # later when the ZipFile is collected
            self._zip = None
            fp.close()
        for handle in (self._file, self._las, *(v[0] for v in self._spill.values())):
            try:
                if handle is not None:
                    handle.close()
            except Exception:  # noqa: BLE001 - already failing; the .part goes anyway
                pass
        self.tmp.unlink(missing_ok=True)
        self._drop_spill()

    # --- NPZ: one spill file per array, then the zip ------------------------------------------
    _NPZ_FIELDS = {"xyz": (np.float64, (3,)), "range_m": (np.float64, ()),
                   "cell_w": (np.int32, ()), "cell_h": (np.int32, ()),
                   "sample": (np.int64, ())}  # PointCloud's stored types; np.savez's order
    _COPY_BYTES = 1 << 24  # spill bytes copied into the zip per read

    def _open_spill(self) -> None:
        """The first member (xyz, half the bytes) is written in place in the zip as blocks
        come (:class:`_DirectMember`); the others spill to files of their own, copied in after
        it at the end."""
        import zipfile

        from ..cloud import PHOTON_FIELDS
        fields = dict(self._NPZ_FIELDS)
        fields.update({k: (PHOTON_FIELDS[k], ()) for k in self.photon_fields})
        first = next(iter(fields)) if _DirectMember.supported() else None
        names = {k: scratch(self.path.with_name(f"{self.path.name}.{k}.part")) for k in fields}
        try:  # every name seen by the guard before any file is made; none left on a failure
            if first is not None:
                self._zip = zipfile.ZipFile(self.tmp, mode="w",
                                            compression=zipfile.ZIP_STORED, allowZip64=True)
                self._direct = _DirectMember(self._zip, first + ".npy")
            for k, (dtype, row) in fields.items():
                handle = None if k == first else open(names[k], "wb")  # noqa: SIM115
                self._spill[k] = (handle, names[k], np.dtype(dtype), row)
        except BaseException:
            self.abort()
            raise

    def _write_npz(self) -> None:
        """The zip np.savez writes (stored members, zip64, a version 1.0 .npy header each):
        the first member closed with its header, the others' arrays copied from the spill
        files (:func:`_copy_member`)."""
        fmt = np.lib.format
        names = [*self._NPZ_FIELDS, "meta", *self.photon_fields]
        import zipfile
        if self._zip is None:  # every member spilled (_DirectMember.supported() is False)
            self._zip = zipfile.ZipFile(self.tmp, mode="w", compression=zipfile.ZIP_STORED,
                                        allowZip64=True)
        zf = self._zip
        for k in names:  # on a failure, abort() drops the zip (no central directory)
            if k == "meta":
                with zf.open("meta.npy", "w", force_zip64=True) as member:
                    fmt.write_array(member, np.array(self._meta))
                continue
            f, spill, dtype, row = self._spill[k]
            header = _npy_header(dtype, (int(self.n), *row))
            if f is None:
                self._direct.close(header)
                continue
            f.close()
            with zf.open(k + ".npy", "w", force_zip64=True) as member:
                member.write(header)
                _copy_member(zf, member, spill, self._crc.get(k, 0), self._COPY_BYTES)
        zf.close()
        self._zip = None
        self._drop_spill()

    def _drop_spill(self) -> None:
        self._crc = {}
        for _, spill, _, _ in self._spill.values():
            spill.unlink(missing_ok=True)
        self._spill = {}

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.close()
            except BaseException as failed:
                self.abort()
                name_the_file(failed, self.path, self.tmp)
                raise
        else:
            self.abort()
            name_the_file(exc, self.path, self.tmp)


def las_creation_date() -> datetime.date:
    """SOURCE_DATE_EPOCH's day (UTC) where it is set to a number of seconds, else
    LAS_CREATION_DATE: never the day of writing (reproducible builds' convention)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    try:
        return datetime.datetime.fromtimestamp(int(epoch), datetime.UTC).date()
    except (ValueError, OverflowError, OSError):
        return LAS_CREATION_DATE


def _las_header(laspy, cloud: PointCloud, meta_text: str):
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.creation_date = las_creation_date()
    # LAS stores scaled int32 coordinates: 0.1 mm steps around the (first) cloud's centre.
    centre = cloud.xyz.mean(axis=0) if len(cloud) else np.zeros(3)
    header.offsets = np.round(centre, 3)
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.add_extra_dims([laspy.ExtraBytesParams("range_m", np.float64),
                           laspy.ExtraBytesParams("cell_w", np.int32),
                           laspy.ExtraBytesParams("cell_h", np.int32),
                           laspy.ExtraBytesParams("sample", np.int32)]
                          + [laspy.ExtraBytesParams(k, np.int32) for k in ("count", "pulse")
                             if getattr(cloud, k) is not None])
    # A VLR holds at most 65,535 bytes; a request's meta (its conditions listed) can hold
    # more: records 1, 2, ... in order, joined on reading (_las_meta)
    data = meta_text.encode()
    parts = [data[i:i + LAS_VLR_BYTES] for i in range(0, len(data), LAS_VLR_BYTES)] or [b""]
    for k, part in enumerate(parts, start=1):
        header.vlrs.append(laspy.VLR(user_id="APCG", record_id=k, record_data=part,
                                     description="meta" if len(parts) == 1
                                     else f"meta {k} of {len(parts)}"))
    return header


LAS_VLR_BYTES = 65535  # a LAS VLR's record length is an unsigned 16-bit integer


def _las_meta(vlrs) -> dict:
    """The meta of _las_header's records (one, or several in record order)."""
    parts = sorted((v.record_id, bytes(v.record_data)) for v in vlrs if v.user_id == "APCG")
    return json.loads(b"".join(p for _, p in parts).decode()) if parts else {}


def _write_las(path: Path, tmp: Path, cloud: PointCloud, meta_text: str,
               compress: bool) -> None:
    laspy = _laspy(compress)
    las = _fill_las(path, laspy.LasData(_las_header(laspy, cloud, meta_text)), cloud)
    with open(tmp, "wb") as f:
        las.write(f, do_compress=compress)


def read_cloud(path) -> tuple[PointCloud, dict]:
    """Read a cloud written by :func:`write_cloud` or by another lidar tool (any PLY with x y z,
    LAS / LAZ); :func:`read_cloud_attributes` also gives the file's other per-point values."""
    cloud, meta, _ = read_cloud_attributes(path)
    return cloud, meta


def read_cloud_attributes(path) -> tuple[PointCloud, dict, dict[str, np.ndarray]]:
    """The cloud, its meta and every other per-point attribute of the file by name (length-n
    arrays in the file's numeric types, native byte order): LAS / LAZ dimensions of any point
    format (intensity, return_number, classification, gps_time, red / green / blue, extra bytes;
    an extra dimension of k numbers as name_0 .. name_k-1), PLY vertex properties, NPZ arrays.

    range_m, cell_w, cell_h and sample go into the cloud (range_m defaults to the norm of xyz,
    the cell indices to 0); a broken or truncated file raises InputError naming it."""
    path = Path(path)
    ext = _fmt(path)
    if not path.exists():
        raise InputError(f"no such point cloud file: {path}")
    try:
        read = {".npz": _read_npz, ".ply": _read_ply}.get(ext, _read_las)
        xyz, cols, meta = read(path)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any parse failure is a broken file to the user
        raise InputError(f"cannot read point cloud {path}: {exc}") from exc
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(f"cannot read point cloud {path}: {int(bad.sum())} of its {n} points "
                         f"have a coordinate that is not a finite number (the first: point "
                         f"{int(np.argmax(bad))}, {xyz[np.argmax(bad)].tolist()})")
    own = {k: _own_column(path, k, cols.pop(k, None), n) for k in _OWN}
    with np.errstate(over="ignore"):  # an overflow is refused by PointCloud below
        r = own["range_m"] if own["range_m"] is not None else np.linalg.norm(xyz, axis=1)
    zeros = np.zeros(n, np.int32)
    photon = _photon_columns(path, ext, cols, meta, n)
    try:  # e.g. a range taken as the norm of coordinates near 1e308: not finite
        cloud = PointCloud(xyz, r, own["cell_w"] if own["cell_w"] is not None else zeros,
                           own["cell_h"] if own["cell_h"] is not None else zeros,
                           own["sample"], **photon)
    except InputError as exc:
        raise InputError(f"cannot read point cloud {path}: {exc}") from None
    return cloud, meta, cols


def _own_column(path, k: str, v, n: int):
    """One of the cloud's own columns as read: finite numbers (range_m), else whole numbers
    that fit the type the cloud stores them in; else an InputError naming the file, the
    field, a refused value and what is accepted."""
    if v is None:
        return None
    v = np.asarray(v)
    finite = v.dtype.kind in "biu" or (v.dtype.kind == "f" and np.isfinite(v).all())
    whole = k == "range_m" or v.dtype.kind in "biu" or (finite and (v == np.round(v)).all())
    if v.shape != (n,) or not finite or not whole:
        raise InputError(f"cannot read point cloud {path}: its {k!r} values are not "
                         f"{'finite numbers' if k == 'range_m' else 'whole numbers'}, "
                         f"one per point ({n} points; got shape {v.shape}, "
                         f"type {v.dtype})")
    if k in _STORED and n:
        info = np.iinfo(_STORED[k])
        out = not_held(v, _STORED[k])
        if out.any():
            i = int(np.argmax(out))
            raise InputError(f"cannot read point cloud {path}: its {k!r} value {v[i]!r} "
                             f"(point {i}) does not fit; accepted: whole numbers from "
                             f"{info.min} to {info.max}")
    return v


def _photon_columns(path, ext: str, cols: dict, meta, n: int) -> dict:
    """A photon cloud's label, count and pulse where the file's meta names its sensor (an
    APCG photon cloud; another tool's "label" column stays an attribute): PLY and NPZ store
    them by name, LAS the label as its classification (LAS_CLASS). They stay in ``cols``
    too, as the file's attributes."""
    if not (isinstance(meta, dict) and meta.get("sensor")):
        return {}
    out = {k: _own_column(path, k, cols[k], n) for k in PHOTON_FIELDS if k in cols}
    if ext in (".las", ".laz") and "classification" in cols:
        code = np.asarray(cols["classification"])
        signal, noise = LAS_CLASS[1], LAS_CLASS[0]
        if np.isin(code, (signal, noise)).all():  # codes another tool gave: no labels
            out["label"] = (code == signal).astype(np.uint8)
    return out


def _laspy(compressed: bool):
    try:
        import laspy
    except ImportError as exc:
        raise InputError("LAS files need laspy: pip install 'apcg[io]'") from exc
    if compressed and not laspy.LazBackend.detect_available():
        raise InputError("LAZ files need lazrs: pip install lazrs (or pip install 'laspy[lazrs]')")
    return laspy


def _read_npz(path: Path):
    with np.load(path, allow_pickle=False) as z:
        if "xyz" not in z.files:
            raise InputError(f"{path}: the NPZ file has no 'xyz' array (it has {z.files})")
        xyz = np.asarray(z["xyz"], np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            if xyz.size != 0:
                raise InputError(f"{path}: the NPZ file's 'xyz' array has shape {xyz.shape}; "
                                 "a cloud's is (n, 3), one row of x, y, z per point")
            xyz = xyz.reshape(0, 3)
        meta = json.loads(str(z["meta"])) if "meta" in z.files else {}
        cols = {}
        for k in z.files:
            a = z[k] if k not in ("xyz", "meta") else None
            # other arrays are per-point values only when they have one number per point
            if a is not None and (k in _OWN or (a.ndim == 1 and len(a) == len(xyz)
                                                and a.dtype.kind in "biuf")):
                cols[k] = a
    return xyz, cols, meta


def _read_las(path: Path):
    laspy = _laspy(path.suffix.lower() == ".laz")
    try:
        las = laspy.read(path)
    except laspy.errors.LaspyException as exc:
        if laspy.LazBackend.detect_available():
            raise
        # a compressed file named .las also needs the LAZ backend
        raise InputError(f"cannot read point cloud {path}: {exc} (if it is compressed LAZ: "
                         "pip install lazrs)") from exc
    n, announced = len(las.points), las.header.point_count
    if n != announced:  # laspy reads a short file as fewer (or no) points without complaint
        raise InputError(f"{path} is truncated: {announced} points announced, {n} stored")
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], 1)
    cols = {}
    for name in las.point_format.dimension_names:
        if name in ("X", "Y", "Z"):  # the unscaled integers behind las.x, las.y, las.z
            continue
        a = np.asarray(las[name])
        if a.ndim == 2:
            cols.update({f"{name}_{i}": a[:, i].copy() for i in range(a.shape[1])})
        else:
            cols[name] = a
    return xyz, cols, _las_meta(las.header.vlrs)


def ply_header_end(data: bytes) -> int:
    """Where a PLY's ``end_header`` line starts in ``data``, -1 if it has none: a line of its
    own, since a comment (our meta, a tool's note) may hold the words. Every PLY reader of the
    package finds the header's end here (clouds, and the catalog's mesh files)."""
    found = _END_HEADER.search(data)
    return found.start() if found else -1


def _ply_header(path: Path, data: bytes):
    """format, meta, elements [(name, count, [(property, dtype code, or None for a list)])] and
    where the body starts."""
    end = ply_header_end(data)
    body = data.find(b"\n", end) + 1 if end >= 0 else 0
    if not data.startswith(b"ply") or body == 0:
        raise InputError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    fmt, meta, elements = None, {}, []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        try:
            if parts[:2] == ["comment", "meta"]:
                meta = _json_dict(line.split("meta", 1)[1])
            elif parts[:1] == ["format"]:
                fmt = parts[1]
            elif parts[:1] == ["element"]:
                elements.append((parts[1], int(parts[2]), []))
                if elements[-1][1] < 0:
                    raise ValueError
            elif parts[:1] == ["property"]:
                is_list = parts[1] == "list"
                types, name = (parts[2:4], parts[4]) if is_list else (parts[1:2], parts[2])
                codes = [_PLY_NAMES[t] for t in types]
                elements[-1][2].append((name, None if is_list else codes[0]))
        except (IndexError, KeyError, ValueError):
            raise InputError(f"{path}: bad PLY header line {line!r} (types: "
                             f"{' '.join(sorted(_PLY_NAMES))})") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{path}: unknown PLY format {fmt!r}; accepted: ascii, "
                         "binary_little_endian, binary_big_endian")
    return fmt, meta, elements, body


_END_HEADER = re.compile(rb"^end_header[ \t]*\r?$", re.MULTILINE)


def _json_dict(text: str) -> dict:
    """Our meta comment; another tool's comment that happens to start with "meta" is no meta."""
    try:
        meta = json.loads(text)
    except ValueError:
        return {}
    return meta if isinstance(meta, dict) else {}


def _ascii_values(path, name: str, v: np.ndarray, code: str) -> np.ndarray:
    """An ASCII PLY property's numbers (read as float64) in its declared type: a value the
    type cannot hold (not whole, or out of its range) is refused, not truncated or wrapped
    by the cast."""
    t = np.dtype(code)
    if t.kind == "f":
        with np.errstate(over="ignore"):
            out = v.astype(t)
        bad = np.isfinite(v) & ~np.isfinite(out)  # too large for a float property
        accepted = f"numbers of magnitude up to {np.finfo(t).max:.6g}"
    else:
        info = np.iinfo(t)
        bad = not_held(v, t)
        out = None if bad.any() else v.astype(t)
        accepted = f"whole numbers from {info.min} to {info.max}"
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"cannot read point cloud {path}: its {name!r} value "
                         f"{repr(float(v[i])).removesuffix('.0')} (vertex {i}) does not "
                         f"fit the declared type {_PLY_TYPES[code]}; accepted: {accepted}")
    return out


def _read_ply(path: Path):
    with open(path, "rb") as f:
        data = f.read()
    fmt, meta, elements, body = _ply_header(path, data)
    at = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if at is None:
        raise InputError(f"{path}: the PLY file has no vertex element")
    _, n, props = elements[at]
    if any(t is None for _, t in props):
        raise InputError(f"{path}: list properties on vertices are not supported")
    if fmt == "ascii":
        # one line per element: skip the lines of the elements before the vertices
        lines = [ln for ln in data[body:].splitlines() if ln.strip()]
        skip = sum(e[1] for e in elements[:at])
        tokens = b" ".join(lines[skip:skip + n]).split()
        if len(tokens) != n * len(props):
            raise InputError(f"{path} is truncated or malformed: {n} vertices of {len(props)} "
                             f"values announced, {len(tokens)} values found")
        rec = np.array(tokens, dtype=np.float64).reshape(n, len(props))
        cols = {p: _ascii_values(path, p, rec[:, i], t) for i, (p, t) in enumerate(props)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        for name, count, eprops in elements[:at]:
            if any(t is None for _, t in eprops):
                raise InputError(f"{path}: element {name!r} before the vertices has list "
                                 "properties, so where the vertices start in this binary PLY "
                                 "is unknown; write the vertex element first")
            body += count * np.dtype([(p, endian + t) for p, t in eprops]).itemsize
        dt = np.dtype([(p, endian + t) for p, t in props])
        if len(data) - body < n * dt.itemsize:
            raise InputError(f"{path} is truncated: {n} vertices announced, fewer stored")
        rec = np.frombuffer(data, dtype=dt, count=n, offset=body)
        cols = {p: rec[p].astype(rec[p].dtype.newbyteorder("=")) for p, _ in props}
    if not {"x", "y", "z"} <= set(cols):
        raise InputError(f"{path}: vertices have no x, y, z")
    xyz = np.stack([cols.pop("x"), cols.pop("y"), cols.pop("z")], 1)
    return xyz, cols, meta
