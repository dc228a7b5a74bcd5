"""APCG generation (paper Fig. 1, SPEC sections 5-6): nu + noise -> generator -> DeNorm -> Im2PC.

A model is a directory with ``model.json`` (network, condition space, lidar, types, tau) and
``generator.onnx``. It runs through onnxruntime (no torch needed: this is how Blender runs it) or
through torch, whose weights are read from the same ONNX file, so both give the same images.
Noise is drawn with numpy from the seed, so the runtime never changes the result.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cloud import PointCloud
from .condition import Condition, ConditionSpace, scale_ratio
from .depth import TAU_DEFAULT, denorm, im2pc
from .errors import InputError, check_int
from .lidar import LidarParams

DEFAULT_MODEL_DIR = Path(__file__).with_name("models") / "default"
NOISE_DIM = 100
RUNTIMES = ("auto", "onnx", "torch")


def default_model_dir() -> Path:
    return DEFAULT_MODEL_DIR


@dataclass
class GenerationResult:
    cloud: PointCloud  # stacked; cloud.sample indexes rows of ``table`` x count
    images: np.ndarray  # (N, H, W) denormalised depth images
    table: np.ndarray  # (N, 6) the condition of each image (type column = model type code)


class ModelTypes:
    """The lookups every generative model shares over its ``types`` (from model.json)."""

    types: list[dict]
    space: ConditionSpace

    def type_code(self, key) -> int:
        """The model's code of a type given by catalog name or catalog index."""
        for t in self.types:
            if (isinstance(key, (int, np.integer)) and t["catalog_index"] == int(key)) or (
                    isinstance(key, str) and t["name"].lower() == key.lower()):
                return int(t["code"])
        raise InputError(f"type {key!r} is not one this model was trained on; it knows: "
                         f"{', '.join(t['name'] for t in self.types[:12])}"
                         f"{' ...' if len(self.types) > 12 else ''}")

    def depth_length(self, codes) -> np.ndarray:
        lengths = np.array([t["depth_length_m"] for t in self.types])
        return lengths[np.asarray(codes, dtype=np.int64)]

    def condition_row(self, type_key, range_m, elevation, pitch, yaw, roll) -> np.ndarray:
        cond = Condition(self.type_code(type_key), range_m, elevation, pitch, yaw, roll)
        return cond.as_array()

    def repeated_conditions(self, table, count) -> np.ndarray:
        """``table`` checked against the model's condition space, each row ``count`` times."""
        table = self.space.check(table)
        return np.repeat(table, check_int("count", count, 1), axis=0)


def load_model(directory=None, runtime: str = "auto"):
    """The model in ``directory`` (default: the shipped one): the cGAN, or a comparison family
    (model.json's ``family``) whose loader an installed package registers under the
    ``apcg.model_families`` entry points (the training package registers the three of its own;
    this core package never imports it)."""
    d = Path(directory) if directory else DEFAULT_MODEL_DIR
    meta = d / "model.json"
    family = "cgan"
    if meta.exists():
        try:
            family = json.loads(meta.read_text()).get("family", "cgan")
        except (json.JSONDecodeError, AttributeError) as exc:
            raise InputError(f"{meta} is not a readable model.json: {exc}") from exc
    if family == "cgan":
        return APCGModel(d, runtime=runtime)
    from importlib.metadata import entry_points
    loaders = {ep.name: ep for ep in entry_points(group="apcg.model_families")}
    if family not in loaders:
        raise InputError(f"{d} is a {family!r} model; loading it needs a package that registers "
                         f"that family (pip install 'apcg[train]'); registered: "
                         f"{', '.join(sorted(loaders)) or 'none'}")
    return loaders[family].load()(d)


