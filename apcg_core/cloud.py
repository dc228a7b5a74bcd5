"""A point cloud in the observation frame with its per-point attributes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, check_int

# Per-point photon attributes (SPEC section 8) and their stored types.
PHOTON_FIELDS = {"label": np.uint8, "count": np.int32, "pulse": np.int32}


@dataclass
class PointCloud:
    """Points (N, 3) in the observation frame (metres, float64) and per-point attributes.

    ``range_m`` is the slant range of each point, ``cell_w`` / ``cell_h`` its centred cell,
    ``sample`` the index of the sample a point belongs to when clouds of a batch are stacked.
    A photon cloud (SPEC section 8) also carries ``label`` (1 signal, 0 noise), ``count`` (the
    events in the point's bin) and, as events, ``pulse``; an ideal cloud has none of them.
    """

    xyz: np.ndarray
    range_m: np.ndarray
    cell_w: np.ndarray
    cell_h: np.ndarray
    sample: np.ndarray | None = None
    label: np.ndarray | None = None
    count: np.ndarray | None = None
    pulse: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = _points(self.xyz)
        n = len(self.xyz)
        self.range_m = _column("range_m", self.range_m, np.float64, n)
        self.cell_w = _column("cell_w", self.cell_w, np.int32, n)
        self.cell_h = _column("cell_h", self.cell_h, np.int32, n)
        if self.sample is not None:
            self.sample = _column("sample", self.sample, np.int64, n)
        for name, dtype in PHOTON_FIELDS.items():
            if getattr(self, name) is not None:
                setattr(self, name, _column(name, getattr(self, name), dtype, n))

    def checked(self) -> PointCloud:
        """This cloud checked again, as a new cloud sharing its arrays: a field replaced
        since it was built (another length, a list) is refused here, not broadcast into a
        file (writers call this)."""
        return PointCloud(self.xyz, self.range_m, self.cell_w, self.cell_h, self.sample,
                          *(getattr(self, f) for f in PHOTON_FIELDS))

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def empty(self) -> bool:
        return len(self.xyz) == 0

    @property
    def photon_fields(self) -> list[str]:
        """The photon attributes this cloud carries (none for an ideal cloud)."""
        return [f for f in PHOTON_FIELDS if getattr(self, f) is not None]

    def select(self, mask) -> PointCloud:
        def pick(a):
            return None if a is None else a[mask]
        return PointCloud(self.xyz[mask], self.range_m[mask], self.cell_w[mask],
                          self.cell_h[mask], pick(self.sample),
                          *(pick(getattr(self, f)) for f in PHOTON_FIELDS))

    def split(self, n_samples: int) -> list[PointCloud]:
        """One cloud per sample of a batch (points keep their order); every point's sample
        must be one of the ``n_samples``, so no point is dropped."""
        if self.sample is None:
            raise InputError("this cloud has no sample index; it is not a batch")
        n_samples = check_int("n_samples", n_samples, 0)
        if len(self.sample):
            lo, hi = int(self.sample.min()), int(self.sample.max())
            if lo < 0 or hi >= n_samples:
                raise InputError(f"PointCloud.sample holds {lo if lo < 0 else hi}, not a sample "
                                 f"of the {n_samples} asked for; accepted: 0 to "
                                 f"{n_samples - 1}")
        order = np.argsort(self.sample, kind="stable")
        bounds = np.searchsorted(self.sample[order], np.arange(n_samples + 1))
        return [self.select(order[bounds[i]:bounds[i + 1]]) for i in range(n_samples)]


def _numbers(name: str, value) -> np.ndarray:
    """``value`` as an array of numbers (bool, integer or real), else an InputError."""
    a = np.asarray(value)
    if a.dtype.kind not in "biuf":
        raise InputError(f"PointCloud.{name} must hold numbers, got an array of {a.dtype}")
    return a


def _points(value) -> np.ndarray:
    """xyz as float64 (n, 3) finite numbers; an empty array of any shape is no points."""
    a = _numbers("xyz", value)
    if a.size == 0:
        a = a.reshape(0, 3)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"PointCloud.xyz must have shape (n, 3), one row of x, y, z per "
                         f"point, got {a.shape}")
    a = np.asarray(a, dtype=np.float64)
    _check_finite("xyz", a)
    return a


def _column(name: str, value, dtype, n: int) -> np.ndarray:
    """One per-point field as ``dtype``, shape (n,): real fields finite; integer fields, when
    converted from another type, whole numbers that fit ``dtype`` (never truncated or
    wrapped). An array already of ``dtype`` is taken as it is, with no copy and no pass over
    its values (apcg generate builds a cloud per block)."""
    a = _numbers(name, value)
    if a.shape != (n,):
        raise InputError(f"PointCloud.{name} must have one value per point, shape ({n},); "
                         f"got shape {a.shape} for {n} points")
    if np.dtype(dtype).kind == "f":
        a = np.asarray(a, dtype=dtype)
        _check_finite(name, a)
    elif a.dtype != dtype:
        a = _integers(name, a, dtype)
    return a


def _check_finite(name: str, a: np.ndarray) -> None:
    # one sum, without a temporary: NaN or inf anywhere makes it non-finite (an overflow of
    # finite values too, which the exact test below then lets through)
    with np.errstate(over="ignore", invalid="ignore"):
        total = a.sum() if a.size else 0.0
    if not np.isfinite(total) and not np.isfinite(a).all():
        bad = ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)
        i = int(np.argmax(bad))
        raise InputError(f"PointCloud.{name} must hold finite numbers; {int(bad.sum())} of "
                         f"{len(a)} points do not (the first: point {i}, {a[i].tolist()})")


def not_held(a: np.ndarray, dtype) -> np.ndarray:
    """Mask of the values of ``a`` that the integer ``dtype`` does not hold as they are (not
    finite, not whole, or out of its range): what a cast would wrap or truncate. The one test
    of every reader and writer of clouds (PointCloud's fields, a file's columns)."""
    info = np.iinfo(dtype)
    if a.dtype.kind == "f":
        # compared as floats: iinfo.max + 1 is exact there, iinfo.max may not be
        return ~np.isfinite(a) | (a != np.round(a)) | (a < info.min) | (
            a >= float(info.max) + 1)
    return (a < info.min) | (a > info.max)


def _integers(name: str, a: np.ndarray, dtype) -> np.ndarray:
    """``a`` converted to the integer ``dtype`` where every value is a whole number that fits."""
    info = np.iinfo(dtype)
    if a.size and not np.can_cast(a.dtype, dtype):
        bad = not_held(a, dtype)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"PointCloud.{name} value {a[i].item()!r} (point {i}) does not "
                             f"fit; accepted: whole numbers from {info.min} to {info.max}")
    return a.astype(dtype)
