"""An autoencoder with the shapes of Stable Diffusion's VAE (the KL-f8 model
the paper uses, `stabilityai/sd-vae-ft-ema`): four levels of residual blocks
(two per level in the encoder, three in the decoder), a stride-2 convolution
or a nearest upsample between levels, one self-attention block in the middle,
and a 4-channel latent at 1/8 of the side. Its weights cannot be downloaded
here, so it is built with random (seeded) weights, to measure what serving a
model of the paper's size costs and to prove the tensor contract, not to
generate images. The latent is the posterior mean, as the manifest's
contract says; the scale is SD's 0.18215."""

from __future__ import annotations

import math

import torch
from torch import nn
import torch.nn.functional as F

from .config import AutoencoderConfig

SD_LATENT_SCALE = 0.18215


class TwoPassGroupNorm(nn.GroupNorm):
    """GroupNorm computed as mean, then the variance of the centred values.
    nn.GroupNorm exports as InstanceNormalization, which ONNX Runtime computes
    as E[x^2] - E[x]^2: with random weights some groups have a mean far above
    their spread, and that cancellation cost 6e-4 against PyTorch."""

    def forward(self, x):
        b, c, h, w = x.shape
        g = x.reshape(b, self.num_groups, -1)
        d = g - g.mean(dim=-1, keepdim=True)
        y = (d / torch.sqrt((d * d).mean(dim=-1, keepdim=True) + self.eps)).reshape(b, c, h, w)
        return y * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)


def norm(ch: int) -> nn.GroupNorm:
    # SD uses 32 groups; narrower smoke-test widths fall back to a divisor of the width.
    return TwoPassGroupNorm(math.gcd(32, ch), ch, eps=1e-6)


class Residual(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.norm1, self.conv1 = norm(cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = norm(cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x):
        h = self.conv1(F.silu(self.norm1(x)))
        return self.skip(x) + self.conv2(F.silu(self.norm2(h)))


class SpatialAttention(nn.Module):
    """Single-head self-attention over the pixels of a feature map."""

    def __init__(self, ch: int):
        super().__init__()
        self.norm = norm(ch)
        self.qkv = nn.Linear(ch, 3 * ch)
        self.out = nn.Linear(ch, ch)

    def forward(self, x):
        b, c, h, w = x.shape
        t = self.norm(x).flatten(2).transpose(1, 2)
        q, k, v = self.qkv(t).chunk(3, dim=-1)
        a = torch.softmax(q @ k.transpose(1, 2) / math.sqrt(c), dim=-1) @ v
        return x + self.out(a).transpose(1, 2).reshape(b, c, h, w)


class Middle(nn.Sequential):
    def __init__(self, ch: int):
        super().__init__(Residual(ch, ch), SpatialAttention(ch), Residual(ch, ch))


class Downsample(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, ch, 3, stride=2)

    def forward(self, x):
        # SD pads only the right and bottom, so an even side halves exactly.
        return self.conv(F.pad(x, (0, 1, 0, 1)))


class Upsample(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.conv = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x):
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


class Encoder(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        w = cfg.widths
        layers: list[nn.Module] = [nn.Conv2d(3, w[0], 3, padding=1)]
        prev = w[0]
        for level, ch in enumerate(w):
            layers += [Residual(prev, ch), Residual(ch, ch)]
            prev = ch
            if level < len(w) - 1:
                layers.append(Downsample(ch))
        layers += [Middle(prev), norm(prev), nn.SiLU(), nn.Conv2d(prev, 2 * cfg.latent_channels, 3, padding=1),
                   nn.Conv2d(2 * cfg.latent_channels, 2 * cfg.latent_channels, 1)]
        self.net = nn.Sequential(*layers)
        self.latent_channels = cfg.latent_channels

    def forward(self, image):
        """image (B, 3, H, W) in [-1, 1] -> the posterior mean (B, C, H/8, W/8)."""
        return self.net(image)[:, : self.latent_channels]


class Decoder(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        w = cfg.widths[::-1]
        c = cfg.latent_channels
        layers: list[nn.Module] = [nn.Conv2d(c, c, 1), nn.Conv2d(c, w[0], 3, padding=1), Middle(w[0])]
        prev = w[0]
        for level, ch in enumerate(w):
            layers += [Residual(prev, ch), Residual(ch, ch), Residual(ch, ch)]
            prev = ch
            if level < len(w) - 1:
                layers.append(Upsample(ch))
        layers += [norm(prev), nn.SiLU(), nn.Conv2d(prev, 3, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, latent):
        return self.net(latent)


class SDVAEShaped(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        self.register_buffer("scale", torch.tensor(SD_LATENT_SCALE))
