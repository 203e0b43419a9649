"""Model sizes and settings, kept in one JSON-serialisable dataclass so a
checkpoint, the export and the manifest all say the same thing."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import json

# The world's action vector (see docs/world.md): what each entry means and the
# factor the denoiser multiplies it by before embedding.
ACTION_NAMES = ["forward", "back", "left", "right", "jump", "yaw_delta_deg", "pitch_delta_deg"]
ACTION_SCALE = [1.0, 1.0, 1.0, 1.0, 1.0, 1 / 15, 1 / 15]


@dataclass
class AutoencoderConfig:
    image_size: int = 64
    latent_channels: int = 4
    # Each width halves the resolution once after the first: (32, 64, 64) -> 1/4.
    widths: tuple[int, ...] = (32, 64, 64)
    # "small": the autoencoder trained here (autoencoder.py); "sd-vae": the
    # shapes of Stable Diffusion's VAE (sdvae.py; SD's widths are 128, 256, 512, 512).
    kind: str = "small"

    @property
    def downsample(self) -> int:
        return 2 ** (len(self.widths) - 1)

    @property
    def latent_size(self) -> int:
        return self.image_size // self.downsample


@dataclass
class Layout:
    """Which context slots a denoiser graph takes: `counts[i]` frames at `rates[i]`."""

    name: str
    rates: tuple[int, ...]
    counts: tuple[int, ...]

    @property
    def frames(self) -> int:
        return sum(self.counts)


LAYOUTS = {
    "baseline": Layout("baseline", (1,), (4,)),
    "memory_retrieval": Layout("memory_retrieval", (1,), (4,)),
    "worldpack": Layout("worldpack", (1, 4, 16), (2, 4, 16)),
    "nearest_frame_packing": Layout("nearest_frame_packing", (1, 4, 16), (2, 4, 16)),
    # WorldPack with the newest frame pinned to the first full-rate slot (`worldpack plan --keep-last`).
    "worldpack_keep_last": Layout("worldpack_keep_last", (1, 4, 16), (2, 4, 16)),
}


@dataclass
class CDiTConfig:
    latent_channels: int = 4
    latent_size: int = 16
    patch: int = 2
    hidden: int = 128
    depth: int = 4
    heads: int = 4
    mlp_ratio: float = 4.0
    action_dim: int = 7
    # One input projection per rate; rate r embeds with a kernel sqrt(r) times the patch per side.
    rates: tuple[int, ...] = (1, 4, 16)
    rope_base: float = 10000.0
    # Relative camera translations (blocks) are divided by this before embedding.
    pose_translation_scale: float = 10.0
    # Relative time (frames) is divided by this before the sinusoidal embedding.
    time_unit: float = 1.0
    # Where-it-lands positions: each context token also gets the target's
    # position code at the point where its ray lands in the target view, were
    # the surface at each of these depths (blocks). () turns it off (older runs).
    landing_depths: tuple[float, ...] = ()
    # The camera's focal length over the image width (fx / W), for those rays.
    focal: float = 0.0
    # A noise level per context frame as a model input (`context_noise_r<rate>`):
    # training corrupts context latents by that much, and at inference the
    # runtime tells the model which frames it generated itself. False: older runs.
    context_noise: bool = False
    # The geometry model: a stored frame depth-warped into the target view
    # (its latent and coverage, `warp.py`) is added to the target's own
    # tokens through a projection of its own. False: older runs.
    warp: bool = False

    @property
    def grid(self) -> int:
        return self.latent_size // self.patch


@dataclass
class DiffusionConfig:
    timesteps: int = 1000
    beta_start: float = 1e-4
    beta_end: float = 0.02


@dataclass
class ModelConfig:
    autoencoder: AutoencoderConfig = field(default_factory=AutoencoderConfig)
    cdit: CDiTConfig = field(default_factory=CDiTConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_json(d: dict) -> "ModelConfig":
        ae = AutoencoderConfig(**{**d["autoencoder"], "widths": tuple(d["autoencoder"]["widths"])})
        cd = CDiTConfig(**{**d["cdit"], "rates": tuple(d["cdit"]["rates"]),
                           "landing_depths": tuple(d["cdit"].get("landing_depths", ()))})
        return ModelConfig(ae, cd, DiffusionConfig(**d["diffusion"]))


def side_factor(rate: int) -> int:
    s = round(rate ** 0.5)
    if s * s != rate:
        raise ValueError(f"rate {rate} is not a square: a rate must shrink both sides equally")
    return s


def tokens_per_frame(latent_size: int, patch: int, rate: int) -> int:
    """Tokens one context frame at `rate` costs: the latent is replicate-padded
    up to a multiple of the kernel, then cut into kernel-sized patches."""
    k = patch * side_factor(rate)
    side = -(-latent_size // k)
    return side * side


def dumps(obj) -> str:
    return json.dumps(obj, indent=2)
