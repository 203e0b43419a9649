"""A small convolutional autoencoder standing in for the SD VAE (which cannot
be downloaded here): images in [-1, 1] to a 4-channel latent at 1/4 of the
side. Deterministic; like SD, the diffusion model sees `latent * scale`, where
`scale` makes the training latents unit-variance (SD's is 0.18215)."""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from .config import AutoencoderConfig
from .sdvae import SDVAEShaped


class ResBlock(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(8, ch)
        self.conv1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.norm2 = nn.GroupNorm(8, ch)
        self.conv2 = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, x):
        h = self.conv1(F.silu(self.norm1(x)))
        return x + self.conv2(F.silu(self.norm2(h)))


class Encoder(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        w = cfg.widths
        layers: list[nn.Module] = [nn.Conv2d(3, w[0], 3, padding=1), ResBlock(w[0])]
        for a, b in zip(w, w[1:]):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), ResBlock(b)]
        layers += [nn.GroupNorm(8, w[-1]), nn.SiLU(), nn.Conv2d(w[-1], cfg.latent_channels, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, image):
        """image: (B, 3, H, W) in [-1, 1] -> raw latent (B, C, H/d, W/d)."""
        return self.net(image)


class Decoder(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        w = cfg.widths[::-1]
        layers: list[nn.Module] = [nn.Conv2d(cfg.latent_channels, w[0], 3, padding=1), ResBlock(w[0])]
        for a, b in zip(w, w[1:]):
            layers += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(a, b, 3, padding=1), ResBlock(b)]
        layers += [nn.GroupNorm(8, w[-1]), nn.SiLU(), nn.Conv2d(w[-1], 3, 3, padding=1)]
        self.net = nn.Sequential(*layers)

    def forward(self, latent):
        """raw latent -> image (B, 3, H, W), nominally in [-1, 1] (not clamped)."""
        return self.net(latent)


class Autoencoder(nn.Module):
    def __init__(self, cfg: AutoencoderConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)
        # Set after training from the latents' standard deviation.
        self.register_buffer("scale", torch.tensor(1.0))


def build(cfg: AutoencoderConfig) -> nn.Module:
    """The autoencoder `cfg.kind` names, untrained."""
    if cfg.kind == "sd-vae":

        return SDVAEShaped(cfg)
    if cfg.kind != "small":
        raise SystemExit(f"config autoencoder.kind: {cfg.kind!r} is neither \"small\" nor \"sd-vae\"")
    return Autoencoder(cfg)

