"""The conditional diffusion transformer (CDiT, as in NWM) with WorldPack's
packed context: one input projection per compression rate, temporal RoPE over
each context frame's time offset, and a camera-pose embedding of each context
frame relative to the target.

Shapes: the target latent x_t is (B, C, h, w); a context group at rate r is
(B, S, C, h, w) and becomes S * (h / (p sqrt r))^2 tokens."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from .config import ACTION_SCALE, CDiTConfig, side_factor

MASKED = -1e9  # added to the attention logits of empty slots


def sincos_2d(dim: int, grid: int) -> np.ndarray:
    """DiT's fixed 2-D sine-cosine table, (grid*grid, dim), row-major tokens."""
    def one_axis(d: int, pos: np.ndarray) -> np.ndarray:
        omega = 1.0 / 10000 ** (np.arange(d // 2, dtype=np.float64) / (d / 2))
        out = np.outer(pos.reshape(-1), omega)
        return np.concatenate([np.sin(out), np.cos(out)], axis=1)
    ys, xs = np.meshgrid(np.arange(grid, dtype=np.float64), np.arange(grid, dtype=np.float64), indexing="ij")
    return np.concatenate([one_axis(dim // 2, ys), one_axis(dim // 2, xs)], axis=1).astype(np.float32)


def sincos_2d_at(dim: int, gy: torch.Tensor, gx: torch.Tensor) -> torch.Tensor:
    """`sincos_2d` evaluated at real-valued grid positions: (...) -> (..., dim);
    at integer positions it equals the table's rows."""
    d = dim // 2
    omega = 1.0 / 10000 ** (torch.arange(d // 2, dtype=torch.float32, device=gy.device) / (d / 2))
    ay, ax = gy.unsqueeze(-1) * omega, gx.unsqueeze(-1) * omega
    return torch.cat([torch.sin(ay), torch.cos(ay), torch.sin(ax), torch.cos(ax)], dim=-1)


def token_rays(latent_size: int, kernel: int, focal: float) -> np.ndarray:
    """Camera-frame directions (x right, y down, z = 1; OpenCV) through the
    centres of the tokens a `kernel`-wide patchify makes, row-major, (n, 3).
    `focal` is fx over the image width; the principal point is the centre."""
    side = -(-latent_size // kernel)
    lo = np.arange(side) * kernel
    centre = (lo + np.minimum(lo + kernel, latent_size)) / 2 / latent_size  # fraction of the width
    xn = (centre - 0.5) / focal
    ys, xs = np.meshgrid(xn, xn, indexing="ij")
    return np.stack([xs.ravel(), ys.ravel(), np.ones(side * side)], axis=1).astype(np.float32)


def pool_table(table: np.ndarray, grid: int, factor: int) -> np.ndarray:
    """Average-pools a (grid*grid, D) table with a factor x factor kernel,
    replicate-padding the grid first when it does not divide."""
    side = -(-grid // factor)
    t = table.reshape(grid, grid, -1)
    pad = side * factor - grid
    t = np.pad(t, ((0, pad), (0, pad), (0, 0)), mode="edge")
    return t.reshape(side, factor, side, factor, -1).mean(axis=(1, 3)).reshape(side * side, -1).astype(np.float32)


def scalar_embedding(x: torch.Tensor, dim: int = 256, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal features of a float vector (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=x.device) / half)
    args = x[:, None].float() * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


class ScalarEmbedder(nn.Module):
    def __init__(self, hidden: int, unit: float = 1.0):
        super().__init__()
        self.unit = unit
        self.mlp = nn.Sequential(nn.Linear(256, hidden), nn.SiLU(), nn.Linear(hidden, hidden))

    def forward(self, x):
        return self.mlp(scalar_embedding(x / self.unit))


def pad_replicate(x, k: int):
    """(N, C, h, w) with the last row and column repeated up to multiples of
    k, as F.pad's "replicate" mode would (which torch.export cannot trace with
    a dynamic batch, so the paper's 28x28 latents at rate 16 would not export)."""
    pw, ph = (-x.shape[3]) % k, (-x.shape[2]) % k
    if pw:
        x = torch.cat([x, x[:, :, :, -1:].expand(-1, -1, -1, pw)], dim=3)
    if ph:
        x = torch.cat([x, x[:, :, -1:, :].expand(-1, -1, ph, -1)], dim=2)
    return x


def modulate(x, shift, scale):
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


def rotate(x, cos, sin):
    """Real-valued RoPE on the two halves of the head dimension."""
    a, b = x.chunk(2, dim=-1)
    return torch.cat([a * cos - b * sin, a * sin + b * cos], dim=-1)


class Attention(nn.Module):
    def __init__(self, hidden: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(hidden, hidden)
        self.kv = nn.Linear(hidden, 2 * hidden)
        self.out = nn.Linear(hidden, hidden)

    def forward(self, x, context, bias=None, cos=None, sin=None):
        b, n, d = x.shape
        m = context.shape[1]
        hd = d // self.heads
        q = self.q(x).view(b, n, self.heads, hd).transpose(1, 2)
        k, v = self.kv(context).view(b, m, 2, self.heads, hd).permute(2, 0, 3, 1, 4)
        if cos is not None:
            # Queries sit at time 0 (no rotation); keys rotate by their frame's offset.
            k = rotate(k, cos, sin)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        return self.out(y.transpose(1, 2).reshape(b, n, d))


class Block(nn.Module):
    def __init__(self, cfg: CDiTConfig):
        super().__init__()
        h = cfg.hidden
        self.norm_self = nn.LayerNorm(h, elementwise_affine=False, eps=1e-6)
        self.self_attn = Attention(h, cfg.heads)
        self.norm_cross = nn.LayerNorm(h, elementwise_affine=False, eps=1e-6)
        self.norm_context = nn.LayerNorm(h, elementwise_affine=False, eps=1e-6)
        self.cross_attn = Attention(h, cfg.heads)
        self.norm_mlp = nn.LayerNorm(h, elementwise_affine=False, eps=1e-6)
        inner = int(h * cfg.mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(h, inner), nn.GELU(approximate="tanh"), nn.Linear(inner, h))
        # adaLN-Zero: 11 modulation chunks, zero-initialised so every block starts as the identity.
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(h, 11 * h))

    def forward(self, x, context, c, bias, cos, sin):
        (sh_sa, sc_sa, g_sa, sh_ctx, sc_ctx, sh_ca, sc_ca, g_ca, sh_mlp, sc_mlp, g_mlp) = self.ada(c).chunk(11, dim=-1)
        h = modulate(self.norm_self(x), sh_sa, sc_sa)
        x = x + g_sa.unsqueeze(1) * self.self_attn(h, h)
        kv = modulate(self.norm_context(context), sh_ctx, sc_ctx)
        q = modulate(self.norm_cross(x), sh_ca, sc_ca)
        x = x + g_ca.unsqueeze(1) * self.cross_attn(q, kv, bias, cos, sin)
        return x + g_mlp.unsqueeze(1) * self.mlp(modulate(self.norm_mlp(x), sh_mlp, sc_mlp))


class CDiT(nn.Module):
    def __init__(self, cfg: CDiTConfig):
        super().__init__()
        self.cfg = cfg
        h, p, c = cfg.hidden, cfg.patch, cfg.latent_channels
        if cfg.latent_size % p:
            raise ValueError(f"latent size {cfg.latent_size} must be a multiple of the patch {p}")
        if 1 not in cfg.rates:
            raise ValueError("rates must include 1 (the base patchify)")
        # Rate 1 is the base patchify, shared by the noisy target and uncompressed context (as NWM).
        self.patchify = nn.Conv2d(c, h, p, stride=p)
        self.rate_proj = nn.ModuleDict({
            f"r{r}": nn.Conv2d(c, h, p * side_factor(r), stride=p * side_factor(r)) for r in cfg.rates if r != 1
        })
        base = sincos_2d(h, cfg.grid)
        self.register_buffer("pos_r1", torch.from_numpy(base), persistent=False)
        for r in cfg.rates:
            if r != 1:
                self.register_buffer(f"pos_r{r}", torch.from_numpy(pool_table(base, cfg.grid, side_factor(r))), persistent=False)
        if cfg.landing_depths:
            if cfg.focal <= 0:
                raise ValueError("landing_depths need the camera's focal (fx / width) in the config")
            for r in cfg.rates:
                rays = token_rays(cfg.latent_size, p * side_factor(r), cfg.focal)
                self.register_buffer(f"rays_r{r}", torch.from_numpy(rays), persistent=False)
            self.register_buffer("landing_depth", torch.tensor(cfg.landing_depths, dtype=torch.float32), persistent=False)
            # Zero: a fine-tune starts as the model it came from and opens these as they help.
            self.landing_gate = nn.Parameter(torch.zeros(len(cfg.landing_depths), h))
        if cfg.warp:
            # Latent channels plus coverage, patchified onto the target's own tokens (no context slot).
            self.warp_proj = nn.Conv2d(c + 1, h, p, stride=p)
        self.t_embed = ScalarEmbedder(h)
        self.rel_time_embed = ScalarEmbedder(h, cfg.time_unit)
        self.action_embed = nn.Sequential(nn.Linear(cfg.action_dim, h), nn.SiLU(), nn.Linear(h, h))
        self.register_buffer("action_scale", torch.tensor(ACTION_SCALE[: cfg.action_dim]), persistent=False)
        self.pose_embed = nn.Sequential(nn.Linear(12, h), nn.SiLU(), nn.Linear(h, h))
        if cfg.context_noise:
            # Levels are small (0..1): a unit of 0.001 spreads them over the sinusoid's periods.
            self.context_noise_embed = ScalarEmbedder(h, 0.001)
        pose_scale = torch.ones(12)
        pose_scale[[3, 7, 11]] = 1.0 / cfg.pose_translation_scale
        self.register_buffer("pose_scale", pose_scale, persistent=False)
        hd = h // cfg.heads
        inv_freq = 1.0 / cfg.rope_base ** (torch.arange(0, hd // 2, dtype=torch.float32) / (hd // 2))
        self.register_buffer("rope_inv_freq", inv_freq, persistent=False)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.depth))
        self.final_norm = nn.LayerNorm(h, elementwise_affine=False, eps=1e-6)
        self.final_ada = nn.Sequential(nn.SiLU(), nn.Linear(h, 2 * h))
        self.final = nn.Linear(h, p * p * c)
        self._init_weights()

    def _init_weights(self):
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        w = self.patchify.weight.data
        nn.init.xavier_uniform_(w.view(w.shape[0], -1))
        nn.init.zeros_(self.patchify.bias)
        for emb in (self.t_embed.mlp, self.rel_time_embed.mlp, self.action_embed, self.pose_embed):
            nn.init.normal_(emb[0].weight, std=0.02)
            nn.init.normal_(emb[2].weight, std=0.02)
        if self.cfg.context_noise:
            # Zero: a fine-tune from a model without it starts as that model.
            nn.init.normal_(self.context_noise_embed.mlp[0].weight, std=0.02)
            nn.init.zeros_(self.context_noise_embed.mlp[2].weight)
        if self.cfg.warp:
            # Zero: a fine-tune from a model without the warp starts as that model.
            nn.init.zeros_(self.warp_proj.weight)
            nn.init.zeros_(self.warp_proj.bias)
        for blk in self.blocks:
            nn.init.zeros_(blk.ada[-1].weight)
            nn.init.zeros_(blk.ada[-1].bias)
        for lin in (self.final_ada[-1], self.final):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)
        self.init_rate_projections_from_base()

    @torch.no_grad()
    def init_rate_projections_from_base(self):
        """Rate r's kernel = the base kernel repeated sqrt(r) times per side,
        divided by the repeat count r; bias copied. It then embeds a frame as
        the base patchify would embed the frame average-pooled by sqrt(r)."""
        for name, proj in self.rate_proj.items():
            s = side_factor(int(name[1:]))
            w = self.patchify.weight.repeat_interleave(s, dim=2).repeat_interleave(s, dim=3)
            proj.weight.copy_(w / (s * s))
            proj.bias.copy_(self.patchify.bias)

    def landing_code(self, rate: int, poses):
        """(B, S, n, D): for each context token, the target's position code where
        its ray lands in the target view at each assumed depth, gated; zero where
        it lands behind the target camera or well outside its image. Without
        depth the model cannot know where remembered content belongs in the new
        view; this tells it, for surfaces at those distances."""
        b, s, _ = poses.shape
        rt = poses.view(b, s, 3, 4)
        rays = torch.einsum("bsij,nj->bsni", rt[..., :3], getattr(self, f"rays_r{rate}"))
        points = rt[:, :, None, None, :, 3] + rays.unsqueeze(3) * self.landing_depth.view(1, 1, 1, -1, 1)
        z = points[..., 2]
        ahead = z > 0.05
        z = torch.where(ahead, z, torch.ones_like(z))
        g = self.cfg.grid
        gx = (points[..., 0] / z * self.cfg.focal + 0.5) * g - 0.5
        gy = (points[..., 1] / z * self.cfg.focal + 0.5) * g - 0.5
        near_view = ahead & (gx > -1.5) & (gx < g + 0.5) & (gy > -1.5) & (gy < g + 0.5)
        code = sincos_2d_at(self.cfg.hidden, gy, gx) * near_view.unsqueeze(-1).to(z.dtype)
        return (code * self.landing_gate).sum(dim=3)

    def embed_group(self, rate: int, frames, offsets, poses, mask, noise=None):
        """One rate's slots -> tokens (B, S*n, D), key positions and mask (B, S*n).
        `noise` (B, S): each frame's context noise level (models with `context_noise`)."""
        b, s, c, hh, ww = frames.shape
        proj = self.patchify if rate == 1 else self.rate_proj[f"r{rate}"]
        k = proj.kernel_size[0]
        x = frames.reshape(b * s, c, hh, ww)
        x = pad_replicate(x, k)
        x = proj(x).flatten(2).transpose(1, 2)  # (B*S, n, D)
        n = x.shape[1]
        x = x + getattr(self, f"pos_r{rate}")
        x = x.reshape(b, s, n, -1) + self.pose_embed(poses * self.pose_scale).unsqueeze(2)
        if self.cfg.landing_depths:
            x = x + self.landing_code(rate, poses)
        if self.cfg.context_noise:
            x = x + self.context_noise_embed(noise.reshape(-1)).view(b, s, 1, -1)
        tokens = x.reshape(b, s * n, -1)
        positions = offsets.unsqueeze(-1).expand(b, s, n).reshape(b, s * n)
        token_mask = mask.unsqueeze(-1).expand(b, s, n).reshape(b, s * n)
        return tokens, positions, token_mask

    def forward(self, x_t, timestep, action, rel_time, groups, rates=None, warp=None, features=None):
        """groups: per rate in `rates` (default cfg.rates order of the layout),
        a tuple (frames (B,S,C,h,w), time offsets (B,S), relative poses (B,S,12),
        mask (B,S)[, noise levels (B,S) with `context_noise`]). `warp`
        (B,C+1,h,w): the warped frame's latent and coverage (models with
        `warp`; `warp.warp_input`). Returns the predicted noise, shaped like x_t.
        `features` (a list): each block's output tokens (B, grid², hidden) are
        appended to it (a discriminator built on this model reads them)."""
        rates = rates or self.cfg.rates
        want = 5 if self.cfg.context_noise else 4
        if len(groups) != len(rates) or any(len(g) != want for g in groups):
            raise ValueError(f"expected {len(rates)} context groups of {want} tensors for rates {rates}")
        b, c, hh, ww = x_t.shape
        p = self.cfg.patch
        x = self.patchify(x_t).flatten(2).transpose(1, 2) + self.pos_r1
        if self.cfg.warp:
            if warp is None:
                raise ValueError("this model takes a warp input (cfg.warp)")
            x = x + self.warp_proj(warp).flatten(2).transpose(1, 2)
        cond = self.t_embed(timestep) + self.rel_time_embed(rel_time) + self.action_embed(action * self.action_scale)
        parts = [self.embed_group(r, *g) for r, g in zip(rates, groups)]
        context = torch.cat([t for t, _, _ in parts], dim=1)
        positions = torch.cat([q for _, q, _ in parts], dim=1)
        mask = torch.cat([m for _, _, m in parts], dim=1)
        bias = ((1.0 - mask) * MASKED)[:, None, None, :]
        angles = (positions.unsqueeze(-1) * self.rope_inv_freq)[:, None]  # (B, 1, M, hd/2)
        cos, sin = torch.cos(angles), torch.sin(angles)
        for blk in self.blocks:
            x = blk(x, context, cond, bias, cos, sin)
            if features is not None:
                features.append(x)
        shift, scale = self.final_ada(cond).chunk(2, dim=-1)
        x = self.final(modulate(self.final_norm(x), shift, scale))
        g = hh // p
        x = x.view(b, g, g, p, p, c).permute(0, 5, 1, 3, 2, 4)
        return x.reshape(b, c, hh, ww)
