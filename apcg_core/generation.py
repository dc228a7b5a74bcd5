"""APCG generation (paper Fig. 1, SPEC sections 5-6): nu + noise -> generator -> DeNorm -> Im2PC.

A model is a directory with ``model.json`` (network, condition space, lidar, types, tau) and
``generator.onnx``. It runs through onnxruntime (no torch needed: this is how Blender runs it) or
through torch, whose weights are read from the same ONNX file, so both give the same images.
Noise is drawn with numpy from the seed, so the runtime never changes the result.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cloud import PointCloud
from .condition import NOISE_DIM, Condition, ConditionSpace, scale_ratio
from .depth import TAU_DEFAULT, denorm, im2pc
from .errors import InputError, check_int
from .families import family_of, get_family, read_model_meta, register
from .lidar import LidarParams
from .typetable import Conditions, TypeTable

DEFAULT_MODEL_DIR = Path(__file__).with_name("models") / "default"
RUNTIMES = ("auto", "onnx", "torch")


def default_model_dir() -> Path:
    return DEFAULT_MODEL_DIR


@dataclass
class GenerationResult:
    cloud: PointCloud  # stacked; cloud.sample indexes rows of ``conditions``
    images: np.ndarray  # (N, H, W) denormalised depth images (empty for point-set families)
    conditions: Conditions  # the condition of each cloud, in the model's type table

    @property
    def table(self) -> np.ndarray:
        return self.conditions.table


class ModelTypes:
    """What every model knows of its types and conditions (from its model.json): the base of
    every family's model. ``types`` is the model's :class:`TypeTable`; a condition from
    elsewhere reaches the model as :class:`Conditions` and is mapped into it by name."""

    directory: Path
    meta: dict
    types: TypeTable
    space: ConditionSpace
    lidar: LidarParams

    def __init__(self, directory=None) -> None:
        """A model's type table and condition space alone (no network loaded)."""
        self._read_model_json(directory)

    def _read_model_json(self, directory) -> None:
        self.directory = Path(directory) if directory else DEFAULT_MODEL_DIR
        self.meta = read_model_meta(self.directory)
        try:
            self.space = ConditionSpace.from_dict(self.meta["condition_space"])
            self.lidar = LidarParams.from_dict(self.meta["lidar"])
        except (KeyError, TypeError) as exc:
            raise InputError(f"{self.directory / 'model.json'} is incomplete ({exc!r})") from exc
        self.types = TypeTable.from_records(self.meta["types"],
                                            owner=f"model {self.directory}")

    @property
    def family(self) -> str:
        return str(self.meta.get("family", "cgan"))

    def type_name(self, key) -> str:
        """The catalog name of ``key``: a name this model knows, or a catalog index."""
        if isinstance(key, str) and key.strip() in self.types:
            return key.strip()
        if isinstance(key, (int, np.integer)) or (isinstance(key, str) and key.strip().isdigit()):
            from .catalog.catalog import default_catalog
            return default_catalog().get(int(key)).name
        self.types.code(key)  # refuses, naming what the model knows
        return key

    def conditions(self, names, pose) -> Conditions:
        """Conditions for type ``names`` (one per row; names or catalog indices) at ``pose``
        (N, 5) [r0 m, beta0, pitch, yaw, roll rad], in this model's type table."""
        names = [names] if isinstance(names, (str, int, np.integer)) else list(names)
        return Conditions.from_names(self.types, [self.type_name(n) for n in names], pose)

    def condition(self, type_key, range_m, elevation, pitch=0.0, yaw=0.0,
                  roll=0.0) -> Conditions:
        """One condition (radians, metres), checked physically."""
        row = Condition(0, range_m, elevation, pitch, yaw, roll).as_array()[1:]
        return self.conditions([type_key], row[None])

    def depth_length(self, codes) -> np.ndarray:
        return self.types.column("depth_length_m").astype(np.float64)[
            np.asarray(codes, dtype=np.int64)]

    def repeated_conditions(self, conditions: Conditions, count) -> np.ndarray:
        """``conditions`` mapped by name into this model's types, checked against its
        condition space, each row ``count`` times (the table the model generates from)."""
        if not isinstance(conditions, Conditions):
            raise InputError("a model generates from Conditions (rows with the type table "
                             "their codes refer to; see model.conditions(names, pose)), not "
                             f"a bare {type(conditions).__name__}")
        table = self.space.check(conditions.recoded(self.types))
        return np.repeat(table, check_int("count", count, 1), axis=0)

    def result(self, cloud: PointCloud, images, table: np.ndarray) -> GenerationResult:
        return GenerationResult(cloud, images, Conditions(self.types, table))


class _CGANFamily:
    """The paper's cGAN as the core knows it: its loader (training adds the rest)."""

    name = "cgan"

    @staticmethod
    def load(directory, runtime: str = "auto"):
        return APCGModel(directory, runtime=runtime)


def load_model(directory=None, runtime: str = "auto"):
    """The model in ``directory`` (default: the shipped one), opened by the family that made
    it (model.json ``family``), whatever that family is."""
    from . import plus  # noqa: F401 - registers the APCG+ loader (the core's second family)
    d = Path(directory) if directory else DEFAULT_MODEL_DIR
    if runtime not in RUNTIMES:
        raise InputError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
    return get_family(family_of(d)).load(d, runtime=runtime)


