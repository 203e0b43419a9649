"""Few-step distillation of a trained CDiT's DDIM sampler.

The method is progressive distillation's target (Salimans & Ho, 2022, eq. 8)
over a fixed student grid in one round: the student takes one DDIM step per
segment of its grid (e.g. 999 -> 499 -> clean), and learns to land where the
teacher lands after `teacher_steps` DDIM steps over the same segment. Inputs
are the forward process's noisy latents at the segment's start, as in
progressive distillation, with the teacher's own conditioning (context noise
levels, warps), so the student sees what the teacher saw.

One round instead of halving rounds because the teacher is already a short
sampler (the served one takes 10 DDIM steps): the targets of a 2-step
student are 5-step teacher segments, cheap enough to compute on every batch.

The student predicts v (Salimans & Ho's v-parameterisation): at t = 999 the
signal is 0.6% of the state, and an epsilon-predicting student's clean-frame
estimate would amplify its error 158-fold there. Its exported graph turns v
back into epsilon (`EpsFromV`), so the Rust sampler and every backend run it
unchanged; the manifest's `diffusion.distilled` names the grid it must be
sampled on.

`edge_weight` > 0 adds the gradient difference loss of Mathieu, Couprie &
LeCun (2016, "Deep multi-scale video prediction beyond mean square error"),
eq. 5 with alpha 1, on the frozen decoder's images of the student's and the
target's clean frames: whatever a one-step student cannot place exactly, the
latent MSE alone spreads into blur; this term asks for edges as strong as the
teacher's where they are.

`adversarial_weight` > 0 adds an adversarial term, as Adversarial Diffusion
Distillation does (Sauer et al. 2023, "Adversarial Diffusion Distillation":
a one-step student initialised from the diffusion model, trained against a
discriminator on its samples beside the distillation loss): a regression
target alone gives the mean of what could be there, which is blur wherever
the context leaves the frame open (the warp's holes, new ground). The
discriminator is the conditional PatchGAN of the fusion head's pix2pix
training (losses.PatchDiscriminator), on the decoded frame beside the warp it
was made from (image and landed mask); real frames are the clean latents
decoded by the same decoder. The decoder is the one the student will be
served with (`decoder_from`, e.g. the sharpened one), frozen. The term's
weight is VQGAN's adaptive one at the student's last layer, times
`adversarial_weight`, from step `adversarial_start` on (the discriminator
trains from the first step), at most `adversarial_cap`: when the
discriminator wins outright its gradient at the last layer shrinks and the
adaptive weight, a ratio of gradient norms, runs away. `standardise_judged`: the
discriminator judges frames (and the warp beside them) standardised by the real frames'
mean and spread; a spectral-normalised discriminator moves its logits at most as far as
its input moves, and on dark, low-contrast frames the real and generated patches lie
closer than its hinge margin. `judge_holes`: both terms weight each
discriminator patch by its share of the warp's holes (plus a floor of
0.05): where the warp landed, real and generated frames are nearly the same
and the patches there teach it nothing. `judge` "teacher" replaces the pixel
PatchGAN with Latent Adversarial Diffusion Distillation's discriminator
(Sauer et al. 2024; losses.TeacherFeatureJudge): the student's clean latent
and the true one, re-noised to a level below `judge_noise`, through the
frozen teacher, a small head per block on its tokens; it judges latents with
the teacher's conditioning (context, action, warp), and no frame is decoded.
`judge_lr`: the discriminator's learning rate when it differs from the
student's (the two time-scale rule of Heusel et al. 2017: a discriminator
that learns faster keeps up with its generator). Where ADD distils the teacher's score, this
keeps progressive distillation's target: the teacher here is a short
deterministic sampler, whose landing point is cheap and exact."""

from __future__ import annotations

import copy
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
from ..core.losses import (PatchDiscriminator, TeacherFeatureJudge, adaptive_weight, gradient_difference,
                           hinge_discriminator, patch_mean)
from ..core.recipe import ContextAugmenter, Recipe
from ..core.student import parse_grid
from ..core.warp import batch_warp_pixels, warp_input
from ..io.checkpoints import load_autoencoder, load_optimiser, log, pick_device, run_config, save
from ..io.graphs import decoder_from as load_decoder
from .denoiser import optimise


