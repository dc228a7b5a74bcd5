"""Generator and discriminator of the improved cGAN (SPEC section 7, paper Fig. 4), with a width
multiplier (1.0 = the paper's channels) and the ablation switches of Table 3."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from ..condition import FIELDS, NOISE_DIM

COND_DIM = len(FIELDS)


@dataclass(frozen=True)
class NetConfig:
    """Architecture of one cGAN. ``width`` scales every channel count (1.0 = the paper);
    ``conv`` False = fully connected layers instead of (transposed) convolutions;
    ``attention`` False = no self-attention; ``loss`` 'wgan-gp' or 'bce' (Table 3)."""

    width: float = 1.0
    conv: bool = True
    attention: bool = True
    loss: str = "wgan-gp"
    height: int = 64
    width_px: int = 256

    def __post_init__(self) -> None:
        if not 0 < self.width <= 4:
            raise ValueError(f"width must be in (0, 4], got {self.width}")
        if self.loss not in ("wgan-gp", "bce"):
            raise ValueError(f"loss must be 'wgan-gp' or 'bce', got {self.loss!r}")
        if self.height % 16 or self.width_px % 16:
            raise ValueError("image height and width must be multiples of 16")

    def channels(self, base: int) -> int:
        return max(1, int(round(base * self.width)))

    def to_dict(self) -> dict:
        return asdict(self)


class SelfAttention(nn.Module):
    """SAGAN self-attention over the positions of a feature map; gamma starts at 0 so the layer
    starts as the identity."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        inner = max(1, channels // 8)
        self.query = nn.Conv2d(channels, inner, 1)
        self.key = nn.Conv2d(channels, inner, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q = self.query(x).flatten(2).transpose(1, 2)  # (b, hw, inner)
        k = self.key(x).flatten(2)  # (b, inner, hw)
        attn = torch.softmax(torch.bmm(q, k), dim=-1)  # (b, hw, hw)
        v = self.value(x).flatten(2)  # (b, c, hw)
        out = torch.bmm(v, attn.transpose(1, 2)).view(b, c, h, w)
        return x + self.gamma * out


class Generator(nn.Module):
    """(noise 100 + nu 6) -> depth image in [-1, 1], (B, 1, H, W)."""

    def __init__(self, cfg: NetConfig = NetConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        c = [cfg.channels(n) for n in (512, 256, 128, 64)]
        h0, w0 = cfg.height // 16, cfg.width_px // 16
        self.first_shape = (c[0], h0, w0)
        if cfg.conv:
            self.layer1 = nn.Sequential(
                nn.ConvTranspose2d(NOISE_DIM + COND_DIM, c[0], (h0, w0)), nn.ReLU())
            self.attention = SelfAttention(c[0]) if cfg.attention else nn.Identity()
            mid = []
            for a, b in zip(c[:-1], c[1:], strict=True):
                mid += [nn.ConvTranspose2d(a, b, 4, 2, 1), nn.BatchNorm2d(b), nn.ReLU()]
            self.middle = nn.Sequential(*mid)
            self.out = nn.Sequential(nn.ConvTranspose2d(c[-1], 1, 4, 2, 1), nn.Tanh())
        else:
            # Table 3's "without TConv": the same five stages as fully connected layers; the
            # first keeps a (C, 4, 16) shape so self-attention can still attach to it.
            self.first_shape = (max(1, c[0] // 16), h0, w0)
            first = self.first_shape[0] * h0 * w0
            sizes = [first, cfg.channels(1024), cfg.channels(2048), cfg.channels(4096)]
            self.layer1 = nn.Sequential(nn.Linear(NOISE_DIM + COND_DIM, first), nn.ReLU())
            self.attention = (SelfAttention(self.first_shape[0]) if cfg.attention
                              else nn.Identity())
            mid = []
            for a, b in zip(sizes[:-1], sizes[1:], strict=True):
                mid += [nn.Linear(a, b), nn.BatchNorm1d(b), nn.ReLU()]
            self.middle = nn.Sequential(*mid)
            self.out = nn.Sequential(nn.Linear(sizes[-1], cfg.height * cfg.width_px), nn.Tanh())

    def forward(self, noise: torch.Tensor, nu: torch.Tensor) -> torch.Tensor:
        z = torch.cat([noise, nu], dim=1)
        if self.cfg.conv:
            x = self.layer1(z[:, :, None, None])
            x = self.attention(x)
            return self.out(self.middle(x))
        x = self.layer1(z).view(-1, *self.first_shape)
        x = self.attention(x).flatten(1)
        return self.out(self.middle(x)).view(-1, 1, self.cfg.height, self.cfg.width_px)


class Discriminator(nn.Module):
    """(depth image, nu) -> one unbounded score (a logit for the BCE ablation)."""

    def __init__(self, cfg: NetConfig = NetConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        c = [cfg.channels(n) for n in (64, 128, 256, 512)]
        if cfg.conv:
            layers, prev = [], 1 + COND_DIM
            for i, ch in enumerate(c):
                layers += [nn.Conv2d(prev, ch, 4, 2, 1), nn.LeakyReLU(0.2)]
                if i == 3 and cfg.attention:
                    layers.append(SelfAttention(ch))
                prev = ch
            self.features = nn.Sequential(*layers)
            self.fc = nn.Linear(c[-1] * (cfg.height // 16) * (cfg.width_px // 16), 1)
        else:
            hw = cfg.height * cfg.width_px
            sizes = [hw + COND_DIM, cfg.channels(1024), cfg.channels(512), cfg.channels(256),
                     cfg.channels(1024)]
            layers = []
            for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
                layers += [nn.Linear(a, b), nn.LeakyReLU(0.2)]
                if i == 3 and cfg.attention:
                    layers += [_Unflatten(b), SelfAttention(b // 16), nn.Flatten()]
            self.features = nn.Sequential(*layers)
            self.fc = nn.Linear(sizes[-1], 1)

    def forward(self, image: torch.Tensor, nu: torch.Tensor) -> torch.Tensor:
        b = image.shape[0]
        if self.cfg.conv:
            cond = nu[:, :, None, None].expand(b, COND_DIM, *image.shape[-2:])
            x = self.features(torch.cat([image, cond], dim=1))
        else:
            x = self.features(torch.cat([image.flatten(1), nu], dim=1))
        return self.fc(x.flatten(1)).squeeze(1)


class _Unflatten(nn.Module):
    """(B, n) -> (B, n / 16, 1, 16) so the FC discriminator's fourth layer can self-attend."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.view(x.shape[0], self.n // 16, 1, 16)