class APCGModel(ModelTypes):
    """The paper's cGAN as exported: model.json + generator.onnx. ``tau`` is its Im2PC
    threshold (SPEC section 6); ``TAUS`` the candidates `apcg choose-tau` sweeps."""

    TAUS = (-0.99, -0.98, -0.95, -0.9, -0.8, -0.6, -0.3, 0.0)
    DEFAULT_TAU = TAU_DEFAULT

    @staticmethod
    def check_tau(tau) -> float:
        if not (isinstance(tau, (int, float, np.floating)) and np.isfinite(tau)
                and -1.0 <= tau < 1.0):
            raise InputError(f"tau = {tau!r} is out of range; accepted: -1 <= tau < 1 (the "
                             "generator's tanh output, background -1)")
        return float(tau)

    def __init__(self, directory=None, runtime: str = "auto") -> None:
        self._read_model_json(directory)
        onnx_path = self.directory / "generator.onnx"
        if not onnx_path.is_file():
            raise InputError(f"{self.directory} is not a cGAN model (no generator.onnx; "
                             "`apcg export` makes one from a training run)")
        self.onnx_path = onnx_path
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
            self._session = onnx_session(self.onnx_path, ort.SessionOptions())
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
    def generate(self, conditions: Conditions, count: int = 1,
                 seed: int = 0) -> GenerationResult:
        """Point clouds for ``conditions`` (mapped by type name into this model's types),
        ``count`` samples each (rows repeated), noise from ``seed``."""
        table = self.repeated_conditions(conditions, count)
        nu = self.space.encode(table)
        noise = np.random.default_rng(seed).standard_normal((len(table), NOISE_DIM))
        img_n = self.images_from(noise, nu)
        # a model trained without Norm (eq. 17) made the depth image itself
        d = denorm(img_n, scale_ratio(table[:, 1])) if self.norm else img_n
        codes = table[:, 0].astype(np.int64)
        cloud = im2pc(d, table[:, 1], table[:, 2], self.depth_length(codes), self.lidar,
                      tau=self.tau)
        return self.result(cloud, d, table)


register(_CGANFamily())


_BROKEN = ("a partial or corrupt file: export the model again (`apcg export`), or copy it "
           "again from where it came")


def onnx_session(path, options):
    """An onnxruntime session over ``path``; a file it cannot load is named, not a traceback."""
    import onnxruntime as ort

    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for bad files
        raise InputError(f"{path} cannot be loaded ({type(exc).__name__}): {_BROKEN}") from exc


def onnx_weights(path) -> dict:
    """name -> numpy array of every weight in an ONNX file (initializers, through the Identity
    aliases the exporter makes for tensors that happen to be equal)."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError as exc:
        raise InputError("reading ONNX weights into torch needs the onnx package: "
                         "pip install 'apcg[train]'") from exc
    try:
        m = onnx.load(str(path))
    except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
        raise InputError(f"{path} cannot be read as ONNX ({type(exc).__name__}): "
                         f"{_BROKEN}") from exc
    w = {i.name: numpy_helper.to_array(i).copy() for i in m.graph.initializer}
    for n in m.graph.node:
        if n.op_type == "Identity" and n.input[0] in w:
            w[n.output[0]] = w[n.input[0]]
    return w


def conditions_from_csv(path, model: ModelTypes) -> Conditions:
    """Rows ``type,range_m,elevation_deg,pitch_deg,yaw_deg,roll_deg`` (header required; the
    type by catalog name, or catalog index), in the model's type table. A dataset's
    conditions.csv (its ``type_name`` column) is read as it is."""
    import csv

    from .lidar import DEG
    need = ["type", "range_m", "elevation_deg", "pitch_deg", "yaw_deg", "roll_deg"]
    known: dict = {}
    if not Path(path).is_file():
        raise InputError(f"conditions CSV {path} does not exist (or is not a file)")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            fields = reader.fieldnames or []
            type_col = "type" if "type" in fields else "type_name"
            if any(k not in fields for k in [type_col, *need[1:]]):
                raise InputError(f"{path}: a conditions CSV needs the header {','.join(need)} "
                                 "(or a dataset's conditions.csv)")
            rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path} is not a readable CSV text file ({exc})") from exc
    if not rows:
        raise InputError(f"{path} has no conditions")
    names = []
    for i, r in enumerate(rows):
        key = (r[type_col] or "").strip()
        if key not in known:
            try:
                known[key] = model.type_name(key)
            except InputError as exc:
                raise InputError(f"{path}, row {i + 1}: {exc}") from exc
        names.append(known[key])
    try:
        pose = np.array([[float(r[k]) for k in need[1:]] for r in rows], dtype=np.float64)
    except (TypeError, ValueError):
        pose = None
    if pose is not None:
        pose[:, 1:] *= DEG
        bad = ~np.isfinite(pose).all(axis=1) | (pose[:, 0] <= 0) \
            | (np.abs(pose[:, 1]) >= np.pi / 2) | (np.abs(pose[:, 2]) > np.pi / 2) \
            | (np.abs(pose[:, 3:]) > np.pi).any(axis=1)
    if pose is None or bad.any():  # the first bad row, with the physical check's own words
        for i, r in enumerate(rows):
            try:
                Condition(0, float(r["range_m"]), *(float(r[k]) * DEG for k in need[2:]))
            except (TypeError, ValueError, InputError) as exc:
                raise InputError(f"{path}, row {i + 1}: {exc}") from exc
    return model.conditions(names, pose)


__all__ = ["NOISE_DIM", "APCGModel", "Conditions", "GenerationResult", "ModelTypes",
           "conditions_from_csv", "default_model_dir", "load_model"]
