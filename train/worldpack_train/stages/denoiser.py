"""Training: the autoencoder, latent caching, and the CDiT (DDPM, eps-prediction).
Every stage checkpoints to its run folder and resumes from it."""

from __future__ import annotations

import json
import math
from pathlib import Path
import time

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..core import data as wdata
from ..core.cdit import CDiT
from ..core.config import LAYOUTS
from ..core.diffusion import Schedule
from ..core.recipe import ContextAugmenter, Recipe
from ..core.warp import batch_warp
from ..io.checkpoints import checkpoint_step, load_autoencoder, load_optimiser, log, pick_device, run_config, save
from .autoencoder import encode, train_autoencoder


def load_initial_weights(model: CDiT, init_from: Path, dev: torch.device) -> None:
    """Fine-tuning (paper: packing variants start from the trained baseline):
    the checkpoint's EMA weights, every key accounted for. Only the parts a
    newer option adds may be missing (they start as their initialisation
    leaves them: zero-gated or re-derived), and nothing may be left over."""
    base = torch.load(init_from, map_location=dev)["ema"]
    own = model.state_dict()
    added_by_options = ("landing_gate", "context_noise_embed.", "rate_proj.", "warp_proj.")
    missing = [k for k in own if k not in base]
    unexpected = [k for k in base if k not in own]
    refused = [k for k in missing if not k.startswith(added_by_options)]
    mismatched = [f"{k} {tuple(base[k].shape)} -> {tuple(own[k].shape)}" for k in own if k in base and base[k].shape != own[k].shape]
    if refused or unexpected or mismatched:
        raise SystemExit(f"--init-from {init_from}: does not fit this run's model: missing {refused}, "
                         f"unexpected {unexpected}, other shapes {mismatched}")
    model.load_state_dict(base, strict=False)
    if any(k.startswith("rate_proj.") for k in missing):
        model.init_rate_projections_from_base()  # a baseline has only the base patchify
    fresh = sorted({k.split(".")[0] for k in missing})
    print(f"initialised from {init_from}" + (f"; new, from their initialisation: {fresh}" if fresh else ""))