def segment_times(start: torch.Tensor, end: torch.Tensor, steps: int) -> list[torch.Tensor]:
    """Per item, the `steps` timesteps the teacher visits from `start` towards
    `end`: evenly over [start, end) for an inner segment, over [start, 0] for
    one that ends clean (end -1), as the runtime's DDIM ends its own samples."""
    s, last, clean = start.float(), end.clamp_min(0).float(), end < 0
    out = []
    for j in range(steps):
        frac = torch.where(clean, j / max(steps - 1, 1), j / steps)
        out.append(torch.round(s - frac * (s - last)).long())
    return out


@torch.no_grad()
def teacher_segment(eps_fn, alpha_bar: torch.Tensor, x: torch.Tensor, start: torch.Tensor, end: torch.Tensor,
                    steps: int) -> torch.Tensor:
    """The teacher's deterministic DDIM from `x` at `start` to `end` (-1: clean) in `steps` steps."""
    abar = lambda t: torch.where(t >= 0, alpha_bar[t.clamp_min(0)], 1.0).view(-1, 1, 1, 1)
    times = segment_times(start, end, steps)
    for j, t in enumerate(times):
        ab, ab_next = abar(t), abar(times[j + 1] if j + 1 < steps else end)
        eps = eps_fn(x, t.float())
        x0 = (x - (1 - ab).sqrt() * eps) / ab.sqrt()
        x = ab_next.sqrt() * x0 + (1 - ab_next).sqrt() * eps
    return x


def distillation_record(grid, teacher_path, teacher_step, teacher_steps, edge_weight, adversarial, in_pixels, judge_noise,
                        judge_lr, adversarial_weight, adversarial_start, origin, adversarial_cap, judged, judge_holes,
                        decoder_from) -> dict:
    """What the manifest says of how the student was made."""
    record = {"method": "progressive distillation target (Salimans & Ho 2022), one round", "timesteps": grid,
              "teacher": str(teacher_path), "teacher_steps": teacher_step, "teacher_steps_per_segment": teacher_steps,
              "prediction": "v (exported as epsilon)"}
    if edge_weight > 0:
        record["edge_weight"] = edge_weight
    if adversarial:
        record["adversarial"] = {"method": "Adversarial Diffusion Distillation's adversarial term (Sauer et al. 2023): "
                                           "conditional PatchGAN on decoded frames, hinge loss, VQGAN's adaptive weight"
                                 if in_pixels else
                                 "Latent Adversarial Diffusion Distillation (Sauer et al. 2024): the frozen teacher's "
                                 "block features of re-noised latents, a head per block, hinge loss, VQGAN's adaptive weight",
                                 "judge_noise": None if in_pixels else judge_noise, "judge_lr": judge_lr,
                                 "weight": adversarial_weight, "start": adversarial_start, "from_step": origin,
                                 "cap": adversarial_cap, "judged_scale": judged, "judged_by_holes": judge_holes,
                                 "decoder": str(decoder_from) if decoder_from else "the run's"}
    return record


@torch.no_grad()
def judged_scale(source, autoencoder, batch: int, dev) -> tuple[float, float]:
    """The real frames' mean and spread, from one batch of them, fixed for the run: spectral
    normalisation bounds how far the discriminator's logits move per unit of input, so on
    dark, low-contrast frames (Doom's: std 0.19 in [-1, 1]) real and generated patches lie
    too close for its hinge margin; standardised, they lie as far apart as on any world."""
    probe = torch.from_numpy(source.batch(np.random.default_rng(5000), batch).target).to(dev)
    frames = autoencoder.decoder(probe / autoencoder.scale)
    print(f"the discriminator judges frames standardised by mean {frames.mean().item():.3f}, std {frames.std().item():.3f}")
    return frames.mean().item(), frames.std().item()


