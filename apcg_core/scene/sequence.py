"""The scene sequence format (issue 36; docs/SCENES.md) and its reader. numpy only.

A sequence directory (``apcg scene sequence SCENE.toml -o DIR``):

    sequence.json        the header, written first: format, version, the scene as read (lidar,
                         pointing, scan, sequence, targets), backend, supersample, quantize,
                         sensor, seed, frame count and the frame file pattern
    frames/000000.npz    one file per frame (the same layout as `apcg scene scan`'s NPZ)
    poses.csv            every target's pose at every frame's start, one row each (at the end)
    manifest.json        the frames' sha256, written last: the sequence is complete

A frame file (uncompressed NPZ, its bytes a function of the scene, the options and the frame
alone) holds per point ``xyz`` (scene frame, metres, float64), ``range_m``, ``cell_w``,
``cell_h``, ``sample`` (0: one cloud), ``instance`` (int32: the target's track id, 1-based,
its [[target]] position; 0 for a photon stage's noise point), ``type`` (the target's catalog
name; "" for noise) and, with a sensor, ``label`` / ``count`` / ``pulse`` (SPEC section 8);
per target (T rows, track id i at row i - 1) ``track_id``, ``track_type``, ``position``
(T, 3) and ``rotation`` (T, 3, 3) body -> scene (a body point p at position + rotation @ p;
det -1, the scene frame being left-handed as numbers), ``pose`` (T, 6: range_m, azimuth_deg,
elevation_deg, pitch_deg, yaw_deg, roll_deg, SPEC section 2's angles), ``points`` (its points
in this frame), ``in_window`` and ``clipped`` (and, in a scene with a generated target,
``generated``: its points in this frame came from its model, False where it is simulated
(its model's fallback too) and where it is not in the window); and ``frame``,
``t_s`` (the frame's start) and ``meta`` (JSON).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..lidar import DEG

FORMAT = "apcg-scene-sequence"
FORMAT_VERSION = 1
FRAMES_DIR = "frames"
HEADER = "sequence.json"
POSES = "poses.csv"
MANIFEST = "manifest.json"
POSE_COLUMNS = ("range_m", "azimuth_deg", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg")
CSV_COLUMNS = ("frame", "t_s", "track_id", "type", "x_m", "y_m", "z_m",
               *(f"r{i}{j}" for i in range(3) for j in range(3)), *POSE_COLUMNS, "points",
               "in_window")


def frame_file(frame: int) -> str:
    """A frame's file, relative to the sequence directory."""
    return f"{FRAMES_DIR}/{frame:06d}.npz"


def frame_arrays(scan, angles: np.ndarray, meta: dict) -> dict:
    """The arrays of one frame file (in their stored order) from a scanned frame (``scan``:
    cloud, instance, type names, poses) and its targets' pose angles (T, 6; metres, rad)."""
    cloud = scan.cloud
    names = np.array(["", *scan.type_names])
    out = {"xyz": cloud.xyz, "range_m": cloud.range_m, "cell_w": cloud.cell_w,
           "cell_h": cloud.cell_h, "sample": np.zeros(len(cloud), np.int64),
           "instance": np.asarray(scan.instance, np.int32),
           "type": names[np.asarray(scan.instance, np.int64)]}
    for f in cloud.photon_fields:
        out[f] = getattr(cloud, f)
    pose = angles.copy()
    pose[:, 1:] /= DEG
    out.update(track_id=np.arange(1, len(scan.type_names) + 1, dtype=np.int32),
               track_type=np.array(scan.type_names), position=scan.position,
               rotation=scan.rotation, pose=pose, points=scan.points_of(),
               in_window=np.asarray(scan.in_window, bool),
               clipped=np.asarray(scan.clipped, bool))
    if getattr(scan, "generated", None) is not None:
        out["generated"] = np.asarray(scan.generated, bool)
    out.update(frame=np.int64(scan.frame),
               t_s=np.float64(scan.t_s), meta=np.array(json.dumps(meta, sort_keys=True)))
    return out


@dataclass
class Frame:
    """One frame read back: the cloud's arrays and the targets' poses."""

    frame: int
    t_s: float
    xyz: np.ndarray
    range_m: np.ndarray
    cell_w: np.ndarray
    cell_h: np.ndarray
    instance: np.ndarray
    type: np.ndarray
    track_id: np.ndarray
    track_type: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    pose: np.ndarray
    points: np.ndarray
    in_window: np.ndarray
    clipped: np.ndarray
    label: np.ndarray | None = None
    count: np.ndarray | None = None
    pulse: np.ndarray | None = None
    # (T,): its points came from its model (in the window, drawn by it; a scene that
    # generates)
    generated: np.ndarray | None = None
    meta: dict | None = None

    def points_of(self, track_id: int) -> np.ndarray:
        """The points (P, 3) of one target in this frame."""
        return self.xyz[self.instance == track_id]