def optimise(model: torch.nn.Module, ema: torch.nn.Module, opt: torch.optim.Optimizer, loss: torch.Tensor, ema_decay: float) -> None:
    """One optimiser step on `loss` (gradients clipped to norm 10), then the EMA weights follow."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    with torch.no_grad():
        for pe, pm in zip(ema.parameters(), model.parameters()):
            pe.lerp_(pm, 1 - ema_decay)


def train_cdit(data: Path, run: Path, policy: str, steps: int, batch: int, lr: float, ema_decay: float,
               device: str, minutes: float | None, init_from: Path | None, memory_focus: float = 0.0,
               recipe: Recipe | None = None, warp: bool = False) -> None:
    recipe = recipe or Recipe()
    recipe.check()
    cfg = run_config(run)
    if warp and not cfg.cdit.warp:
        if any(run.glob("cdit-*.pt")):
            raise SystemExit(f"--warp: {run} already holds CDiT checkpoints without the warp input: use another --run")
        cfg.cdit.warp = True
        (run / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))
        print(f"{run}/config.json: warp turned on (a depth-warped stored frame is now a model input)")
    if cfg.cdit.warp and recipe.rollout_share > 0:
        raise SystemExit("--rollout-share: rollout fine-tuning does not make warps for its predictions yet; use it without --warp")
    if recipe.needs_noise_input() and not cfg.cdit.context_noise:
        if any(run.glob("cdit-*.pt")):
            raise SystemExit(f"--context-noise/--generated-level need the context-noise input, and {run} already holds "
                             "CDiT checkpoints without it: use another --run (sharing autoencoder.pt and latents by links)")
        cfg.cdit.context_noise = True
        (run / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))
        print(f"{run}/config.json: context_noise turned on (a noise level per context frame is now a model input)")
    dev = pick_device(device)
    layout = LAYOUTS[policy]
    missing = set(layout.rates) - set(cfg.cdit.rates)
    if missing:
        raise SystemExit(f"--policy {policy}: the model has no projection for rates {sorted(missing)}")
    source = wdata.PlannedLatents(data, run / "latents", policy, layout, memory_focus, warp=cfg.cdit.warp)
    if memory_focus:
        print(f"{memory_focus:.0%} of each batch from the {len(source.needy):,} targets that need memory")
    model = CDiT(cfg.cdit).to(dev)
    ema = CDiT(cfg.cdit).to(dev)
    # The landing gates start at zero; at the base rate they would open over most of a short fine-tune.
    gates = [p for n, p in model.named_parameters() if n == "landing_gate"]
    rest = [p for n, p in model.named_parameters() if n != "landing_gate"]
    groups = [{"params": rest}] + ([{"params": gates, "lr": 10 * lr}] if gates else [])
    opt = torch.optim.AdamW(groups, lr=lr, weight_decay=0.0)
    sched = Schedule(cfg.diffusion)
    alpha_bar = torch.tensor(sched.alphas_cumprod, dtype=torch.float32, device=dev)
    ckpt = run / f"cdit-{policy}.pt"
    step = 0
    origin = str(init_from) if init_from is not None else None
    if ckpt.exists():
        state = torch.load(ckpt, map_location=dev)
        origin = state.get("init_from", origin)
        model.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        load_optimiser(opt, state, ckpt)
        step = state["step"]
        if state.get("memory_focus", 0.0) != memory_focus:
            raise SystemExit(f"--memory-focus: {ckpt} was trained with {state.get('memory_focus', 0.0)}, not {memory_focus}; "
                             "resume with the same value or use another --run")
        # Options added later read as their defaults in older checkpoints.
        saved = {**Recipe().to_json(), **state.get("recipe", {})}
        if saved != recipe.to_json() and "opt" in state:
            raise SystemExit(f"the recipe differs from the one {ckpt} was trained with ({saved}); "
                             "resume with the same options or use another --run")
        print(f"resuming {ckpt.name} at step {step}")
    else:
        if init_from is not None:
            load_initial_weights(model, init_from, dev)
        ema.load_state_dict(model.state_dict())
    ema.requires_grad_(False)
    rng = np.random.default_rng(1000 + step)
    torch.manual_seed(1000 + step)
    # The frozen autoencoder's encoder turns each batch's warped frames into the model's warp input.
    autoencoder = load_autoencoder(run, dev).requires_grad_(False) if cfg.cdit.warp else None
    augment = ContextAugmenter(recipe, source, layout.rates, alpha_bar, cfg.cdit.context_noise, 2000 + step, dev)
    noisy = recipe.pose_noise_translation > 0 or recipe.pose_noise_degrees > 0
    pose_noise = (recipe.pose_noise_translation, recipe.pose_noise_degrees, augment.gen) if noisy else None
    deadline = time.time() + minutes * 60 if minutes is not None else math.inf
    bar = tqdm(total=steps, initial=step, desc=f"cdit {policy}", unit="step")
    started, seen = time.time(), 0
    checkpoint = lambda: save(ckpt, model=model.state_dict(), ema=ema.state_dict(), opt=opt.state_dict(), step=step,
                              policy=policy, memory_focus=memory_focus, init_from=origin, recipe=recipe.to_json(),
                              plans_query=source.plans_query, data=wdata.describe(data))
    while step < steps and time.time() < deadline:
        drawn = source.batch(rng, batch)
        x0, action, rel_time, groups = augment(drawn, ema)
        warp_in = batch_warp(source, drawn, autoencoder, dev, pose_noise, augment.pose_noisy_items) if autoencoder is not None else None
        t = torch.randint(0, cfg.diffusion.timesteps, (batch,), device=dev)
        noise = torch.randn_like(x0)
        ab = alpha_bar[t].view(-1, 1, 1, 1)
        xt = ab.sqrt() * x0 + (1 - ab).sqrt() * noise
        # The layout's own rates, as the export passes them: a layout whose rates
        # are not a prefix of the model's must not train with the wrong projections.
        eps = model(xt, t.float(), action, rel_time, groups, rates=layout.rates, warp=warp_in)
        loss = F.mse_loss(eps, noise)
        optimise(model, ema, opt, loss, ema_decay)
        step += 1
        seen += batch
        bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{loss.item():.4f}")
            log(run, {"stage": f"cdit-{policy}", "step": step, "loss": loss.item(),
                      "samples_per_s": seen / (time.time() - started)})
        if step % 500 == 0:
            checkpoint()
    bar.close()
    checkpoint()
    print(f"cdit {policy} at step {step} ({seen / max(time.time() - started, 1e-9):.1f} samples/s this run)")


FINE_TUNED = ["nearest_frame_packing", "memory_retrieval", "worldpack"]


def train_variants(data: Path, run: Path, baseline_steps: int, fraction: float, batch: int, lr: float, ema_decay: float,
                   device: str, minutes: float | None, memory_focus: float = 0.0, baseline: Path | None = None,
                   policies: list[str] | None = None, recipe: Recipe | None = None) -> None:
    """The paper's training order. Each stage resumes its own checkpoint; a
    sitting that runs out of `minutes` stops after checkpointing and the next
    call carries on where it stopped. Fine-tunes start only from a finished
    baseline, so all of them start from the same weights: this run's own, or
    `baseline` (another run's finished checkpoint, e.g. to fine-tune with a
    changed recipe). `memory_focus` and `recipe` apply to the fine-tunes."""
    if not 0 < fraction <= 1:
        raise SystemExit(f"--fraction: must be in (0, 1], got {fraction}")
    if baseline is not None and not baseline.exists():
        raise SystemExit(f"--baseline: no checkpoint at {baseline}")
    unknown = [p for p in policies or [] if p not in LAYOUTS or p == "baseline"]
    if unknown:
        raise SystemExit(f"--policies: {unknown} are not fine-tuned variants; choose from {sorted(set(LAYOUTS) - {'baseline'})}")
    deadline = time.time() + minutes * 60 if minutes is not None else math.inf
    left = lambda: None if deadline == math.inf else max(0.0, (deadline - time.time()) / 60)
    if not (run / "autoencoder.pt").exists():
        train_autoencoder(data, run, 4000, 32, 1e-3, device, left())
    encode(data, run, device)
    base = baseline or run / "cdit-baseline.pt"
    if baseline is None:
        train_cdit(data, run, "baseline", baseline_steps, batch, lr, ema_decay, device, left(), None)
    if checkpoint_step(base) < baseline_steps:
        print(f"baseline at step {checkpoint_step(base)} of {baseline_steps}: run again to continue")
        return
    fine_steps = max(1, int(round(fraction * baseline_steps)))
    fine_tuned = policies or FINE_TUNED
    for policy in fine_tuned:
        if left() == 0:
            print("out of time for this sitting: run again to continue")
            return
        train_cdit(data, run, policy, fine_steps, batch, lr, ema_decay, device, left(), base, memory_focus, recipe)
    done = {p: checkpoint_step(run / f"cdit-{p}.pt") for p in fine_tuned}
    done["baseline"] = checkpoint_step(base)
    print("variants at steps " + ", ".join(f"{k} {v}" for k, v in done.items()))