class APCGModel(ModelTypes):
    def __init__(self, directory=None, runtime: str = "auto") -> None:
        self.directory = Path(directory) if directory else DEFAULT_MODEL_DIR
        meta_path = self.directory / "model.json"
        onnx_path = self.directory / "generator.onnx"
        if not meta_path.exists() or not onnx_path.exists():
            raise InputError(f"{self.directory} is not an APCG model (needs model.json and "
                             "generator.onnx; `apcg export` makes one from a training run)")
        self.meta = json.loads(meta_path.read_text())
        self.onnx_path = onnx_path
        self.space = ConditionSpace.from_dict(self.meta["condition_space"])
        self.lidar = LidarParams.from_dict(self.meta["lidar"])
        self.types = self.meta["types"]
        self.tau = float(self.meta.get("tau", TAU_DEFAULT))
        self.norm = bool(self.meta.get("norm", True))
        if runtime not in RUNTIMES:
            raise InputError(f"runtime must be one of {RUNTIMES}, got {runtime!r}")
        self.runtime = self._pick(runtime)
        self._session = None
        self._torch_g = None

    # --- runtimes --------------------------------------------------------------------------------
    @staticmethod
    def _pick(runtime: str) -> str:
        if runtime != "auto":
            return runtime
        try:
            import onnx  # noqa: F401
            import torch  # noqa: F401
            return "torch"
        except ImportError:
            return "onnx"

    def _onnx_session(self):
        if self._session is None:
            try:
                import onnxruntime as ort
            except ImportError as exc:
                raise InputError("generation without torch needs onnxruntime: "
                                 "pip install onnxruntime") from exc
            opts = ort.SessionOptions()
            self._session = ort.InferenceSession(str(self.onnx_path), opts,
                                                 providers=["CPUExecutionProvider"])
        return self._session

    def torch_generator(self):
        """The generator as a torch module (eval mode), weights read from the ONNX file."""
        if self._torch_g is None:
            import torch

            from .nn import Generator, NetConfig
            g = Generator(NetConfig(**self.meta["net"]))
            state = onnx_weights(self.onnx_path)
            own = g.state_dict()
            missing = [k for k in own if k not in state and not k.endswith("num_batches_tracked")]
            if missing:
                raise InputError(f"{self.onnx_path} lacks weights {missing[:5]}")
            g.load_state_dict({k: torch.from_numpy(state[k]) if k in state else own[k]
                               for k in own})
            self._torch_g = g.eval()
        return self._torch_g

    def images_from(self, noise: np.ndarray, nu: np.ndarray, batch: int = 256) -> np.ndarray:
        """Normalised images (N, H, W) for noise (N, 100) and nu (N, 6), float32."""
        noise = np.ascontiguousarray(noise, np.float32)
        nu = np.ascontiguousarray(nu, np.float32)
        out = []
        for s in range(0, len(nu), batch):
            z, c = noise[s:s + batch], nu[s:s + batch]
            if self.runtime == "onnx":
                img = self._onnx_session().run(None, {"noise": z, "nu": c})[0]
            else:
                import torch
                with torch.no_grad():
                    img = self.torch_generator()(torch.from_numpy(z), torch.from_numpy(c)).numpy()
            out.append(img[:, 0])
        h, w = self.lidar.height, self.lidar.width
        return np.concatenate(out) if out else np.zeros((0, h, w), np.float32)

    # --- conditions ------------------------------------------------------------------------------
    def generate(self, table, count: int = 1, seed: int = 0) -> GenerationResult:
        """Point clouds for conditions ``table`` (N, 6) [type code, r0 m, beta0, pitch, yaw,
        roll rad], ``count`` samples each (rows repeated), noise from ``seed``."""
        table = self.repeated_conditions(table, count)
        nu = self.space.encode(table)
        noise = np.random.default_rng(seed).standard_normal((len(table), NOISE_DIM))
        img_n = self.images_from(noise, nu)
        # a model trained without Norm (eq. 17) made the depth image itself
        d = denorm(img_n, scale_ratio(table[:, 1])) if self.norm else img_n
        codes = table[:, 0].astype(np.int64)
        cloud = im2pc(d, table[:, 1], table[:, 2], self.depth_length(codes), self.lidar,
                      tau=self.tau)
        return GenerationResult(cloud, d, table)


def onnx_weights(path) -> dict:
    """name -> numpy array of every weight in an ONNX file (initializers, through the Identity
    aliases the exporter makes for tensors that happen to be equal)."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError as exc:
        raise InputError("reading ONNX weights into torch needs the onnx package: "
                         "pip install 'apcg[train]'") from exc
    m = onnx.load(str(path))
    w = {i.name: numpy_helper.to_array(i).copy() for i in m.graph.initializer}
    for n in m.graph.node:
        if n.op_type == "Identity" and n.input[0] in w:
            w[n.output[0]] = w[n.input[0]]
    return w


def conditions_from_csv(path, model: ModelTypes) -> np.ndarray:
    """Rows ``type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg`` (header required)."""
    import csv

    from .lidar import DEG
    need = ["type", "range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg"]
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or any(k not in reader.fieldnames for k in need):
            raise InputError(f"{path}: a conditions CSV needs the header {','.join(need)}")
        rows = []
        for i, r in enumerate(reader):
            try:
                key = int(r["type"]) if r["type"].strip().isdigit() else r["type"].strip()
                rows.append([model.type_code(key), float(r["range_m"]),
                             float(r["elevation_deg"]) * DEG, float(r["pitch_deg"]) * DEG,
                             float(r["yaw_deg"]) * DEG, float(r["roll_deg"]) * DEG])
            except (ValueError, InputError) as exc:
                raise InputError(f"{path}, row {i + 1}: {exc}") from exc
    if not rows:
        raise InputError(f"{path} has no conditions")
    return np.array(rows)


__all__ = ["APCGModel", "GenerationResult", "ModelTypes", "conditions_from_csv",
           "default_model_dir", "load_model"]
