"""Losses shared by the training stages."""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

LUMA = torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)  # Rec. 601 weights, as eval::metrics' luma


def gradient_difference(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
    """The gradient difference loss of Mathieu, Couprie & LeCun (2016, "Deep
    multi-scale video prediction beyond mean square error", eq. 5, alpha 1):
    mean |(|grad a|) - (|grad b|)| over both image axes. Where MSE alone
    settles for blur, this asks for edges as strong as the target's.
    `where` (N, 1, H, W, in [0, 1]): only pixel pairs it holds at both ends count."""
    dy = lambda x: x[..., 1:, :] - x[..., :-1, :]
    dx = lambda x: x[..., :, 1:] - x[..., :, :-1]
    if where is None:
        return (dy(a).abs() - dy(b).abs()).abs().mean() + (dx(a).abs() - dx(b).abs()).abs().mean()
    wy, wx = where[..., 1:, :] * where[..., :-1, :], where[..., :, 1:] * where[..., :, :-1]
    term = lambda d, w: ((d(a).abs() - d(b).abs()).abs() * w).sum() / (w.sum() * a.shape[1] + 1e-6)
    return term(dy, wy) + term(dx, wx)


def detail_energy_difference(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor, patch: int = 8) -> torch.Tensor:
    """A detail term blind to where the detail sits: per patch (`patch`
    pixels, half-overlapping), the luma gradient energy of `a` and of `b`
    over the neighbour pairs `where` (N, 1, H, W, in [0, 1]) holds at both
    ends, compared as |sqrt(Ea) - sqrt(Eb)| and weighted by how much of the
    patch `where` covers.

    EnhanceNet's texture loss (Sajjadi et al. 2017) matches the Gram
    matrices of VGG features patch by patch so that a super-resolved image
    carries the target's texture without having to place every edge; here
    the features are the luma derivatives, whose energy is what the
    sharpness ratio measures, so no pretrained network is needed. Where the
    truth is unknowable pixel by pixel (the warp's holes) MSE asks for its
    mean; this asks for detail as strong as the truth's."""
    luma = lambda x: (x * LUMA.to(x.dtype)).sum(1, keepdim=True)
    wx, wy = where[..., :, 1:] * where[..., :, :-1], where[..., 1:, :] * where[..., :-1, :]

    def energy(x):
        y = luma(x)
        gx = F.pad((y[..., :, 1:] - y[..., :, :-1]).pow(2) * wx, (0, 1, 0, 0))
        gy = F.pad((y[..., 1:, :] - y[..., :-1, :]).pow(2) * wy, (0, 0, 0, 1))
        return F.avg_pool2d(gx + gy, patch, stride=patch // 2)

    pairs = F.avg_pool2d(F.pad(wx, (0, 1, 0, 0)) + F.pad(wy, (0, 0, 0, 1)), patch, stride=patch // 2)
    per_pair = lambda e: (e / pairs.clamp(min=1e-3) + 1e-8).sqrt()
    gap = (per_pair(energy(a)) - per_pair(energy(b))).abs()
    return (gap * pairs).sum() / pairs.sum().clamp(min=1e-3)


class PatchDiscriminator(nn.Module):
    """pix2pix's PatchGAN (Isola et al. 2017) as VQGAN uses it, sized for 64x64
    frames: four 4x4 convolutions (two of stride 2), one logit per 34-pixel
    patch (14x14 of them). `channels` > 3 makes it conditional: the image
    comes with what it was made from. Spectral normalisation (Miyato et al.
    2018) in place of BatchNorm keeps it one function in both of a step's
    passes (BatchNorm's batch and running statistics differ, so a decoder
    trained against one mode learned to fool a discriminator that was not the
    one training) and bounds how fast it can outrun the generator."""

    def __init__(self, channels: int = 3, width: int = 32):
        super().__init__()
        sn = nn.utils.parametrizations.spectral_norm
        self.net = nn.Sequential(
            sn(nn.Conv2d(channels, width, 4, 2, 1)), nn.LeakyReLU(0.2),
            sn(nn.Conv2d(width, width * 2, 4, 2, 1)), nn.LeakyReLU(0.2),
            sn(nn.Conv2d(width * 2, width * 4, 4, 1, 1)), nn.LeakyReLU(0.2),
            sn(nn.Conv2d(width * 4, 1, 4, 1, 1)),
        )

    def forward(self, image):
        return self.net(image)


class TeacherFeatureJudge(nn.Module):
    """The discriminator of Latent Adversarial Diffusion Distillation (Sauer
    et al. 2024, "Fast High-Resolution Image Synthesis with Latent
    Adversarial Diffusion Distillation"): the frozen teacher denoiser is its
    backbone, and a small head per block reads that block's tokens of a
    re-noised latent and gives one logit per token (a patch of the frame).
    Only the heads train. Where a pixel PatchGAN trained from scratch on
    dark Doom frames stayed at chance, these heads separate a 1-step
    student's latents from the true ones within 150 steps at low noise
    (docs/doom.md, "The teacher as the discriminator")."""

    def __init__(self, hidden: int, depth: int):
        super().__init__()
        self.heads = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(hidden), nn.Linear(hidden, hidden), nn.LeakyReLU(0.2), nn.Linear(hidden, 1))
            for _ in range(depth))

    def forward(self, features: list[torch.Tensor]) -> torch.Tensor:
        """Each block's tokens (B, n, hidden), n a square grid -> logits (B, depth, side, side)."""
        b, n, _ = features[0].shape
        side = int(round(n ** 0.5))
        logits = torch.cat([head(f) for head, f in zip(self.heads, features)], dim=-1)  # (B, n, depth)
        return logits.transpose(1, 2).reshape(b, len(self.heads), side, side)


def hinge_discriminator(real_logits: torch.Tensor, fake_logits: torch.Tensor,
                        patch_weight: torch.Tensor | None = None) -> torch.Tensor:
    """The hinge loss of a discriminator (Lim & Ye 2017, as VQGAN trains it);
    `patch_weight` (broadcast to the logits) weights each patch's share."""
    return patch_mean(F.relu(1.0 - real_logits), patch_weight) + patch_mean(F.relu(1.0 + fake_logits), patch_weight)


def patch_mean(logits: torch.Tensor, patch_weight: torch.Tensor | None = None) -> torch.Tensor:
    """The mean over a PatchGAN's logits, weighted per patch when `patch_weight` is given."""
    if patch_weight is None:
        return logits.mean()
    w = patch_weight.expand_as(logits)
    return (logits * w).sum() / w.sum()


def adaptive_weight(reconstruction: torch.Tensor, adversarial: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
    """VQGAN's lambda (Esser et al. 2021, eq. 7): the reconstruction term's
    gradient norm at the generator's last layer over the adversarial term's,
    so neither swamps the other."""
    g_rec = torch.autograd.grad(reconstruction, last, retain_graph=True)[0]
    g_adv = torch.autograd.grad(adversarial, last, retain_graph=True)[0]
    return (g_rec.norm() / (g_adv.norm() + 1e-4)).clamp(0.0, 1e4).detach()
