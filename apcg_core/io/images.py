"""Depth images in files: NPY (float32, exact) or PNG (16-bit grayscale, d in [-1, 1] mapped to
[0, 65535], so background is 0). The PNG writer is a few lines of zlib: no imaging library."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_path


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(
        ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png16_bytes(img: np.ndarray) -> bytes:
    """A 16-bit grayscale PNG of ``img`` (H, W) with values in [-1, 1]."""
    a = np.asarray(_depth_image(img), dtype=np.float64)
    v = np.round((np.clip(a, -1, 1) + 1.0) / 2.0 * 65535).astype(">u2")
    h, w = v.shape
    raw = b"".join(b"\x00" + v[i].tobytes() for i in range(h))
    head = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", head)
            + _png_chunk(b"IDAT", zlib.compress(raw, 6)) + _png_chunk(b"IEND", b""))


def _depth_image(img, path=None) -> np.ndarray:
    """``img`` as an array both formats can hold: (H, W) of at least one pixel (a PNG of
    none is invalid), finite numbers (a NaN would be written as background, an infinity as
    the far end) that stay finite as float32 (NPY); else an InputError naming the file."""
    where = f"cannot write {path}: " if path is not None else ""
    a = np.asarray(img)
    if a.ndim != 2 or a.size == 0:
        raise InputError(f"{where}a depth image has shape (H, W) with H, W >= 1, "
                         f"got {a.shape}")
    if a.dtype.kind not in "biuf":
        raise InputError(f"{where}a depth image holds numbers, got an array of {a.dtype}")
    with np.errstate(over="ignore"):
        bad = ~np.isfinite(a.astype(np.float32))
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"{where}a depth image holds finite numbers within float32's range; "
                         f"{int(bad.sum())} pixels do not (the first: row {row}, column {col}, "
                         f"{a[row, col].item()!r})")
    return a


def write_depth_image(path, img: np.ndarray) -> Path:
    path = Path(path)
    img = _depth_image(img, path)
    ext = path.suffix.lower()
    if ext not in DEPTH_IMAGE_SUFFIXES:
        raise InputError(f"unsupported depth image format {ext!r}; accepted: "
                         f"{', '.join(DEPTH_IMAGE_SUFFIXES)}")
    with atomic_path(path) as tmp:
        if ext == ".npy":
            with open(tmp, "wb") as f:
                np.save(f, img.astype(np.float32))
        else:
            tmp.write_bytes(png16_bytes(img))
    return path


DEPTH_IMAGE_SUFFIXES = (".npy", ".png")