def judge_for(in_pixels, disc, judged, warped, landed, image, x0, x0_student, autoencoder, teacher, judge_noise, alpha_bar,
              action, rel_time, groups, rates, warp_in):
    """What the discriminator sees of a batch: the generated sample, a thunk for the real one,
    and the function that judges either. Pixels: decoded frames beside the warp; teacher:
    latents re-noised alike (one level and one noise per sample) through the frozen teacher."""
    if in_pixels:
        mean, std = judged or (0.0, 1.0)
        scaled = lambda frame: (frame - mean) / std
        condition = torch.cat([scaled(warped.permute(0, 3, 1, 2).float() / 127.5 - 1.0) * landed[:, None],
                               landed[:, None].float()], dim=1)
        return image, lambda: autoencoder.decoder(x0 / autoencoder.scale), \
            lambda frame: disc(torch.cat([scaled(frame), condition], dim=1))
    t_judge = torch.randint(0, judge_noise, (len(x0),), device=x0.device)
    ab_judge = alpha_bar[t_judge].view(-1, 1, 1, 1)
    noise_judge = torch.randn_like(x0)

    def judge_of(latent):
        features = []
        teacher(ab_judge.sqrt() * latent + (1 - ab_judge).sqrt() * noise_judge, t_judge.float(), action,
                rel_time, groups, rates=rates, warp=warp_in, features=features)
        return disc(features)

    return x0_student, lambda: x0, judge_of


def check_judge(adversarial: bool, cfg, teacher_path: Path, judge: str, standardise_judged: bool, judge_noise: int) -> None:
    if adversarial and not cfg.cdit.warp:
        raise SystemExit("--adversarial-weight: the discriminator judges a frame beside its warp; "
                         f"{teacher_path} is not a geometry model (no warp input)")
    if judge not in ("pixels", "teacher"):
        raise SystemExit(f"--judge: pixels or teacher, got {judge!r}")
    if judge == "teacher" and standardise_judged:
        raise SystemExit("--standardise-judged: the teacher judges latents, which are already standardised")
    if not 0 < judge_noise <= cfg.diffusion.timesteps:
        raise SystemExit(f"--judge-noise: a timestep in 1..{cfg.diffusion.timesteps}, got {judge_noise}")


def resume_student(ckpt: Path, grid: list[int], student, ema, opt, disc, opt_d, standardise_judged: bool,
                   judge: str) -> tuple[int, int, tuple | None]:
    """The student, its optimiser and, when it judged the same inputs, its discriminator from
    a checkpoint: the step, the step the adversarial fine-tune began at, the judged scale."""
    dev = next(student.parameters()).device
    adversarial = disc is not None
    saved = torch.load(ckpt, map_location=dev, weights_only=False)
    if saved["distilled"]["timesteps"] != grid:
        raise SystemExit(f"--grid: {ckpt} was distilled for {saved['distilled']['timesteps']}, not {grid}")
    # A checkpoint moved between machines may carry only its EMA weights.
    student.load_state_dict(saved.get("model", saved["ema"]))
    ema.load_state_dict(saved["ema"])
    load_optimiser(opt, saved, ckpt)
    step = saved["step"]
    origin = saved.get("adversarial_origin", step)
    judged = saved.get("judged_scale")
    kind = saved.get("judge_kind", "pixels")
    if adversarial and "disc" in saved and (judged is not None) == standardise_judged and kind == judge:
        disc.load_state_dict(saved["disc"])
        load_optimiser(opt_d, saved, ckpt, key="opt_d")  # at --judge-lr, not the saved rate
    elif adversarial and "disc" in saved:
        # A discriminator trained on other inputs would judge these by the wrong measure.
        what = f"{'standardised' if judged else 'raw'} frames" if kind == "pixels" else "latents through the teacher"
        print(f"a fresh discriminator: {ckpt.name}'s judged {what}")
        judged, origin = None, step
    print(f"resuming {ckpt.name} at step {step}")
    return step, origin, judged


def clean_target(target_state: torch.Tensor, x_t: torch.Tensor, ab: torch.Tensor, ab_end: torch.Tensor) -> torch.Tensor:
    """The clean frame that one DDIM step from x_t must predict to land on the teacher's state (eq. 8)."""
    ratio = ((1 - ab_end) / (1 - ab)).sqrt()
    return (target_state - ratio * x_t) / (ab_end.sqrt() - ratio * ab.sqrt())


