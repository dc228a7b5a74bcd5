"""FD-depth: a Fréchet distance over features of a depth-image encoder this project trains on
its own standard data. It stands in for the paper's FID (Inception v3 weights cannot be had
offline) and is never called FID.

    apcg fd-depth train --data DIR -o ENCODER [--epochs 4]
    apcg fd-depth score --encoder ENCODER --data DIR [--model DIR] [--pairs 2000]

The encoder is a small CNN that classifies the aircraft type from a normalised depth image
(Norm, eq. 17: what the generator makes); its 128 penultimate features are the space in which
the distance is measured. Its held-out accuracy is saved beside it. The score compares the
features of the test split's real images with those of generated images at the same conditions.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from apcg_core.condition import NOISE_DIM
from apcg_core.depth import norm, pc2im
from apcg_core.errors import InputError

from .data import DepthDataset

FEATURES = 128


class DepthEncoder(nn.Module):
    def __init__(self, n_types: int, height: int = 64, width: int = 256) -> None:
        super().__init__()
        chans = [1, 16, 32, 64, 128]
        layers = []
        for a, b in zip(chans[:-1], chans[1:], strict=True):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), nn.BatchNorm2d(b),
                       nn.LeakyReLU(0.2)]
        self.conv = nn.Sequential(*layers, nn.AdaptiveAvgPool2d((2, 4)), nn.Flatten())
        self.features = nn.Sequential(nn.Linear(128 * 8, FEATURES), nn.LeakyReLU(0.2))
        self.head = nn.Linear(FEATURES, n_types)
        self.shape = (height, width)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(self.conv(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.embed(x))


# The encoder's accuracy settles within a few epochs (default 4); beyond this many a request
# is a mistake (1e308 would be a step count no machine finishes, and no integer for ceil).
MAX_EPOCHS = 1000


def check_epochs(epochs) -> float:
    from numbers import Real
    if isinstance(epochs, bool) or not isinstance(epochs, Real) or not (
            math.isfinite(epochs) and 0 < epochs <= MAX_EPOCHS):
        raise InputError(f"--epochs {epochs!r} not accepted: a number > 0 and <= {MAX_EPOCHS} "
                         "(default 4: the encoder's accuracy settles within a few epochs, and "
                         "more only lengthens the run)")
    return float(epochs)


BATCH = 64  # the encoder's batch; a train split smaller than this trains in one batch of all


def train_encoder(data_dir, out_dir, epochs: float = 4.0, batch: int | None = None,
                  seed: int = 0, lr: float = 1e-3, progress: bool = True) -> dict:
    """Train the encoder on ``data_dir``'s train split in batches of ``batch`` (None: 64, or
    the whole split when it is smaller, said on stderr); its accuracy on the test split and
    the settings are written beside it (encoder.json)."""
    from apcg_core.errors import check_int
    epochs = check_epochs(epochs)
    if batch is not None:
        check_int("batch", batch, 2, 65536)
    check_int("seed", seed, 0, 2**32 - 1)
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
        raise InputError(f"lr must be a finite number > 0, got {lr!r}")
    torch.manual_seed(seed)
    train, test = DepthDataset(data_dir, "train"), DepthDataset(data_dir, "test")
    batch = _fitting_batch(batch, len(train), data_dir)
    n_types = len(train.types)
    enc = DepthEncoder(n_types, train.height, train.width)
    opt = torch.optim.Adam(enc.parameters(), lr=lr)
    steps = int(np.ceil(epochs * len(train) / batch))
    labels = train.conditions[:, 0].astype(np.int64)
    t0 = time.perf_counter()
    enc.train()
    for step in range(steps):
        idx = train.batch_indices(seed, step, batch)
        x = torch.from_numpy(train.images(idx))[:, None]
        loss = nn.functional.cross_entropy(enc(x), torch.from_numpy(labels[idx]))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if progress and (step + 1) % 100 == 0:
            print(f"encoder step {step + 1}/{steps} loss {float(loss):.3f}", file=sys.stderr,
                  flush=True)
    acc = accuracy(enc, test)
    from apcg_core.io.atomic import atomic_path
    from apcg_core.io.dataset import write_atomic
    out = Path(out_dir)
    with atomic_path(out / "encoder.pt") as tmp:
        torch.save({"state": enc.state_dict(), "n_types": n_types,
                    "shape": [train.height, train.width]}, tmp)
    meta = {"dataset": train.header.get("name"), "data": str(data_dir), "epochs": epochs,
            "steps": steps, "batch": batch, "seed": seed, "lr": lr,
            "test_accuracy_type": acc, "chance": 1.0 / n_types, "n_types": n_types,
            "train_seconds": round(time.perf_counter() - t0, 1), "features": FEATURES,
            "command": f"apcg fd-depth train --data {data_dir} -o {out_dir} --epochs {epochs:g} "
                       f"--seed {seed}"}
    write_atomic(out / "encoder.json", (json.dumps(meta, indent=1) + "\n").encode())
    return meta


def _fitting_batch(batch: int | None, n_train: int, data_dir) -> int:
    """The batch the encoder trains in: ``batch`` as asked, or (None) :data:`BATCH`, or the
    whole train split when it holds fewer samples than that (said once on stderr). A split of
    fewer than 2 samples, or fewer than an asked ``batch``, is refused naming the dataset."""
    if n_train < 2:
        raise InputError(f"{data_dir}: its train split holds {n_train} sample(s); the FD-depth "
                         "encoder trains on at least 2 (build the dataset with more samples "
                         "per type)")
    if batch is None:
        if n_train >= BATCH:
            return BATCH
        print(f"fd-depth train: {data_dir}'s train split holds {n_train} samples, fewer than "
              f"the batch of {BATCH}: training in batches of {n_train} (the whole split)",
              file=sys.stderr, flush=True)
        return n_train
    if n_train < batch:
        raise InputError(f"{data_dir}: its train split holds {n_train} samples, fewer than "
                         f"one batch of {batch}: give a batch of at most {n_train}")
    return batch


MADE_BY = "`apcg fd-depth train`"
# test pairs an FD-depth score needs: its floor splits the real images in two halves, each of
# at least 2 (a Fréchet distance's covariance needs 2 a side)
MIN_PAIRS = 4


def load_encoder(path) -> DepthEncoder:
    """The encoder in directory ``path``; a missing, empty, truncated or foreign encoder.pt is
    one InputError naming it (``training.distill.read_torch_state``), as is one whose weights
    do not fit the network its own header describes."""
    from .distill import holds, read_torch_state
    if Path(path).is_file():
        raise InputError(f"--encoder {path} is a file; give the encoder's directory (the -o "
                         f"of {MADE_BY}, holding encoder.pt)")
    p = Path(path) / "encoder.pt"
    if not p.exists():
        raise InputError(f"{path} holds no encoder.pt (make one with {MADE_BY})")
    st = read_torch_state(p, "an FD-depth encoder", ("state", "n_types", "shape"), MADE_BY)
    n, shape = st["n_types"], st["shape"]

    def whole(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= 1

    if not (whole(n) and isinstance(shape, (list, tuple)) and len(shape) == 2
            and all(whole(v) and v <= 1 << 16 for v in shape) and n <= 1 << 20):
        raise InputError(f"{p} describes no encoder: n_types {n!r}, shape {shape!r} (expected "
                         f"a type count >= 1 and [height, width] in pixels); {MADE_BY} "
                         "writes it again")
    enc = DepthEncoder(n, *shape)
    try:
        enc.load_state_dict(st["state"])
    except (RuntimeError, TypeError, AttributeError, KeyError) as exc:
        raise InputError(f"{p}: its weights ({holds(st['state'])}) do not fit the encoder "
                         f"of {n} types and {shape[0]} x {shape[1]} images it describes; "
                         f"{MADE_BY} writes it again") from exc
    return enc.eval()


def encoder_meta(path) -> dict:
    """An encoder directory's ``encoder.json`` (its accuracy, data, seed), checked."""
    p = Path(path) / "encoder.json"
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path} holds no encoder.json (make the encoder with "
                         f"{MADE_BY})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p} is corrupt ({exc}); {MADE_BY} writes it again") from exc
    need = ("test_accuracy_type", "chance")
    if not isinstance(meta, dict) or any(k not in meta for k in need):
        raise InputError(f"{p} is not an FD-depth encoder's record (needs "
                         f"{', '.join(need)}); {MADE_BY} writes it")
    return meta


