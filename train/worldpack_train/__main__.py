"""`python -m worldpack_train <stage>`: `make` (what `worldpack train` runs: the whole recipe,
pipeline.py), and the stages it is made of for those who run them by hand: train-ae, encode,
train, variants, distill, export, paper-scale, recover, fusion-train, fusion-export,
fusion-strip, fusion-pair, warp-frames, sharpen-decoder, swap-decoder (docs/training.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from . import pipeline, settings
from .core.config import LAYOUTS
from .core.recipe import Recipe
from .io import manifest
from .stages import autoencoder, denoiser, distill, export, fusion, paper_scale, recover, sharpen


def recipe_options(p):
    g = p.add_argument_group("training for autoregressive stability (recipe.py; all off by default)")
    g.add_argument("--context-noise", type=float, default=0.0, help="largest noise level on context latents (0: off)")
    g.add_argument("--context-noise-share", type=float, default=0.5, help="share of context frames that get noise")
    g.add_argument("--rollout-share", type=float, default=0.0,
                   help="share of each batch whose newest context frame is the model's own prediction (0: off)")
    g.add_argument("--rollout-steps", type=int, default=4, help="DDIM steps for those predictions")
    g.add_argument("--generated-level", type=float, default=0.0,
                   help="context noise level that marks a generated frame (in training and, via the manifest, at inference)")
    g.add_argument("--pose-noise-translation", type=float, default=0.0, help="sd of context pose noise, blocks")
    g.add_argument("--pose-noise-degrees", type=float, default=0.0, help="sd of context rotation noise, degrees")
    g.add_argument("--pose-noise-share", type=float, default=1.0,
                   help="share of each batch's items whose context and warp-source poses get that noise")

def recipe_of(a):
    return Recipe(a.context_noise, a.context_noise_share, a.rollout_share, a.rollout_steps, a.generated_level,
                  a.pose_noise_translation, a.pose_noise_degrees, a.pose_noise_share)

def common(p, data=True):
    if data:
        p.add_argument("--data", type=Path, required=True, help="a suite from `worldpack sim dataset`")
    p.add_argument("--run", type=Path, required=True, help="run folder: config, checkpoints, logs")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")


def add_product(sub) -> None:
    """The one command: a dataset folder to a served model folder."""
    p = sub.add_parser("make", help="the whole recipe, a dataset folder to a served model folder with its card "
                       "(pipeline.py; what `worldpack train` runs; resumes when run again)")
    p.add_argument("--data", type=Path, required=True, help="a suite in the dataset format (docs/dataset.md)")
    p.add_argument("--out", type=Path, required=True, help="the model folder to write (train.json, lineage.json, "
                   "train.log, MODEL.md beside the graphs)")
    p.add_argument("--from", dest="source", help="fine-tune from a shipped family (voxel, doom) or a folder "
                   "`worldpack train` wrote; default: from scratch")
    p.add_argument("--hours", type=float, help="the whole command's budget in hours (default 2)")
    p.add_argument("--device", choices=["cpu", "cuda"], help="where the training stages run (default cpu)")
    p.add_argument("--heldout", type=Path, help="a suite to evaluate on instead of a split of --data")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a setting of train.json on a new run, e.g. teacher.steps=500 (JSON values)")
    p.add_argument("--bin", type=Path, required=True, help="the worldpack binary (check, plan, eval)")
    p.add_argument("--repo", type=Path, default=Path.cwd(), help="where the shipped families' fixtures/ are")


def add_training(sub) -> None:
    """The training stages: autoencoder, latents, CDiT, the paper's variants, the distilled student."""
    p = sub.add_parser("train-ae", help="train the autoencoder (resumes from run/autoencoder.pt)")
    common(p)
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--minutes", type=float, help="stop (and checkpoint) after this much wall time")
    p = sub.add_parser("encode", help="cache every frame's scaled latent under run/latents")
    common(p)
    p = sub.add_parser("train", help="train the CDiT on one policy's plans (resumes from run/cdit-<policy>.pt); "
                       "trains the autoencoder and caches latents first when they are missing")
    common(p)
    p.add_argument("--policy", default="worldpack", choices=sorted(LAYOUTS))
    p.add_argument("--steps", type=int, default=20000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument("--minutes", type=float)
    p.add_argument("--init-from", type=Path, help="fine-tune from this CDiT checkpoint (its EMA weights)")
    p.add_argument("--memory-focus", type=float, default=0.0,
                   help="share of each batch drawn from targets that need memory beyond the 4 newest frames "
                        "(needs `worldpack plan --memory-need`; 0: uniform)")
    p.add_argument("--warp", action="store_true",
                   help="the geometry model: a stored frame depth-warped into the target view is a model input (warp.py)")
    recipe_options(p)
    p = sub.add_parser("variants", help="the paper's order: the 4-frame baseline from scratch, then nearest frame "
                       "packing, memory retrieval and WorldPack each fine-tuned from it (resumable, one stage at a time)")
    common(p)
    p.add_argument("--baseline-steps", type=int, default=20000)
    p.add_argument("--fraction", type=float, default=0.2, help="each fine-tune's steps as a fraction of the baseline's (paper: 200k / 1M)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument("--minutes", type=float, help="wall-time budget for this sitting, shared by the stages")
    p.add_argument("--memory-focus", type=float, default=0.0,
                   help="the fine-tunes' share of each batch from targets that need memory (see train)")
    p.add_argument("--baseline", type=Path,
                   help="fine-tune from this finished baseline checkpoint instead of training one in --run")
    p.add_argument("--policies", help="comma-separated fine-tunes (default: nearest_frame_packing,memory_retrieval,worldpack)")
    recipe_options(p)
    p = sub.add_parser("distill", help="distil a trained CDiT's DDIM sampler into a few-step student "
                       "(distill.py; resumes from run/distilled-<policy>-<N>.pt)")
    common(p)
    p.add_argument("--policy", default="worldpack", help="the teacher: run/cdit-<policy>.pt (e.g. from `recover`)")
    p.add_argument("--grid", default="999,499", help="the student's descending timesteps, one DDIM step each")
    p.add_argument("--teacher-steps", type=int, default=5, help="teacher DDIM steps per segment of the grid")
    p.add_argument("--steps", type=int, default=20000)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument("--minutes", type=float)
    p.add_argument("--edge-weight", type=float, default=0.0,
                   help="weight of the gradient difference loss on decoded frames (Mathieu et al. 2016); 0: latent MSE only")
    p.add_argument("--adversarial-weight", type=float, default=0.0,
                   help="times VQGAN's adaptive weight: ADD's adversarial term on decoded frames (a conditional "
                        "PatchGAN beside the warp); 0: off")
    p.add_argument("--adversarial-start", type=int, default=200,
                   help="the step from which the student feels the discriminator (it trains from the first)")
    p.add_argument("--decoder-from", type=Path,
                   help="a model folder whose decoder renders the frames the discriminator judges (the one the "
                        "student will be served with); default: the run's")
    p.add_argument("--adversarial-cap", type=float,
                   help="the most the adversarial term's weight (adaptive weight times --adversarial-weight) may "
                        "reach; default: no cap")
    p.add_argument("--standardise-judged", action="store_true",
                   help="the discriminator judges frames standardised by the real frames' mean and standard "
                        "deviation (measured on the first batch), not raw [-1, 1] values: for dark, low-contrast worlds")
    p.add_argument("--judge-holes", action="store_true",
                   help="weight each discriminator patch (in both terms) by its share of the warp's holes, where "
                        "real and generated frames differ")
    p.add_argument("--judge", choices=("pixels", "teacher"), default="pixels",
                   help="the discriminator: pixels, a conditional PatchGAN on decoded frames (ADD); teacher, heads on "
                        "the frozen teacher's block features of re-noised latents (LADD, Sauer et al. 2024)")
    p.add_argument("--judge-noise", type=int, default=500,
                   help="with --judge teacher: latents are re-noised to a timestep drawn below this one")
    p.add_argument("--judge-lr", type=float, help="the discriminator's learning rate (default: --lr)")


def add_models(sub) -> None:
    """Model folders: export, the paper-scale fixture, recovery into a run, the warp's frame count."""
    p = sub.add_parser("export", help="write ONNX graphs, manifest.json and references to --out")
    common(p, data=False)
    p.add_argument("--policy", default="worldpack", help="which checkpoint: run/cdit-<policy>.pt")
    p.add_argument("--layouts", default="worldpack,baseline", help="comma-separated context layouts to export")
    p.add_argument("--data", type=Path, required=True, help="a suite for the reference inputs and metrics (test split)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--half", action="store_true", help="round the weights to float16 and store them so (half the size)")
    p.add_argument("--distilled", type=int, help="export the N-step student run/distilled-<policy>-N.pt instead")
    p.add_argument("--fusion-from", type=Path, help="a model folder whose fusion head the export keeps (a student keeps its teacher's)")
    p.add_argument("--decoder-from", type=Path, help="a model folder whose decoder the export keeps (a sharpened one, "
                   "`sharpen-decoder`; its encoder must be the run's)")
    p = sub.add_parser("paper-scale", help="a model folder at the paper's shapes (224x224 frames, 4x28x28 latents, "
                       "844 vs 784 context tokens) with random seeded weights: --size paper (CDiT-B/2, SD-VAE-shaped "
                       "autoencoder) to benchmark, --size smoke (same tokens, narrow) for the committed fixture")
    p.add_argument("--size", default="paper", help="paper or smoke")
    p.add_argument("--data", type=Path, required=True, help="a 224x224 suite with plans, for the reference inputs")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--half", action="store_true", help="round the weights to float16 and store them so (half the size)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p = sub.add_parser("recover", help="rebuild a run folder's checkpoints (config, autoencoder, CDiT) from an exported "
                       "model folder, checked against its reference outputs, so a committed model can be fine-tuned")
    p.add_argument("--model", type=Path, required=True, help="an exported model folder (manifest.json, ONNX graphs)")
    p.add_argument("--run", type=Path, required=True, help="the run folder to write")
    p.add_argument("--policy", help="name the checkpoint cdit-<policy>.pt (default: the manifest's training policy)")
    p = sub.add_parser("warp-frames", help="set, in place, how many best-overlap observed frames the runtime fuses "
                       "into a geometry model's warp input (manifest denoiser.warp.frames)")
    p.add_argument("--model", type=Path, required=True, help="a geometry model folder")
    p.add_argument("--frames", type=int, required=True, help="frames to fuse, at least 1 (the co-visible stage keeps 32 candidates)")


def add_heads(sub) -> None:
    """The fusion heads: training, export, strip and pair."""
    p = sub.add_parser("fusion-train", help="train a geometry model's fusion head on `worldpack fusion-data` examples "
                       "(fusion.py; resumes from run/fusion.pt)")
    p.add_argument("--data", type=Path, nargs="+", required=True, help="folders written by `worldpack fusion-data`")
    p.add_argument("--run", type=Path, required=True, help="run folder: fusion.pt, fusion.log")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--width", type=int, default=24, help="channels of each convolution")
    p.add_argument("--edge-weight", type=float, default=0.0,
                   help="weight of the gradient difference loss against the truth (Mathieu et al. 2016); 0: MSE only")
    p.add_argument("--edge-landed", type=float, default=1.0,
                   help="that loss's per-pixel weight where the warp landed (1 in its holes; 0: holes only)")
    p.add_argument("--adversarial-weight", type=float, default=0.0,
                   help="a conditional PatchGAN's term on top of VQGAN's adaptive weight (pix2pix; 0: no discriminator)")
    p.add_argument("--adversarial-start", type=int, default=500,
                   help="the step from which the head feels the discriminator (it trains from step 0)")
    p.add_argument("--texture-weight", type=float, default=0.0,
                   help="weight of the patch-wise detail energy term in the warp's holes (after EnhanceNet's texture loss); 0: off")
    p.add_argument("--landed-weight", type=float, default=1.0,
                   help="weight of the regression terms where the warp landed (0: a head for the holes only)")
    p.add_argument("--init-from", type=Path,
                   help="a fusion-train run folder whose head this run starts from (a fresh optimiser, step 0)")
    p.add_argument("--minutes", type=float, help="stop (and checkpoint) after this much wall time")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p = sub.add_parser("fusion-export", help="copy a geometry model folder with the trained fusion head added")
    p.add_argument("--run", type=Path, required=True, help="the fusion-train run folder")
    p.add_argument("--model", type=Path, required=True, help="the geometry model folder the head was trained on")
    p.add_argument("--out", type=Path, required=True, help="the new model folder (its name becomes the model's)")
    p.add_argument("--data", type=Path, help="a fusion-data folder whose last examples become the references")
    p = sub.add_parser("fusion-strip", help="copy a fused model folder without its fusion head (the bare model whose "
                       "predictions `worldpack fusion-data` makes a head's examples from)")
    p.add_argument("--model", type=Path, required=True, help="the fused model folder to copy")
    p.add_argument("--out", type=Path, required=True, help="the new model folder (its name becomes the model's)")
    p = sub.add_parser("fusion-pair", help="copy a fused model folder with a head pair: another model's head makes the "
                       "frame shown, its own the frame the memory keeps (fusion.py HeadPair)")
    p.add_argument("--kept", type=Path, required=True, help="the fused model folder to copy; its head makes the frame kept")
    p.add_argument("--shown", type=Path, required=True, help="a fused model folder whose head makes the frame shown")
    p.add_argument("--out", type=Path, required=True, help="the new model folder (may be --kept itself)")
    p.add_argument("--data", type=Path, help="a fusion-data folder whose last examples become the references")
    p.add_argument("--hole-fill", type=int, default=0, help="an odd window K: in the warp's holes within K // 2 pixels of "
                   "where it landed, the kept frame's K x K mean becomes the warp's colours diffused into the hole (0: off)")
    p.add_argument("--hole-detail", type=int, default=0, help="an odd window K: in the warp's holes the frame shown "
                   "takes the decoded frame's detail beyond its K x K local mean (0: off)")
    p.add_argument("--warp-detail", type=float, default=0.0, help="a tolerance T in 8-bit levels: where the warp landed, "
                   "the frame shown takes the warp's luma detail beyond its 3x3 local mean, a half where their 5x5 local "
                   "means lie T apart (0: off)")
    p.add_argument("--holes", type=Path, help="a fused model folder whose head's luma detail the frame shown takes in "
                   "the warp's holes (a head trained with fusion-train --texture-weight)")


def add_decoder(sub) -> None:
    """The sharpened decoder: fine-tune and swap."""
    p = sub.add_parser("sharpen-decoder", help="fine-tune run/autoencoder.pt's decoder for sharp frames, the encoder "
                       "(so the latent space) frozen (sharpen.py; resumes from run/decoder-sharp.pt)")
    common(p)
    p.add_argument("--val", type=Path, help="a held-out suite for the PSNR and sharpness logged every 500 steps")
    p.add_argument("--steps", type=int, default=20000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--edge-weight", type=float, default=1.0, help="weight of the gradient difference loss")
    p.add_argument("--adversarial-weight", type=float, default=0.5,
                   help="the PatchGAN term's weight on top of VQGAN's adaptive one (0: no discriminator)")
    p.add_argument("--adversarial-start", type=int, default=500,
                   help="the step from which the decoder feels the discriminator (it trains from step 0)")
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument("--minutes", type=float, help="stop (and checkpoint) after this much wall time")
    p.add_argument("--decoder-from", type=Path, help="a model folder whose exported decoder the fine-tune starts from "
                   "(e.g. an earlier fine-tune's, committed); the discriminator starts afresh")
    p = sub.add_parser("swap-decoder", help="copy a model folder with a `sharpen-decoder` run's decoder in place of its own")
    p.add_argument("--model", type=Path, required=True, help="the model folder to copy (its encoder must be the run's)")
    p.add_argument("--run", type=Path, required=True, help="the sharpen-decoder run folder")
    p.add_argument("--out", type=Path, required=True, help="the new model folder (may be --model itself)")
    p.add_argument("--half", action="store_true", help="round the decoder to float16 and store it so")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="worldpack_train", description=__doc__)
    sub = ap.add_subparsers(dest="stage", required=True)
    for add in (add_product, add_training, add_models, add_heads, add_decoder):
        add(sub)
    return ap


def main() -> None:
    a = parser().parse_args()
    if a.stage == "make":
        pipeline.make(a.data, a.out, a.source, a.hours, a.device, a.heldout, a.bin.resolve(), a.repo.resolve(),
                      settings.overrides(a.set))
        return

    if getattr(a, "threads", 0):
        torch.set_num_threads(a.threads)
    if a.stage == "paper-scale":
        paper_scale.main(a.size, a.data, a.out, a.seed, a.half)
    elif a.stage == "recover":
        recover.recover(a.model, a.run, a.policy)
    elif a.stage == "fusion-train":
        fusion.train(a.data, a.run, a.steps, a.batch, a.lr, a.minutes, a.width, edge_weight=a.edge_weight,
                     edge_landed=a.edge_landed, adversarial_weight=a.adversarial_weight,
                     adversarial_start=a.adversarial_start, init_from=a.init_from, texture_weight=a.texture_weight,
                     landed_weight=a.landed_weight)
    elif a.stage == "fusion-export":
        fusion.export(a.run, a.model, a.out, a.data)
    elif a.stage == "fusion-strip":
        fusion.without_head(a.model, a.out)
    elif a.stage == "fusion-pair":
        fusion.pair(a.kept, a.shown, a.out, a.data, a.hole_fill, a.hole_detail, a.warp_detail, a.holes)
    elif a.stage == "warp-frames":
        manifest.set_warp_frames(a.model, a.frames)
    elif a.stage == "sharpen-decoder":
        sharpen.sharpen_decoder(a.data, a.val, a.run, a.steps, a.batch, a.lr, a.edge_weight, a.adversarial_weight,
                                a.adversarial_start, a.ema, a.device, a.minutes, a.decoder_from)
    elif a.stage == "swap-decoder":
        sharpen.swap_decoder(a.model, a.run, a.out, a.half)
    elif a.stage == "train-ae":
        autoencoder.train_autoencoder(a.data, a.run, a.steps, a.batch, a.lr, a.device, a.minutes)
    elif a.stage == "encode":
        autoencoder.encode(a.data, a.run, a.device)
    elif a.stage == "train":
        # One command from a dataset to a CDiT: earlier stages run first when their output is missing.
        if not (a.run / "autoencoder.pt").exists():
            autoencoder.train_autoencoder(a.data, a.run, 4000, 32, 1e-3, a.device, a.minutes)
        autoencoder.encode(a.data, a.run, a.device)  # skips trajectories already cached
        denoiser.train_cdit(a.data, a.run, a.policy, a.steps, a.batch, a.lr, a.ema, a.device, a.minutes, a.init_from, a.memory_focus,
                         recipe_of(a), a.warp)
    elif a.stage == "variants":
        denoiser.train_variants(a.data, a.run, a.baseline_steps, a.fraction, a.batch, a.lr, a.ema, a.device, a.minutes,
                             a.memory_focus, a.baseline, a.policies.split(",") if a.policies else None, recipe_of(a))
    elif a.stage == "export":
        export.export(a.run, a.policy, a.layouts.split(","), a.data, a.out, a.device, a.half, a.distilled, a.fusion_from, a.decoder_from)
    elif a.stage == "distill":
        distill.distill(a.data, a.run, a.policy, a.grid, a.teacher_steps, a.steps, a.batch, a.lr, a.ema, a.device, a.minutes,
                        a.edge_weight, a.adversarial_weight, a.adversarial_start, a.decoder_from, a.adversarial_cap,
                        a.standardise_judged, a.judge_holes, a.judge, a.judge_noise, a.judge_lr)


if __name__ == "__main__":
    main()