def discriminator_step(judge_of, judged_real, judged_fake: torch.Tensor, weigh, opt_d) -> torch.Tensor:
    """One hinge step of the discriminator on a real and a generated batch; its loss."""
    with torch.no_grad():
        real = judged_real()
    real_logits = judge_of(real)
    d_loss = hinge_discriminator(real_logits, judge_of(judged_fake.detach()), weigh(real_logits))
    opt_d.zero_grad(set_to_none=True)
    d_loss.backward()
    opt_d.step()
    return d_loss


def distill(data: Path, run: Path, policy: str, grid_text: str, teacher_steps: int, steps: int, batch: int, lr: float,
            ema_decay: float, device: str, minutes: float | None, edge_weight: float = 0.0,
            adversarial_weight: float = 0.0, adversarial_start: int = 0, decoder_from: Path | None = None,
            adversarial_cap: float | None = None, standardise_judged: bool = False, judge_holes: bool = False,
            judge: str = "pixels", judge_noise: int = 500, judge_lr: float | None = None) -> None:
    cfg = run_config(run)
    dev = pick_device(device)
    grid = parse_grid(grid_text, cfg.diffusion.timesteps)
    if teacher_steps < 1:
        raise SystemExit(f"--teacher-steps: at least 1 per segment, got {teacher_steps}")
    teacher_path = run / f"cdit-{policy}.pt"
    if not teacher_path.exists():
        raise SystemExit(f"--run: no {teacher_path}; `recover` the served model into it first")
    state = torch.load(teacher_path, map_location=dev, weights_only=False)
    recipe = Recipe(**{k: v for k, v in state.get("recipe", {}).items() if k in Recipe().to_json()})
    memory_focus = float(state.get("memory_focus", 0.0))
    teacher = CDiT(cfg.cdit).to(dev)
    teacher.load_state_dict(state["ema"])
    teacher.eval().requires_grad_(False)
    student = copy.deepcopy(teacher).train().requires_grad_(True)
    ema = copy.deepcopy(teacher).requires_grad_(False)
    opt = torch.optim.AdamW(student.parameters(), lr=lr, weight_decay=0.0)
    adversarial = adversarial_weight > 0
    check_judge(adversarial, cfg, teacher_path, judge, standardise_judged, judge_noise)
    in_pixels = adversarial and judge == "pixels"
    # Pixels: conditional on the warp, the frame (3), the warped image (3) and where it landed (1).
    disc = None if not adversarial else (PatchDiscriminator(channels=7) if in_pixels else
                                         TeacherFeatureJudge(cfg.cdit.hidden, cfg.cdit.depth)).to(dev)
    opt_d = torch.optim.Adam(disc.parameters(), lr=judge_lr or lr, betas=(0.5, 0.9)) if adversarial else None

    name = f"distilled-{policy}-{len(grid)}"
    ckpt = run / f"{name}.pt"
    step = origin = 0  # origin: the step this adversarial fine-tune began at (`adversarial_start` counts from it)
    judged = None  # (mean, std) the discriminator's inputs are standardised by, when they are
    if ckpt.exists():
        step, origin, judged = resume_student(ckpt, grid, student, ema, opt, disc, opt_d, standardise_judged, judge)

    layout = LAYOUTS[policy]
    source = wdata.PlannedLatents(data, run / "latents", policy, layout, memory_focus, warp=cfg.cdit.warp)
    decoded = edge_weight > 0 or in_pixels
    autoencoder = load_autoencoder(run, dev).requires_grad_(False) if cfg.cdit.warp or decoded else None
    if decoder_from is not None:

        load_decoder(decoder_from, autoencoder)
    if adversarial and standardise_judged and judged is None:
        judged = judged_scale(source, autoencoder, batch, dev)
    alpha_bar = torch.tensor(Schedule(cfg.diffusion).alphas_cumprod, dtype=torch.float32, device=dev)
    augment = ContextAugmenter(recipe, source, layout.rates, alpha_bar, cfg.cdit.context_noise, 3000 + step, dev)
    rng = np.random.default_rng(4000 + step)
    torch.manual_seed(4000 + step)
    starts = torch.tensor(grid, device=dev)
    ends = torch.tensor(grid[1:] + [-1], device=dev)
    record = distillation_record(grid, teacher_path, state["step"], teacher_steps, edge_weight, adversarial, in_pixels,
                                 judge_noise, judge_lr or lr, adversarial_weight, adversarial_start, origin, adversarial_cap,
                                 judged, judge_holes, decoder_from)
    extra = lambda: dict(disc=disc.state_dict(), opt_d=opt_d.state_dict(), adversarial_origin=origin,
                         judged_scale=judged, judge_kind=judge) if adversarial else {}
    checkpoint = lambda: save(ckpt, model=student.state_dict(), ema=ema.state_dict(), opt=opt.state_dict(), step=step,
                              policy=policy, memory_focus=memory_focus, recipe=recipe.to_json(), distilled=record,
                              init_from=str(teacher_path), plans_query=source.plans_query,
                              data=state.get("data", wdata.describe(data)), **extra())
    deadline = time.time() + minutes * 60 if minutes is not None else math.inf
    bar = tqdm(total=steps, initial=step, desc=name, unit="step")
    started, seen = time.time(), 0
    while step < steps and time.time() < deadline:
        drawn = source.batch(rng, batch)
        x0, action, rel_time, groups = augment(drawn, teacher)
        warp_in = None
        if cfg.cdit.warp:
            warped, landed = batch_warp_pixels(source, drawn, dev)
            warp_in = warp_input(autoencoder.encoder, autoencoder.scale, warped, landed, autoencoder.cfg.downsample)
        k = torch.randint(0, len(grid), (batch,), device=dev)
        t, end = starts[k], ends[k]
        ab = alpha_bar[t].view(-1, 1, 1, 1)
        ab_end = torch.where(end >= 0, alpha_bar[end.clamp_min(0)], 1.0).view(-1, 1, 1, 1)
        x_t = ab.sqrt() * x0 + (1 - ab).sqrt() * torch.randn_like(x0)
        teacher_eps = lambda x, tt: teacher(x, tt, action, rel_time, groups, rates=layout.rates, warp=warp_in)
        x0_target = clean_target(teacher_segment(teacher_eps, alpha_bar, x_t, t, end, teacher_steps), x_t, ab, ab_end)
        v = student(x_t, t.float(), action, rel_time, groups, rates=layout.rates, warp=warp_in)
        x0_student = ab.sqrt() * x_t - (1 - ab).sqrt() * v
        loss = F.mse_loss(x0_student, x0_target)
        image = autoencoder.decoder(x0_student / autoencoder.scale) if decoded else None
        if edge_weight > 0:
            with torch.no_grad():
                image_target = autoencoder.decoder(x0_target / autoencoder.scale)
            loss = loss + edge_weight * gradient_difference(image, image_target)
        d_loss = weight = torch.tensor(0.0)
        if adversarial:
            judged_fake, judged_real, judge_of = judge_for(in_pixels, disc, judged, warped, landed, image, x0, x0_student,
                                                           autoencoder, teacher, judge_noise, alpha_bar, action, rel_time,
                                                           groups, layout.rates, warp_in)
        if adversarial:
            # With judge_holes, each patch counts by its share of the warp's holes (a floor keeps the rest in play).
            weigh = lambda logits: (F.adaptive_avg_pool2d(1.0 - landed[:, None].float(), logits.shape[-2:]) + 0.05
                                    if judge_holes else None)
            if step - origin >= adversarial_start:
                fake = judge_of(judged_fake)
                g_adv = -patch_mean(fake, weigh(fake))
                weight = adversarial_weight * adaptive_weight(loss, g_adv, student.final.weight)
                if adversarial_cap is not None:
                    weight = weight.clamp(max=adversarial_cap)
                loss = loss + weight * g_adv
        optimise(student, ema, opt, loss, ema_decay)
        if adversarial:
            d_loss = discriminator_step(judge_of, judged_real, judged_fake, weigh, opt_d)
        step += 1
        seen += batch
        bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{loss.item():.4f}", d_loss=f"{d_loss.item():.3f}", weight=f"{float(weight):.3f}")
            log(run, {"stage": name, "step": step, "loss": loss.item(), "d_loss": d_loss.item(),
                      "adversarial_weight": float(weight), "samples_per_s": seen / (time.time() - started)})
        if step % 500 == 0:
            checkpoint()
    bar.close()
    checkpoint()
    print(f"{name} at step {step} ({seen / max(time.time() - started, 1e-9):.1f} samples/s this run)")