@torch.no_grad()
def features(enc: DepthEncoder, images: np.ndarray, batch: int = 256) -> np.ndarray:
    enc.eval()
    out = [enc.embed(torch.from_numpy(np.ascontiguousarray(images[s:s + batch],
                                                           np.float32))[:, None]).numpy()
           for s in range(0, len(images), batch)]
    return np.concatenate(out).astype(np.float64)


@torch.no_grad()
def accuracy(enc: DepthEncoder, ds: DepthDataset, batch: int = 256) -> float:
    enc.eval()
    hits = 0
    for s in range(0, len(ds), batch):
        idx = np.arange(s, min(s + batch, len(ds)))
        pred = enc(torch.from_numpy(ds.images(idx))[:, None]).argmax(1).numpy()
        hits += int((pred == ds.conditions[idx, 0].astype(int)).sum())
    return hits / len(ds)


def _sqrt_psd(m: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh((m + m.T) / 2)
    return (v * np.sqrt(np.clip(w, 0, None))) @ v.T


def frechet_distance(a: np.ndarray, b: np.ndarray, sides=("first", "second")) -> float:
    """||mu_a - mu_b||^2 + Tr(S_a + S_b - 2 (S_a^1/2 S_b S_a^1/2)^1/2) of two feature sets
    (``sides``: what ``a`` and ``b`` are, for a refusal)."""
    if len(a) < 2 or len(b) < 2:
        raise InputError(f"a Fréchet distance needs at least 2 samples a side, got "
                         f"{len(a)} ({sides[0]}) and {len(b)} ({sides[1]})")
    mu_a, mu_b = a.mean(0), b.mean(0)
    s_a, s_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    root = _sqrt_psd(s_a)
    cross = np.sqrt(np.clip(np.linalg.eigvalsh(root @ s_b @ root), 0, None)).sum()
    return float(((mu_a - mu_b) ** 2).sum() + np.trace(s_a) + np.trace(s_b) - 2 * cross)


def cloud_images(model, ds: DepthDataset, idx: np.ndarray, seed: int = 0) -> np.ndarray:
    """Normalised depth images (N, H, W) of the clouds ``model`` generates at samples ``idx``
    of ``ds``: PC2Im (eq. 15) at the dataset's lidar and each type's depth length, then Norm
    (eq. 17), as the dataset's own images are made."""
    res = model.generate(ds.condition_rows(idx), count=1, seed=seed)
    cloud = res.cloud
    n = len(idx)
    sample = cloud.sample if cloud.sample is not None else np.zeros(len(cloud.xyz), np.int64)
    codes = ds.conditions[idx, 0].astype(np.int64)
    length = ds.types.column("depth_length_m").astype(np.float64)[codes]
    img, _ = pc2im(cloud.xyz, ds.conditions[idx, 1], ds.conditions[idx, 2], length,
                   ds.lidar, sample=sample, n_samples=n)
    return norm(np.asarray(img, np.float32).reshape(n, ds.height, ds.width), ds.q[idx])


def fd_depth(encoder, model, data_dir, n_pairs: int = 2000, seed: int = 0) -> dict:
    """FD-depth of ``model`` (any family) on the protocol's test pairs, beside the distance
    between two halves of the real images (what a perfect generator would score at this sample
    size). The conditions reach the model by type name, encoded in its own condition space."""
    from .protocol import draw_pairs
    enc = encoder if isinstance(encoder, DepthEncoder) else load_encoder(encoder)
    pairs = draw_pairs(data_dir, n_pairs, seed, half="test")
    ds, idx = pairs.ds, pairs.idx
    if len(idx) < MIN_PAIRS:  # before the model generates anything
        raise InputError(f"FD-depth needs at least {MIN_PAIRS} test pairs (the distance "
                         "between real and generated images takes 2 a side, and the floor "
                         "beside it splits the real images in two halves of 2 or more); "
                         f"{data_dir} gave {len(idx)}: use a dataset with more test samples"
                         + ("" if not n_pairs or n_pairs >= MIN_PAIRS
                            else f", and --pairs {MIN_PAIRS} or more (0: every one)"))
    rng = np.random.default_rng(seed)
    real = ds.images(idx)
    if tuple(enc.shape) != (ds.height, ds.width):
        raise InputError(f"the encoder reads {enc.shape[0]} x {enc.shape[1]} depth images; "
                         f"dataset {ds.directory} has {ds.height} x {ds.width}: train an "
                         "encoder on a dataset of this lidar (`apcg fd-depth train`)")
    noise = rng.standard_normal((len(idx), NOISE_DIM)).astype(np.float32)
    if callable(getattr(model, "images_from", None)):  # a family that draws depth images
        nu = model.space.encode(model.repeated_conditions(ds.condition_rows(idx), 1))
        fake = model.images_from(noise, nu)
        if not getattr(model, "norm", True):  # trained without Norm: into the encoder's space
            fake = norm(fake, ds.q[idx])
    else:  # every other family draws clouds: their depth images are PC2Im of them
        fake = cloud_images(model, ds, idx, seed)
    fr, fg = features(enc, real), features(enc, fake)
    half = rng.permutation(len(idx))
    floor = frechet_distance(fr[half[: len(idx) // 2]], fr[half[len(idx) // 2:]],
                             ("the real images' first half", "their second half"))
    return {"fd_depth": frechet_distance(fr, fg, ("real images", "generated images")),
            "fd_depth_real_halves": floor,
            "pairs": len(idx), "seed": seed}
