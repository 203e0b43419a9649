"""Training for autoregressive stability: what a batch's context goes through
before the denoiser sees it. Each piece is an option of `Recipe`, off by
default, so a recipe with nothing set trains exactly as before.

- Context noise (GameNGen, DIAMOND): each context frame's latent gets
  Gaussian noise of a random level, and the model is told the level, so at
  inference it can be told which frames are its own (less trustworthy) output.
- Rollout fine-tuning (Memory Forcing's chained training, DIAMOND): for a
  share of the batch, the newest context frame is replaced by the model's own
  few-step prediction of it (EMA weights, no gradient), while older memory
  stays observed; the loss is still on the true next frame.
- Pose noise: the context frames' relative poses are perturbed, so the model
  learns not to trust them blindly."""

from __future__ import annotations

from dataclasses import asdict, dataclass
import math

import numpy as np
import torch

from . import data as wdata
from .diffusion import respaced_timesteps


@dataclass
class Recipe:
    # Largest context noise level (latents are unit-variance); 0: off.
    context_noise: float = 0.0
    # Share of the frames that get noise at all (the rest stay clean).
    context_noise_share: float = 0.5
    # Share of each batch whose newest context frame is the model's own prediction; 0: off.
    rollout_share: float = 0.0
    # DDIM steps for those predictions (few: cheap, and as blurry as a fast sampler's).
    rollout_steps: int = 4
    # The level that marks a frame the model generated: set on the rollout
    # frames here and by the runtime on generated frames at inference.
    generated_level: float = 0.0
    # Pose noise on context frames: translation sd (blocks) and rotation sd (degrees); 0: off.
    pose_noise_translation: float = 0.0
    pose_noise_degrees: float = 0.0
    # Share of each batch's items whose context (and warp-source) poses get that noise.
    pose_noise_share: float = 1.0

    def needs_noise_input(self) -> bool:
        return self.context_noise > 0 or self.generated_level > 0

    def to_json(self) -> dict:
        return asdict(self)

    def check(self) -> None:
        for name in ("context_noise_share", "rollout_share", "pose_noise_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise SystemExit(f"--{name.replace('_', '-')}: must be in [0, 1], got {getattr(self, name)}")
        for name in ("context_noise", "generated_level", "pose_noise_translation", "pose_noise_degrees"):
            if getattr(self, name) < 0:
                raise SystemExit(f"--{name.replace('_', '-')}: must be at least 0, got {getattr(self, name)}")
        if self.rollout_steps < 1:
            raise SystemExit(f"--rollout-steps: must be at least 1, got {self.rollout_steps}")


def rotation_from_axis_angle(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle vectors (radians) -> (..., 3, 3) rotations (Rodrigues)."""
    angle = w.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    k = w / angle
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    cross = torch.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], dim=-1).view(*w.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(cross)
    a = angle[..., None]
    return eye + torch.sin(a) * cross + (1 - torch.cos(a)) * (cross @ cross)


def perturb_poses(poses: torch.Tensor, mask: torch.Tensor, translation_sd: float, degrees_sd: float, gen: torch.Generator) -> torch.Tensor:
    """Relative poses (B, S, 12) with independent noise on every present frame:
    the rotation turned by a random small rotation, the position shifted."""
    b, s, _ = poses.shape
    rt = poses.view(b, s, 3, 4)
    w = torch.randn(b, s, 3, generator=gen, device=poses.device) * math.radians(degrees_sd)
    r = rt[..., :3] @ rotation_from_axis_angle(w)
    p = rt[..., 3] + torch.randn(b, s, 3, generator=gen, device=poses.device) * translation_sd
    out = torch.cat([r, p.unsqueeze(-1)], dim=-1).view(b, s, 12)
    return torch.where(mask.unsqueeze(-1) > 0, out, poses)


@torch.no_grad()
def ddim_predict(model, alpha_bar: torch.Tensor, steps: int, action, rel_time, groups, rates, gen: torch.Generator) -> torch.Tensor:
    """Few-step deterministic DDIM samples of the target latents (the runtime's
    `--sampler ddim`, eta 0), from noise drawn with `gen`."""
    b = action.shape[0]
    c, side = model.cfg.latent_channels, model.cfg.latent_size
    x = torch.randn(b, c, side, side, generator=gen, device=action.device)
    ts = respaced_timesteps(len(alpha_bar), steps)[::-1]
    for i, t in enumerate(ts):
        ab = alpha_bar[t]
        ab_prev = alpha_bar[ts[i + 1]] if i + 1 < len(ts) else torch.ones_like(ab)
        eps = model(x, torch.full((b,), float(t), device=x.device), action, rel_time, groups, rates=rates)
        x0 = (x - (1 - ab).sqrt() * eps) / ab.sqrt()
        x = ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps
    return x


class ContextAugmenter:
    """Applies a recipe to batches. `model_for_rollouts` is the EMA model."""

    def __init__(self, recipe: Recipe, source: wdata.PlannedLatents, rates: tuple[int, ...], alpha_bar: torch.Tensor,
                 with_noise_input: bool, seed: int, device: torch.device):
        self.recipe, self.source, self.rates, self.alpha_bar = recipe, source, rates, alpha_bar
        self.with_noise_input = with_noise_input
        self.gen = torch.Generator(device=device).manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.device = device

    def tensors(self, batch: wdata.Batch):
        t = lambda a: torch.from_numpy(a).to(self.device)
        groups = [[t(a) for a in g] for g in batch.groups]
        if self.with_noise_input:
            for g in groups:
                g.append(torch.zeros_like(g[3]))
        return t(batch.target), t(batch.action), t(batch.rel_time), groups

    def __call__(self, batch: wdata.Batch, rollout_model) -> tuple:
        x0, action, rel_time, groups = self.tensors(batch)
        r = self.recipe
        if r.rollout_share > 0:
            self.replace_newest(batch, groups, rollout_model)
        # Which items get pose noise (all of them at share 1, without a draw, as before the share existed).
        self.pose_noisy_items = None
        if r.pose_noise_translation > 0 or r.pose_noise_degrees > 0:
            b = x0.shape[0]
            self.pose_noisy_items = (torch.ones(b, device=self.device) if r.pose_noise_share >= 1.0
                                     else (torch.rand(b, generator=self.gen, device=self.device) < r.pose_noise_share).float())
        for g in groups:
            lat, offsets, poses, mask = g[:4]
            if r.context_noise > 0:
                b, s = mask.shape
                noisy = (torch.rand(b, s, generator=self.gen, device=self.device) < r.context_noise_share) & (mask > 0)
                level = torch.rand(b, s, generator=self.gen, device=self.device) * r.context_noise * noisy
                # Frames already marked generated keep their mark, and get no second dose.
                level = torch.where(g[4] > 0, torch.zeros_like(level), level)
                g[0] = lat + level[..., None, None, None] * torch.randn(lat.shape, generator=self.gen, device=self.device)
                g[4] = g[4] + level
            if r.pose_noise_translation > 0 or r.pose_noise_degrees > 0:
                g[2] = perturb_poses(poses, mask * self.pose_noisy_items[:, None], r.pose_noise_translation, r.pose_noise_degrees, self.gen)
        return x0, action, rel_time, [tuple(g) for g in groups]

    def replace_newest(self, batch: wdata.Batch, groups, model) -> None:
        """The newest context frame (offset -1) of a share of the items becomes
        the model's own prediction of it from that frame's own plan."""
        items = [j for j, (_, t) in enumerate(batch.rows) if t >= 2 and self.rng.random() < self.recipe.rollout_share]
        if not items:
            return
        prev = self.source.gather([(batch.rows[j][0], batch.rows[j][1] - 1) for j in items])
        _, action, rel_time, ctx = self.tensors(prev)
        predicted = ddim_predict(model, self.alpha_bar, self.recipe.rollout_steps, action, rel_time,
                                 [tuple(g) for g in ctx], self.rates, self.gen)
        index = torch.tensor(items, device=self.device)
        for g in groups:
            lat, offsets, mask = g[0], g[1], g[3]
            newest = (offsets[index] == -1) & (mask[index] > 0)  # (n, S)
            if not newest.any():
                continue
            sub = lat[index].clone()
            sub[newest] = predicted.unsqueeze(1).expand_as(sub)[newest]
            g[0] = lat.index_copy(0, index, sub)
            if self.with_noise_input:
                level = g[4][index].clone()
                level[newest] = self.recipe.generated_level
                g[4] = g[4].index_copy(0, index, level)
