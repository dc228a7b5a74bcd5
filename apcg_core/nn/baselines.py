"""Networks of the comparison families, all conditioned on nu (6 values) and sized for a CPU.

GANs take (noise (B, 100), nu (B, 6)) in the generator and (sample, nu) in the critic, like the
cGAN, so the cGAN's WGAN-GP trainer drives them unchanged."""

from __future__ import annotations

import math

import torch
from torch import nn

from ..condition import FIELDS, NOISE_DIM
from ..errors import check_int

COND_DIM = len(FIELDS)


def _mlp(sizes, last_act=True):
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if last_act or i < len(sizes) - 2:
            layers.append(nn.LeakyReLU(0.2))
    return nn.Sequential(*layers)


class PointGenerator(nn.Module):
    """r-GAN style: an MLP from (noise, nu) to N points in the canonical cube (tanh)."""

    def __init__(self, n_points: int = 256, hidden: int = 256) -> None:
        super().__init__()
        self.n_points = n_points
        self.net = nn.Sequential(_mlp([NOISE_DIM + COND_DIM, hidden, 2 * hidden, 4 * hidden]),
                                 nn.Linear(4 * hidden, 3 * n_points), nn.Tanh())

    def forward(self, noise, nu):
        return self.net(torch.cat([noise, nu], 1)).view(-1, self.n_points, 3)


class PointCritic(nn.Module):
    """PointNet: a shared per-point MLP, max-pooled, joined with nu, to one score."""

    def __init__(self, hidden: int = 128) -> None:
        super().__init__()
        self.point = _mlp([3, hidden // 2, hidden, 2 * hidden])
        self.head = _mlp([2 * hidden + COND_DIM, hidden, 1], last_act=False)

    def forward(self, pts, nu):
        f = self.point(pts).max(dim=1).values
        return self.head(torch.cat([f, nu], 1))


class VoxelGenerator(nn.Module):
    """3D-GAN style: (noise, nu) -> 4^3 features -> transposed 3D convolutions -> occupancy
    probabilities on res^3 (res = 4 * 2^k)."""

    def __init__(self, res: int = 32, width: int = 64) -> None:
        super().__init__()
        ups = int(round(math.log2(res / 4)))
        if 4 * 2**ups != res:
            raise ValueError(f"voxel resolution must be 4 * 2^k, got {res}")
        self.res, self.width = res, width
        self.fc = nn.Sequential(nn.Linear(NOISE_DIM + COND_DIM, width * 64), nn.ReLU())
        layers, c = [], width
        for i in range(ups):
            out = 1 if i == ups - 1 else max(8, c // 2)
            layers.append(nn.ConvTranspose3d(c, out, 4, 2, 1))
            if i < ups - 1:
                layers += [nn.BatchNorm3d(out), nn.ReLU()]
            c = out
        self.up = nn.Sequential(*layers, nn.Sigmoid())

    def forward(self, noise, nu):
        x = self.fc(torch.cat([noise, nu], 1)).view(-1, self.width, 4, 4, 4)
        return self.up(x)


class VoxelCritic(nn.Module):
    """3D convolutions over the occupancy grid plus nu broadcast as channels, to one score."""

    def __init__(self, res: int = 32, width: int = 16) -> None:
        super().__init__()
        downs = int(round(math.log2(res / 4)))
        layers, c = [], 1 + COND_DIM
        for i in range(downs):
            out = width * 2**i
            layers += [nn.Conv3d(c, out, 4, 2, 1), nn.LeakyReLU(0.2)]
            c = out
        self.conv = nn.Sequential(*layers, nn.Flatten())
        self.head = nn.Linear(c * 64, 1)

    def forward(self, vox, nu):
        b, _, r, _, _ = vox.shape
        cond = nu[:, :, None, None, None].expand(b, COND_DIM, r, r, r)
        return self.head(self.conv(torch.cat([vox, cond], 1)))


class Denoiser(nn.Module):
    """DPM family: predicts the noise in x_t (B, N, 3) from x_t, the step t and nu; a per-point
    MLP joined with a max-pooled global feature (PointNet), conditioned by concatenation."""

    def __init__(self, hidden: int = 128, t_dim: int = 32) -> None:
        super().__init__()
        self.t_dim = t_dim
        self.local = _mlp([3 + t_dim + COND_DIM, hidden, hidden])
        self.out = _mlp([2 * hidden + t_dim + COND_DIM, hidden, hidden, 3], last_act=False)

    def embed_t(self, t: torch.Tensor) -> torch.Tensor:
        half = self.t_dim // 2
        f = torch.exp(-math.log(1000.0) * torch.arange(half, dtype=torch.float32) / half)
        a = t.float()[:, None] * f[None]
        return torch.cat([a.sin(), a.cos()], 1)

    def forward(self, x, t, nu):
        b, n, _ = x.shape
        ctx = torch.cat([self.embed_t(t), nu], 1)
        h = self.local(torch.cat([x, ctx[:, None].expand(b, n, ctx.shape[1])], 2))
        g = h.max(dim=1).values
        return self.out(torch.cat([h, g[:, None].expand(b, n, g.shape[1]),
                                   ctx[:, None].expand(b, n, ctx.shape[1])], 2))


def check_sampling_steps(steps, schedule_steps: int) -> int:
    """``steps`` when it is a whole number in 1..``schedule_steps``, else a clear error."""
    return check_int("sampling_steps", steps, 1, schedule_steps,
                     hint=" (the model's diffusion steps)")


class Schedule:
    """Linear-beta DDPM schedule over T steps."""

    def __init__(self, steps: int = 200, beta_start: float = 1e-4, beta_end: float = 0.02):
        self.T = steps
        self.beta = torch.linspace(beta_start, beta_end, steps)
        self.alpha = 1.0 - self.beta
        self.alpha_bar = torch.cumprod(self.alpha, 0)

    def noisy(self, x0, t, eps):
        ab = self.alpha_bar[t][:, None, None]
        return ab.sqrt() * x0 + (1 - ab).sqrt() * eps

    @torch.no_grad()
    def sample(self, net: Denoiser, nu, n_points: int, generator: torch.Generator,
               sampling_steps: int | None = None):
        """Ancestral sampling, on ``sampling_steps`` evenly spaced steps (DDIM-like striding,
        eta = 1) when fewer than T are asked for."""
        steps = self.T if sampling_steps is None else check_sampling_steps(sampling_steps, self.T)
        ts = torch.linspace(self.T - 1, 0, steps).round().long()
        x = torch.randn(len(nu), n_points, 3, generator=generator)
        for i, t in enumerate(ts):
            t_prev = ts[i + 1] if i + 1 < len(ts) else torch.tensor(-1)
            ab = self.alpha_bar[t]
            ab_prev = self.alpha_bar[t_prev] if t_prev >= 0 else torch.tensor(1.0)
            eps = net(x, t.repeat(len(nu)), nu)
            x0 = ((x - (1 - ab).sqrt() * eps) / ab.sqrt()).clamp(-1.5, 1.5)
            if t_prev < 0:
                x = x0
                break
            # The noise consistent with the clipped x0: with the network's own eps a wrong
            # prediction feeds back (x grows, eps with it) and a trained model sent 2 of 1,000
            # held-out clouds to inf and NaN; this way x_prev weighs x by less than 1.
            eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
            var = (1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev)
            mean = ab_prev.sqrt() * x0 + (1 - ab_prev - var).clamp(min=0).sqrt() * eps
            x = mean + var.sqrt() * torch.randn(x.shape, generator=generator)
        return x
