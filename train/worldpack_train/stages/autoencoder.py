"""The autoencoder stage: training it, scoring it, and the latent cache."""

from __future__ import annotations

import math
from pathlib import Path
import time

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..core import data as wdata
from ..core.autoencoder import Autoencoder
from ..core.autoencoder import build as build_autoencoder
from ..io.checkpoints import load_autoencoder, log, pick_device, resume, run_config, save
from ..metrics import psnr, to_u8


def train_autoencoder(data: Path, run: Path, steps: int, batch: int, lr: float, device: str, minutes: float | None) -> None:
    cfg = run_config(run)
    dev = pick_device(device)
    frames = wdata.Frames(data)
    ae = build_autoencoder(cfg.autoencoder).to(dev)
    opt = torch.optim.AdamW(ae.parameters(), lr=lr, weight_decay=0.0)
    ckpt = run / "autoencoder.pt"
    step = resume(ckpt, ae, opt, "the autoencoder", dev)
    rng = np.random.default_rng(step)
    deadline = time.time() + minutes * 60 if minutes is not None else math.inf
    bar = tqdm(total=steps, initial=step, desc="autoencoder", unit="step")
    while step < steps and time.time() < deadline:
        x = torch.from_numpy(frames.batch(rng, batch)).to(dev)
        z = ae.encoder(x)
        # Noise on the latent teaches the decoder to tolerate a sampler's small errors.
        z_noisy = z + 0.05 * z.detach().std() * torch.randn_like(z)
        y = ae.decoder(z_noisy)
        loss = F.l1_loss(y, x) + F.mse_loss(y, x) + 1e-4 * z.pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(ae.parameters(), 10.0)
        opt.step()
        step += 1
        bar.update(1)
        if step % 50 == 0:
            p = psnr(to_u8(y), to_u8(x))
            bar.set_postfix(loss=f"{loss.item():.4f}", psnr=f"{p:.2f}")
            log(run, {"stage": "autoencoder", "step": step, "loss": loss.item(), "psnr": p})
        if step % 500 == 0:
            save(ckpt, model=ae.state_dict(), opt=opt.state_dict(), step=step)
    bar.close()
    # The latent scale, as SD's 0.18215: one over the latents' standard deviation.
    with torch.no_grad():
        zs = torch.cat([ae.encoder(torch.from_numpy(frames.batch(np.random.default_rng(1), 64)).to(dev)) for _ in range(8)])
        ae.scale.fill_(1.0 / zs.std().item())
    save(ckpt, model=ae.state_dict(), opt=opt.state_dict(), step=step)
    print(f"autoencoder at step {step}; latent scale {ae.scale.item():.5f}")


@torch.no_grad()
def evaluate_autoencoder(ae: Autoencoder, data: Path, dev: torch.device, frames: int = 512) -> float:
    rng = np.random.default_rng(12345)
    x = torch.from_numpy(wdata.Frames(data).batch(rng, frames)).to(dev)
    y = torch.cat([ae.decoder(ae.encoder(c)) for c in x.split(64)])
    return psnr(to_u8(y), to_u8(x))


@torch.no_grad()
def encode(data: Path, run: Path, device: str) -> None:
    """Caches every frame's scaled latent (float16) under run/latents/."""
    dev = pick_device(device)
    ae = load_autoencoder(run, dev)
    out = run / "latents"
    out.mkdir(exist_ok=True)
    dirs = wdata.trajectories(data)
    for d in tqdm(dirs, desc="encode", unit="traj"):
        target = out / f"{d.name}.npy"
        if target.exists():
            continue
        rgb = np.load(d / "rgb.npy")
        z = torch.cat([ae.encoder(torch.from_numpy(wdata.to_unit_range(c)).to(dev)) for c in np.array_split(rgb, max(1, len(rgb) // 256))])
        np.save(target.with_suffix(".tmp.npy"), (z * ae.scale).cpu().numpy().astype(np.float16))
        target.with_suffix(".tmp.npy").replace(target)
    print(f"latents for {len(dirs)} trajectories in {out}")
