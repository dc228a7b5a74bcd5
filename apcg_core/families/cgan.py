"""The paper's cGAN ("cgan") at generation time (SPEC sections 5-6): nu + noise -> generator ->
DeNorm -> Im2PC.

A cGAN model is a directory with ``model.json`` (network, condition space, lidar, types, tau) and
``generator.onnx``. It runs through onnxruntime (no torch needed: this is how Blender runs it) or
through torch, whose weights are read from the same ONNX file, so both give the same images.
Noise is drawn with numpy from the seed, so the runtime never changes the result. Its networks
are :mod:`apcg_core.nn.cgan` (torch); its training is ``training/families/cgan.py``.
"""

from __future__ import annotations

import numpy as np

from ..condition import NOISE_DIM, scale_ratio
from ..depth import TAU_DEFAULT, check_tau, denorm, im2pc
from ..errors import InputError, check_int
from ..typetable import Conditions
from .base import (
    _BROKEN,
    RUNTIMES,
    GenerationResult,
    ModelTypes,
    onnx_session,
    onnx_weights,
    onnxruntime,
)

FAMILY = "cgan"


class APCGModel(ModelTypes):
    """The paper's cGAN as exported: model.json + generator.onnx. ``tau`` is its Im2PC
    threshold (SPEC section 6); ``TAUS`` the candidates `apcg choose-tau` sweeps."""

    TAUS = (-0.99, -0.98, -0.95, -0.9, -0.8, -0.6, -0.3, 0.0)
    DEFAULT_TAU = TAU_DEFAULT

    check_tau = staticmethod(check_tau)  # Im2PC's threshold: the generator's tanh output

    def __init__(self, directory=None, runtime: str = "auto") -> None:
        self._read_model_json(directory)
        onnx_path = self.directory / "generator.onnx"
        if not onnx_path.is_file():
            raise InputError(f"{self.directory} is not a cGAN model (no generator.onnx; "
                             "`apcg export` makes one from a training run)")
        self.onnx_path = onnx_path
        self._check_image_size()
        self.tau = self.meta_tau()
        self.norm = self.meta_flag("norm", True)
        if runtime not in RUNTIMES:
            raise InputError(f"runtime must be one of {RUNTIMES}, got {runtime!r}")
        self.runtime = self._pick(runtime)
        self._session = None
        self._torch_g = None

    # Its network takes the type as one scaled number of nu: `apcg teach` cannot add one.
    TEACHABLE = False

    def _check_image_size(self) -> None:
        """The generator draws net.height x net.width_px images (apcg_core.nn.cgan.NetConfig;
        64 x 256 when model.json's net leaves them out), which Im2PC reads as the lidar's
        window: a model.json whose lidar has another window (edited, or exported with another
        lidar's dataset) is refused at load, naming the file, not by Im2PC mid-generation."""
        net = self.meta.get("net")
        net = net if isinstance(net, dict) else {}
        h, w = net.get("height", 64), net.get("width_px", 256)
        if (h, w) != (self.lidar.height, self.lidar.width):
            raise InputError(f"{self.directory / 'model.json'}: its lidar's window is "
                             f"{self.lidar.width} x {self.lidar.height} cells (width x height) "
                             f"but its generator draws {w!r} x {h!r} images (net.width_px x "
                             "net.height): the model's files and model.json disagree; "
                             f"{_BROKEN}")

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
            ort = onnxruntime("generation without torch needs onnxruntime: "
                              "pip install onnxruntime")
            self._session = onnx_session(self.onnx_path, ort.SessionOptions())
        return self._session

    def torch_generator(self):
        """The generator as a torch module (eval mode), weights read from the ONNX file."""
        if self._torch_g is None:
            import torch

            from ..nn.cgan import Generator, NetConfig
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
        # a whole number >= 0: numpy refuses a negative one, and draws unseeded noise from None
        check_int("seed", seed, 0)
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


class _CGANLoader:
    """The cGAN as the core knows it: its loader (training adds the rest:
    training/families/cgan.py)."""

    name = FAMILY

    @staticmethod
    def load(directory, runtime: str = "auto"):
        return APCGModel(directory, runtime=runtime)


LOADER = _CGANLoader()

__all__ = ["FAMILY", "LOADER", "APCGModel"]
