"""A model folder at the paper's shapes with random (seeded) weights, to
measure what serving that size costs (`worldpack bench step`) and to prove
that the runtime packs and runs the paper's token layout.

The paper's model is a CDiT-B/2 over SD-VAE latents of 224x224 frames:
4x28x28 latents, so 196 / 49 / 16 tokens per context frame at rates
1 / 4 / 16, and 2x196 + 4x49 + 16x16 = 844 packed context tokens against the
4-frame baseline's 4x196 = 784. `--size paper` builds exactly that (hidden 768,
depth 12, heads 12; an SD-VAE-shaped autoencoder, widths 128/256/512/512);
`--size smoke` keeps the token geometry and shrinks the widths so the folder
is small enough to commit (fixtures/paper_tokens)."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ..core.autoencoder import build as build_autoencoder
from ..core.cdit import CDiT
from ..core.config import AutoencoderConfig, CDiTConfig, ModelConfig
from .export import write_model

SIZES = {
    "paper": (AutoencoderConfig(224, 4, (128, 256, 512, 512), "sd-vae"), dict(hidden=768, depth=12, heads=12)),
    "smoke": (AutoencoderConfig(224, 4, (8, 8, 16, 16), "sd-vae"), dict(hidden=64, depth=2, heads=4)),
}


def build(size: str, seed: int) -> tuple[ModelConfig, torch.nn.Module, CDiT]:
    ae_cfg, widths = SIZES[size]
    cfg = ModelConfig(autoencoder=ae_cfg, cdit=CDiTConfig(latent_channels=4, latent_size=ae_cfg.latent_size, patch=2, **widths))
    torch.manual_seed(seed)
    ae = build_autoencoder(cfg.autoencoder)
    model = CDiT(cfg.cdit)
    # adaLN-Zero starts the blocks and the output at exactly zero; random
    # weights there too, so the references pin every layer's effect.
    with torch.no_grad():
        for p in model.parameters():
            if not p.any():
                p.normal_(0.0, 0.02)
    return cfg, ae, model


def main(size: str, data: Path, out: Path, seed: int, half: bool) -> None:
    if size not in SIZES:
        raise SystemExit(f"--size: {size!r} is not one of {sorted(SIZES)}")
    index = data / "index.json"
    if not index.exists():
        raise SystemExit(f"--data: {data} has no index.json; write a 224x224 suite with `worldpack sim loopnav --size 224x224`")
    side = json.loads(index.read_text()).get("width")
    if side != 224:
        raise SystemExit(f"--data: {data} has {side}-pixel frames; the paper's shapes need 224x224 (`worldpack sim loopnav --size 224x224`)")
    cfg, ae, model = build(size, seed)
    params = sum(p.numel() for p in model.parameters())
    print(f"{size}: CDiT hidden {cfg.cdit.hidden}, depth {cfg.cdit.depth}, {params / 1e6:.1f} M parameters; "
          f"autoencoder {sum(p.numel() for p in ae.parameters()) / 1e6:.1f} M; latent 4x{cfg.cdit.latent_size}x{cfg.cdit.latent_size}")
    # Random weights predict nothing, so the folder carries no training record
    # and no accuracy figures; the references still pin every graph.
    # The SD-VAE-shaped decoder is 40 layers deep, and with random weights its
    # activations reach 20 standard deviations: float32 sums in another order
    # (ONNX Runtime's) then differ from PyTorch's by up to 4e-5, so the absolute
    # tolerance is 1e-4 here (1e-5 for the trained models).
    write_model(cfg, ae, model, ["worldpack", "baseline"], data, out, half, training=None, metrics=False,
                created_by=f"python -m worldpack_train paper-scale --size {size} --seed {seed} (random weights)",
                tolerance={"abs": 1e-4, "rel": 1e-4})
