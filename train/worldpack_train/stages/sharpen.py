"""A sharper decoder for a trained autoencoder, its encoder frozen.

The autoencoder trained with L1 + MSE decodes every latent to the mean of the
frames it could stand for, so even its own reconstructions keep only about
half of the truth's edge energy, and every generated frame sits under that
ceiling. This stage fine-tunes the decoder alone, as Stable Diffusion's
released `ft-EMA` / `ft-MSE` VAE decoders were: the encoder, and with it the
latent space every denoiser here was trained on, does not move, so each
denoiser keeps working unchanged. The loss is VQGAN's (Esser et al. 2021,
"Taming Transformers", eq. 5-7): a reconstruction term plus a PatchGAN
discriminator (Isola et al. 2017) under the hinge loss, whose weight is set
each step by the ratio of the two terms' gradient norms at the decoder's last
layer. LPIPS needs pretrained weights that cannot be downloaded here, so the
reconstruction term is L1 plus the gradient difference loss (Mathieu et al.
2016), which asks for edges as strong as the truth's. The exported decoder is
the EMA of the weights (SD's `ft-EMA`).

`swap_decoder` then writes a model folder whose decoder is the fine-tuned one
(graph, reference, manifest record); everything else is copied unchanged."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
import shutil
import time

import numpy as np
import onnx
import torch
from torch import nn
import torch.nn.functional as F
from tqdm import tqdm

from ..core import data as wdata
from ..core.losses import PatchDiscriminator, adaptive_weight, gradient_difference, hinge_discriminator
from ..io.checkpoints import load_autoencoder, log, pick_device, save
from ..io.graphs import check_same_encoder, decoder_from
from ..io.onnx_files import round_to_half, save_arrays, store_half, to_onnx
from ..metrics import psnr, sharpness_ratio, to_u8
from .denoiser import optimise

CHECKPOINT = "decoder-sharp.pt"
# The decoder sees its latent with this much noise (relative to the latents'
# spread), as the autoencoder's own training did: a sampler's output is never exact.
LATENT_NOISE = 0.05


@torch.no_grad()
def held_out(data: Path, frames: int = 256) -> torch.Tensor:
    return torch.from_numpy(wdata.Frames(data).batch(np.random.default_rng(12345), frames))


@torch.no_grad()
def score(encoder: nn.Module, decoder: nn.Module, images: torch.Tensor) -> tuple[float, float]:
    """PSNR and sharpness ratio of decode(encode(x)) over `images`."""
    was_training = decoder.training
    decoder.eval()
    y = torch.cat([decoder(encoder(c)) for c in images.split(64)])
    decoder.train(was_training)
    return psnr(to_u8(y), to_u8(images)), sharpness_ratio(to_u8(y), to_u8(images))


def sharpen_decoder(data: Path, val: Path | None, run: Path, steps: int, batch: int, lr: float, edge_weight: float,
                    adversarial_weight: float, adversarial_start: int, ema_decay: float, device: str,
                    minutes: float | None, start_from: Path | None = None) -> None:
    dev = pick_device(device)
    ae = load_autoencoder(run, dev)
    if start_from is not None and not (run / CHECKPOINT).exists():
        decoder_from(start_from, ae)
        print(f"the decoder starts from {start_from}'s")
    encoder = ae.encoder.eval().requires_grad_(False)
    decoder = ae.decoder.train()
    ema = copy.deepcopy(decoder).eval().requires_grad_(False)
    disc = PatchDiscriminator().to(dev)
    opt_g = torch.optim.Adam(decoder.parameters(), lr=lr, betas=(0.5, 0.9))
    opt_d = torch.optim.Adam(disc.parameters(), lr=lr, betas=(0.5, 0.9))
    settings = {"edge_weight": edge_weight, "adversarial_weight": adversarial_weight,
                "adversarial_start": adversarial_start, "ema_decay": ema_decay, "latent_noise": LATENT_NOISE,
                "discriminator": "PatchGAN, spectral norm"}
    ckpt = run / CHECKPOINT
    step = 0
    if ckpt.exists():
        state = torch.load(ckpt, map_location=dev)
        if state["settings"] != settings:
            raise SystemExit(f"--run: {ckpt} was trained with {state['settings']}, not {settings}; use another run folder")
        decoder.load_state_dict(state["decoder"])
        ema.load_state_dict(state["ema"])
        disc.load_state_dict(state["disc"])
        opt_g.load_state_dict(state["opt_g"])
        opt_d.load_state_dict(state["opt_d"])
        step = state["step"]
        print(f"resuming the decoder fine-tune at step {step}")
    last = decoder.net[-1].weight
    frames = wdata.Frames(data)
    check = held_out(val or data)
    rng = np.random.default_rng(10_000 + step)
    deadline = time.time() + minutes * 60 if minutes is not None else math.inf

    def checkpoint():
        save(ckpt, decoder=decoder.state_dict(), ema=ema.state_dict(), disc=disc.state_dict(), opt_g=opt_g.state_dict(),
             opt_d=opt_d.state_dict(), step=step, settings=settings)

    if step == 0:
        p, s = score(encoder, ema, check)
        print(f"before: held-out PSNR {p:.2f} dB, sharpness {s:.3f}")
        log(run, {"stage": "sharpen", "step": 0, "val_psnr": p, "val_sharpness": s})
    bar = tqdm(total=steps, initial=step, desc="sharpen decoder", unit="step")
    while step < steps and time.time() < deadline:
        x = torch.from_numpy(frames.batch(rng, batch)).to(dev)
        with torch.no_grad():
            z = encoder(x)
            z = z + LATENT_NOISE * z.std() * torch.randn_like(z)
        y = decoder(z)
        reconstruction = F.l1_loss(y, x) + edge_weight * gradient_difference(y, x)
        loss = reconstruction
        adversarial_on = adversarial_weight > 0 and step >= adversarial_start
        weight = torch.tensor(0.0)
        if adversarial_on:
            g_adv = -disc(y).mean()
            weight = adversarial_weight * adaptive_weight(reconstruction, g_adv, last)
            loss = reconstruction + weight * g_adv
        optimise(decoder, ema, opt_g, loss, ema_decay)
        d_loss = torch.tensor(0.0)
        if adversarial_weight > 0:
            # The hinge loss on real frames and the decoder's (detached) output.
            d_loss = hinge_discriminator(disc(x), disc(y.detach()))
            opt_d.zero_grad(set_to_none=True)
            d_loss.backward()
            opt_d.step()
        step += 1
        bar.update(1)
        if step % 50 == 0:
            record = {"stage": "sharpen", "step": step, "reconstruction": reconstruction.item(), "d_loss": d_loss.item(),
                      "adversarial_weight": float(weight)}
            if step % 500 == 0:
                record["val_psnr"], record["val_sharpness"] = score(encoder, ema, check)
                checkpoint()
            bar.set_postfix({k: f"{v:.3f}" for k, v in record.items() if k not in ("stage", "step")})
            log(run, record)
    bar.close()
    checkpoint()
    p, s = score(encoder, ema, check)
    print(f"decoder fine-tune at step {step}: held-out PSNR {p:.2f} dB, sharpness {s:.3f} (EMA weights)")


def swap_decoder(model_dir: Path, run: Path, out: Path, half: bool) -> None:
    """`out`: `model_dir` with the EMA decoder of `run`'s fine-tune in place of
    its own. The encoder (so the latent space), denoiser and any fusion head
    are copied unchanged; the decoder's graph and reference are rewritten and
    the manifest records what the decoder is."""

    state = torch.load(run / CHECKPOINT, map_location="cpu")
    ae = load_autoencoder(run, torch.device("cpu"))
    manifest = json.loads((model_dir / "manifest.json").read_text())
    check_same_encoder(ae.encoder, model_dir, f"--run: {run}'s encoder")
    ae.decoder.load_state_dict(state["ema"])
    ae.decoder.eval()
    if half:
        round_to_half(ae.decoder)
    if out.resolve() != model_dir.resolve():
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(model_dir, out)
    with torch.no_grad():
        raw = torch.from_numpy(np.load(out / "reference" / "decoder" / "latent.npy"))
        image = ae.decoder(raw)
    proto = to_onnx(ae.decoder, (raw,), ["latent"], ["image"])
    if half:
        store_half(proto)
    onnx.save(proto, out / manifest["autoencoder"]["decoder"]["file"])
    save_arrays(out / "reference" / "decoder", {"latent": raw.numpy(), "image": image.numpy()})
    manifest["name"] = out.name
    manifest["autoencoder"]["decoder"]["trained"] = {
        "method": "decoder fine-tuned with the encoder frozen (SD ft-EMA style): L1 + gradient difference + PatchGAN hinge, "
                  "VQGAN's adaptive weight; EMA weights",
        "steps": int(state["step"]), **state["settings"], "decoder_from": model_dir.name,
    }
    if "metrics" in manifest:
        # Its decoded-frame figures were measured with the decoder this one replaces.
        manifest["metrics"]["decoder"] = f"measured with {model_dir.name}'s decoder, before the swap"
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    print(f"wrote {out}: {model_dir.name} with the decoder of {run} (step {state['step']})")