def read_frame(path) -> Frame:
    """One frame file (or `apcg scene scan`'s NPZ)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            optional = ("label", "count", "pulse", "generated")
            need = [f for f in Frame.__dataclass_fields__ if f not in (*optional, "meta")]
            missing = [f for f in need if f not in z.files]
            if missing:
                raise InputError(f"{path}: not a scene frame file (no {', '.join(missing)})")
            kw = {f: z[f] for f in need}
            kw["frame"], kw["t_s"] = int(kw["frame"]), float(kw["t_s"])
            for f in optional:
                kw[f] = z[f] if f in z.files else None
            kw["meta"] = json.loads(str(z["meta"])) if "meta" in z.files else None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: cannot be read as a scene frame file ({exc})") from None
    xyz = np.asarray(kw["xyz"])
    if xyz.ndim != 2 or xyz.shape[1:] != (3,) or xyz.dtype.kind != "f" or not np.isfinite(
            xyz).all():
        raise InputError(f"{path}: its xyz is not (n, 3) finite numbers (shape {xyz.shape}, "
                         f"type {xyz.dtype}): a damaged frame; make the sequence again")
    return Frame(**kw)


def poses_csv_bytes(frames) -> bytes:
    """poses.csv of frames (Frame objects, in order): one row per target per frame."""
    lines = [",".join(CSV_COLUMNS)]
    for f in frames:
        for k in range(len(f.track_id)):
            row = [str(f.frame), repr(f.t_s), str(int(f.track_id[k])), str(f.track_type[k]),
                   *(repr(float(v)) for v in f.position[k]),
                   *(repr(float(v)) for v in f.rotation[k].ravel()),
                   *(repr(float(v)) for v in f.pose[k]), str(int(f.points[k])),
                   str(int(bool(f.in_window[k])))]
            lines.append(",".join(row))
    return ("\n".join(lines) + "\n").encode()


class Sequence:
    """A sequence directory read back: ``header`` (sequence.json), ``len()`` frames,
    ``frame(k)`` one :class:`Frame`, iteration over every frame, and ``tracks()``: per track
    id its type and its poses over the frames."""

    def __init__(self, directory) -> None:
        self.directory = Path(directory)
        head = self.directory / HEADER
        if not head.is_file():
            raise InputError(f"{self.directory} is not a scene sequence (no {HEADER}); make "
                             "one with `apcg scene sequence SCENE.toml -o DIR`")
        try:
            self.header = json.loads(head.read_text())
        except (ValueError, OSError) as exc:
            raise InputError(f"{head}: not a readable sequence header ({exc}); make the "
                             "sequence again") from None
        if not isinstance(self.header, dict):
            raise InputError(f"{head}: not a sequence header (a JSON object)")
        if self.header.get("format") != FORMAT:
            raise InputError(f"{head}: format {self.header.get('format')!r} is not "
                             f"{FORMAT!r}")
        if self.header.get("version", 0) > FORMAT_VERSION:
            raise InputError(f"{head}: version {self.header['version']} is newer than this "
                             f"reader's ({FORMAT_VERSION}); update apcg")
        frames = self.header.get("frames")
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
            raise InputError(f"{head}: frames = {frames!r} is not a count of frames")
        self.n_frames = frames
        self.complete = (self.directory / MANIFEST).is_file()

    def __len__(self) -> int:
        return self.n_frames

    def frame(self, k: int) -> Frame:
        if not 0 <= k < self.n_frames:
            raise InputError(f"frame {k} is not in this sequence; accepted: 0 .. "
                             f"{self.n_frames - 1}")
        path = self.directory / frame_file(k)
        if not path.is_file():
            raise InputError(f"{path} is missing: the sequence is not finished; run the same "
                             "`apcg scene sequence` command again to finish it")
        return read_frame(path)

    def __iter__(self):
        return (self.frame(k) for k in range(self.n_frames))

    def tracks(self) -> dict:
        """{track_id: {"type", "t_s" (F,), "position" (F, 3), "rotation" (F, 3, 3),
        "pose" (F, 6), "points" (F,)}} over every frame."""
        frames = list(self)
        out = {}
        for k, tid in enumerate(frames[0].track_id if frames else []):
            out[int(tid)] = {
                "type": str(frames[0].track_type[k]),
                "t_s": np.array([f.t_s for f in frames]),
                "position": np.stack([f.position[k] for f in frames]),
                "rotation": np.stack([f.rotation[k] for f in frames]),
                "pose": np.stack([f.pose[k] for f in frames]),
                "points": np.array([f.points[k] for f in frames])}
        return out


def load_sequence(directory) -> Sequence:
    """A sequence directory (see this module's docstring)."""
    return Sequence(directory)
