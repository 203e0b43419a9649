"""ONNX export: encoder, decoder and one denoiser graph per context layout,
`manifest.json` describing every tensor, and PyTorch reference inputs,
outputs and sampling traces that the torch-free tests check against.

The denoiser graphs of one model share one weights file (`denoiser.weights`,
ONNX external data), so exporting a second layout costs kilobytes."""

from __future__ import annotations

import json
from pathlib import Path
import shutil
import time

import numpy as np
import onnx
import torch
from torch import nn

from ..core import data as wdata
from ..core.cdit import CDiT
from ..core.config import ACTION_NAMES, ACTION_SCALE, LAYOUTS, Layout, ModelConfig, tokens_per_frame
from ..core.diffusion import Schedule, sample
from ..core.student import EpsFromV
from ..core.warp import batch_warp, forward_warp, warp_input
from ..io.checkpoints import load_autoencoder, run_config
from ..io.graphs import decoder_from as load_decoder
from ..io.onnx_files import context_keys, round_to_half, save_arrays, share_weights, store_half, tensor_spec, to_onnx
from ..metrics import psnr, to_u8
from .autoencoder import evaluate_autoencoder

MANIFEST_FORMAT = "worldpack-model/1"
REFERENCE_BATCH = 2
TRACE_STEPS = 4


def input_names(cfg: ModelConfig, layout: Layout) -> list[str]:
    names = ["x_t", "timestep", "action", "rel_time"]
    for r in layout.rates:
        names += [f"{k}_r{r}" for k in context_keys(cfg)]
    return names + (["warp"] if cfg.cdit.warp else [])


class LayoutGraph(nn.Module):
    """The CDiT with flat inputs in one layout's order, for export."""

    def __init__(self, model: CDiT, layout: Layout):
        super().__init__()
        self.model, self.layout = model, layout
        self.per_group = 5 if model.cfg.context_noise else 4

    def forward(self, x_t, timestep, action, rel_time, *context):
        k = self.per_group
        groups = [tuple(context[k * i: k * i + k]) for i in range(len(self.layout.rates))]
        warp = context[-1] if self.model.cfg.warp else None
        return self.model(x_t, timestep, action, rel_time, groups, rates=self.layout.rates, warp=warp)


def denoiser_io(cfg: ModelConfig, layout: Layout) -> tuple[list[dict], list[dict]]:
    c, s = cfg.cdit.latent_channels, cfg.cdit.latent_size
    ins = [
        tensor_spec("x_t", ["batch", c, s, s], "float32", "noisy target latent (already multiplied by latent_scale)"),
        tensor_spec("timestep", ["batch"], "float32", "original DDPM timestep index in [0, timesteps-1], also when respaced"),
        tensor_spec("action", ["batch", cfg.cdit.action_dim], "float32", "the action leading to the target frame, raw units (see action)"),
        tensor_spec("rel_time", ["batch"], "float32", "frames from the most recent present context frame to the target (>= 1)"),
    ]
    for r, n in zip(layout.rates, layout.counts):
        ins += [
            tensor_spec(f"context_r{r}", ["batch", n, c, s, s], "float32", f"{n} context latents at rate {r} (scaled; zeros in empty slots)"),
            tensor_spec(f"context_time_r{r}", ["batch", n], "float32", "frame time minus target time (negative; 0 in empty slots)"),
            tensor_spec(f"context_pose_r{r}", ["batch", n, 12], "float32", "context camera in the target camera frame, 3x4 row-major (see pose_embedding)"),
            tensor_spec(f"context_mask_r{r}", ["batch", n], "float32", "1 = slot holds a frame, 0 = empty (at least one slot per sample must be 1)"),
        ]
        if cfg.cdit.context_noise:
            ins.append(tensor_spec(f"context_noise_r{r}", ["batch", n], "float32",
                                   "context noise level per slot: 0 for an observed frame, denoiser.context_noise.generated_level "
                                   "for a frame the model generated (0 in empty slots)"))
    if cfg.cdit.warp:
        ins.append(tensor_spec("warp", ["batch", c + 1, s, s], "float32",
                               "a stored frame depth-warped into the target view (denoiser.warp): its scaled latent "
                               "(holes 0 in the image before encoding), then the share of each latent cell it covers"))
    outs = [tensor_spec("eps", ["batch", c, s, s], "float32", "predicted noise epsilon")]
    return ins, outs


def reference_rows(source: wdata.PlannedLatents, count: int) -> list[tuple[int, int]]:
    """Frames on the way back of the first trajectories, where memory matters:
    3/4 of the way through each, then 7/8 when the suite has too few
    trajectories (the graphs are traced at this batch, which must exceed 1)."""
    rows = []
    for fraction in (3 / 4, 7 / 8):
        for i, plans in enumerate(source.plans):
            if len(rows) == count:
                return rows
            rows.append((i, min(len(plans) - 1, int(len(plans) * fraction))))
    return rows


def export(run: Path, policy: str, layout_names: list[str], data: Path, out: Path, device: str, half: bool = False,
           distilled: int | None = None, fusion_from: Path | None = None, decoder_from: Path | None = None,
           warp_data: tuple[Path, ...] = ()) -> None:
    """A trained run's checkpoint (its EMA weights) as a model folder:
    `cdit-<policy>.pt`, or with `distilled` N the N-step student
    `distilled-<policy>-N.pt` (distill.py). `fusion_from`: a model folder
    whose fusion head the new folder keeps; `decoder_from`: one whose decoder
    it keeps (a fine-tuned decoder on the same encoder, sharpen.py); `warp_data`: more
    suites to find the warp's reference cases in when `data` has none."""
    cfg = run_config(run)
    if distilled is None:
        ckpt_path, stage = run / f"cdit-{policy}.pt", f"cdit-{policy}"
        if not ckpt_path.exists():
            raise SystemExit(f"--policy: no {ckpt_path}; train it with `train --policy {policy}`")
    else:
        ckpt_path, stage = run / f"distilled-{policy}-{distilled}.pt", f"distilled-{policy}-{distilled}"
        if not ckpt_path.exists():
            raise SystemExit(f"--distilled: no {ckpt_path}; make it with `distill --policy {policy}` and a {distilled}-step --grid")
    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    ae = load_autoencoder(run, torch.device("cpu"))
    if decoder_from is not None:

        load_decoder(decoder_from, ae)
    model = CDiT(cfg.cdit)
    model.load_state_dict(ckpt["ema"])
    if "distilled" in ckpt:

        model = EpsFromV(model, Schedule(cfg.diffusion).alphas_cumprod)
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()] if (run / "log.jsonl").exists() else []
    last = lambda stage: next((r for r in reversed(log) if r["stage"] == stage), {})
    training = {
        # Checkpoints from before they recorded their data were all trained on `worldpack sim dataset`.
        "data": {**ckpt.get("data", {"source": "worldpack sim dataset (training world seeds)"}),
                 "frame_size": [cfg.autoencoder.image_size] * 2},
        "policy": policy, "steps": ckpt["step"],
        "init_from": ckpt.get("init_from"), "memory_focus": ckpt.get("memory_focus", 0.0),
        "recipe": ckpt.get("recipe", {}),
        # Absent in checkpoints from before plans recorded it: those plans used the target pose.
        "plans_query": ckpt.get("plans_query", "target"),
        "autoencoder_steps": last("autoencoder").get("step"),
        "final_loss": last(stage).get("loss"),
        "samples_per_s": last(stage).get("samples_per_s"),
        "weights": "EMA",
    }
    # A student's first step recovers the clean frame as (x - sqrt(1 - abar) eps) / sqrt(abar) at
    # abar = 4e-5: float32 rounding of eps near x is amplified ~160-fold there, ~3e-5 in the state.
    tolerance = {"abs": 2e-4, "rel": 1e-4} if "distilled" in ckpt else None
    write_model(cfg, ae, model, layout_names, data, out, half, training=training,
                generated_level=ckpt.get("recipe", {}).get("generated_level", 0.0), distilled=ckpt.get("distilled"),
                tolerance=tolerance, warp_data=warp_data)
    if decoder_from is not None:
        manifest = json.loads((out / "manifest.json").read_text())
        theirs = json.loads((decoder_from / "manifest.json").read_text())["autoencoder"]["decoder"]
        manifest["autoencoder"]["decoder"]["trained"] = {**theirs.get("trained", {}), "from": decoder_from.name}
        (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    if fusion_from is not None:
        keep_fusion_head(fusion_from, out)


def keep_fusion_head(source: Path, out: Path) -> None:
    """Copies `source`'s fusion head (graph, references, manifest entry) into
    the model folder `out`: a distilled student keeps its teacher's head."""

    theirs = json.loads((source / "manifest.json").read_text())
    if "fusion" not in theirs:
        raise SystemExit(f"--fusion-from: {source} has no fusion head")
    ours = json.loads((out / "manifest.json").read_text())
    shutil.copy(source / theirs["fusion"]["file"], out / theirs["fusion"]["file"])
    shutil.copytree(source / "reference" / "fusion", out / "reference" / "fusion", dirs_exist_ok=True)
    ours["fusion"] = {**theirs["fusion"], "from": source.name}
    ours["reference"]["graphs"]["fusion"] = theirs["reference"]["graphs"]["fusion"]
    (out / "manifest.json").write_text(json.dumps(ours, indent=2))


def write_model(cfg: ModelConfig, ae, model: CDiT, layout_names: list[str], data: Path, out: Path, half: bool,
                training: dict | None, generated_level: float = 0.0, metrics: bool = True, created_by: str = "python -m worldpack_train export",
                tolerance: dict | None = None, distilled: dict | None = None, warp_data: tuple[Path, ...] = ()) -> None:
    """Graphs, references (inputs from `data`'s first trajectories) and the
    manifest of one model. `training` None: untrained weights (no training
    record, no policy); `metrics` False skips the held-out figures."""
    started = time.time()
    tolerance = tolerance or {"abs": 1e-5, "rel": 1e-4}
    unknown = [n for n in layout_names if n not in LAYOUTS]
    if unknown:
        raise SystemExit(f"--layouts: unknown {unknown}; known {sorted(LAYOUTS)}")
    model.eval()
    ae.eval()
    if half:
        round_to_half(ae, model)
    out.mkdir(parents=True, exist_ok=True)
    ref = out / "reference"

    latent_dir = out / ".latents-tmp"
    cache_latents(cfg, ae, data, latent_dir)
    write_autoencoder(ae, data, out, half)
    rng = np.random.default_rng(7)
    layouts_json, trace_inputs = write_denoisers(cfg, ae, model, layout_names, data, latent_dir, out, half, rng)
    sched = Schedule(cfg.diffusion)
    grid = distilled["timesteps"] if distilled else None
    traces = write_traces(sched, trace_inputs, grid, ref, rng)
    if cfg.cdit.warp:
        save_arrays(ref / "warp", warp_cases((data, *warp_data), ae))
    measured = measure(cfg, ae, model, data, latent_dir, layout_names, sched, grid) if metrics else None
    for f in latent_dir.iterdir():
        f.unlink()
    latent_dir.rmdir()

    manifest = manifest_of(cfg, ae, model, data, out.name, created_by, half, layouts_json, generated_level, distilled,
                           training, measured, tolerance, layout_names, traces)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    print(f"exported {out} in {time.time() - started:.1f} s" + (": " + json.dumps(measured) if measured else ""))


def cache_latents(cfg: ModelConfig, ae, data: Path, latent_dir: Path) -> None:
    """Latents of the reference suite (the test split), encoded now so the export needs no cache."""
    latent_dir.mkdir(exist_ok=True)
    with torch.no_grad():
        for d in wdata.trajectories(data):
            rgb = torch.from_numpy(wdata.to_unit_range(np.load(d / "rgb.npy")))
            z = torch.cat([ae.encoder(c) for c in rgb.split(encode_chunk(cfg))]) * ae.scale
            np.save(latent_dir / f"{d.name}.npy", z.numpy().astype(np.float16))



def write_autoencoder(ae, data: Path, out: Path, half: bool) -> None:
    """The encoder and decoder graphs and their references."""
    ref = out / "reference"
    rgb_ref = np.stack([np.load(wdata.trajectories(data)[0] / "rgb.npy")[k] for k in (0, 7)])
    image = torch.from_numpy(wdata.to_unit_range(rgb_ref))
    with torch.no_grad():
        raw = ae.encoder(image)
        decoded = ae.decoder(raw)
    protos = {
        "encoder": to_onnx(ae.encoder, (image,), ["image"], ["latent"]),
        "decoder": to_onnx(ae.decoder, (raw,), ["latent"], ["image"]),
    }
    for name in ("encoder", "decoder"):
        if half:
            store_half(protos[name])
        onnx.save(protos[name], out / f"{name}.onnx")
    save_arrays(ref / "encoder", {"image": image.numpy(), "latent": raw.numpy()})
    save_arrays(ref / "decoder", {"latent": raw.numpy(), "image": decoded.numpy()})



def write_denoisers(cfg: ModelConfig, ae, model: CDiT, layout_names: list[str], data: Path, latent_dir: Path, out: Path,
                    half: bool, rng: np.random.Generator) -> tuple[list[dict], tuple]:
    """One denoiser graph per layout, from the same weights, with references; the layouts'
    manifest entries and the inputs of the first, which the sampling traces condition on."""
    ref = out / "reference"
    denoisers, layouts_json, trace_inputs = {}, [], None
    for name in layout_names:
        layout = LAYOUTS[name]
        missing = set(layout.rates) - set(cfg.cdit.rates)
        if missing:
            raise SystemExit(f"--layouts {name}: the model has no projection for rates {sorted(missing)}")
        source = wdata.PlannedLatents(data, latent_dir, name, layout, warp=cfg.cdit.warp)
        rows = reference_rows(source, REFERENCE_BATCH)
        batch = source.gather(rows)
        noise = rng.standard_normal(batch.target.shape).astype(np.float32)
        t = np.array([250.0, 750.0][:REFERENCE_BATCH], np.float32)
        ab = Schedule(cfg.diffusion).alphas_cumprod[t.astype(int)].astype(np.float32)[:, None, None, None]
        x_t = np.sqrt(ab) * batch.target + np.sqrt(1 - ab) * noise
        arrays = {"x_t": x_t, "timestep": t, "action": batch.action, "rel_time": batch.rel_time}
        for r, g in zip(layout.rates, batch.groups):
            if cfg.cdit.context_noise:  # non-zero levels, so the references pin the input's effect
                g = (*g, (rng.uniform(0, 0.3, g[3].shape) * g[3]).astype(np.float32))
            for key, arr in zip(context_keys(cfg), g):
                arrays[f"{key}_r{r}"] = arr
        if cfg.cdit.warp:
            arrays["warp"] = batch_warp(source, batch, ae, torch.device("cpu")).numpy()
        names = input_names(cfg, layout)
        args = tuple(torch.from_numpy(arrays[n]) for n in names)
        graph = LayoutGraph(model, layout)
        with torch.no_grad():
            eps = graph(*args)
        denoisers[name] = to_onnx(graph, args, names, ["eps"])
        save_arrays(ref / f"denoiser_{name}", {**arrays, "eps": eps.numpy()})
        # What produced the context inputs, so a runtime can check its own packing.
        plan_rows = []
        for i, t in rows:
            ids = [int(x) for x in source.plans[i][t]]
            plan_rows.append({"target_time": t, "target_c2w": source.poses[i][t].tolist(),
                              "slots": [{"rate": r, "frame": f if f >= 0 else None,
                                         "c2w": source.poses[i][f].tolist() if f >= 0 else None}
                                        for r, f in zip([r for r, n in zip(layout.rates, layout.counts) for _ in range(n)], ids)]})
        (ref / f"denoiser_{name}" / "plan.json").write_text(json.dumps({"rows": plan_rows}, indent=1))
        ins, outs = denoiser_io(cfg, layout)
        layouts_json.append({
            "name": name,
            "file": f"denoiser_{name}.onnx",
            "slots": [{"rate": r, "count": n, "tokens_per_frame": tokens_per_frame(cfg.cdit.latent_size, cfg.cdit.patch, r)}
                      for r, n in zip(layout.rates, layout.counts)],
            "frames": layout.frames,
            "context_tokens": sum(n * tokens_per_frame(cfg.cdit.latent_size, cfg.cdit.patch, r) for r, n in zip(layout.rates, layout.counts)),
            "inputs": ins,
            "outputs": outs,
        })
        if trace_inputs is None:
            trace_inputs = (name, graph, names, arrays)
    if half:
        for proto in denoisers.values():
            store_half(proto)
    share_weights(denoisers, out / "denoiser.weights")
    for name, proto in denoisers.items():
        onnx.save(proto, out / f"denoiser_{name}.onnx")

    return layouts_json, trace_inputs


def write_traces(sched: Schedule, trace_inputs: tuple, grid: list[int] | None, ref: Path, rng: np.random.Generator) -> dict:
    """Sampling traces: the reference sampler with injected noise, PyTorch as the denoiser."""
    trace_layout, graph, names, arrays = trace_inputs

    def eps_fn(x, t):
        feed = {**arrays, "x_t": x, "timestep": t}
        with torch.no_grad():
            return graph(*(torch.from_numpy(feed[n]) for n in names)).numpy()

    # A distilled model is sampled on its own grid with DDIM only.
    traces = {}
    for method in ("ddim",) if grid else ("ancestral", "ddim"):
        steps = len(grid) if grid else TRACE_STEPS
        x_T = rng.standard_normal(arrays["x_t"].shape).astype(np.float32)
        noise = rng.standard_normal((steps, *x_T.shape)).astype(np.float32)
        tr = sample(eps_fn, sched, x_T, steps, method, eta=0.0, noise=noise, timesteps=grid)
        save_arrays(ref / f"trace_{method}", {"timesteps": tr.timesteps, "x": tr.x, "eps": tr.eps, "noise": tr.noise})
        traces[method] = {"folder": f"reference/trace_{method}", "layout": trace_layout, "steps": steps,
                          "eta": 0.0, "conditioning": f"reference/denoiser_{trace_layout} (all inputs but x_t and timestep)"}

    return traces


def manifest_of(cfg: ModelConfig, ae, model: CDiT, data: Path, name: str, created_by: str, half: bool, layouts_json: list[dict],
                generated_level: float, distilled: dict | None, training: dict | None, measured: dict | None,
                tolerance: dict, layout_names: list[str], traces: dict) -> dict:
    a = cfg.autoencoder
    meta0 = json.loads((wdata.trajectories(data)[0] / "meta.json").read_text())
    return {
        "format": MANIFEST_FORMAT,
        "name": name,
        "created_by": created_by,
        "config": cfg.to_json(),
        "image": {"width": a.image_size, "height": a.image_size, "channels": 3, "layout": "NCHW, RGB",
                  "range": [-1.0, 1.0], "from_u8": "x / 127.5 - 1"},
        "intrinsics": meta0["intrinsics"],
        "autoencoder": {
            "encoder": {"file": "encoder.onnx",
                        "inputs": [tensor_spec("image", ["batch", 3, a.image_size, a.image_size], "float32", "RGB in [-1, 1]")],
                        "outputs": [tensor_spec("latent", ["batch", a.latent_channels, a.latent_size, a.latent_size], "float32", "raw latent (not scaled)")]},
            "decoder": {"file": "decoder.onnx",
                        "inputs": [tensor_spec("latent", ["batch", a.latent_channels, a.latent_size, a.latent_size], "float32", "raw latent (divide the model's latent by latent_scale first)")],
                        "outputs": [tensor_spec("image", ["batch", 3, a.image_size, a.image_size], "float32", "RGB, nominally [-1, 1]; clamp before converting")]},
            "latent": {"channels": a.latent_channels, "height": a.latent_size, "width": a.latent_size, "downsample": a.downsample},
            "latent_scale": float(ae.scale.item()),
        },
        "denoiser": {
            "architecture": "CDiT (NWM): adaLN-Zero blocks of self-attention over target tokens, cross-attention to context tokens, MLP",
            "patch": cfg.cdit.patch, "hidden": cfg.cdit.hidden, "depth": cfg.cdit.depth, "heads": cfg.cdit.heads,
            "parameters": sum(p.numel() for p in model.parameters()),
            "target_tokens": cfg.cdit.grid ** 2,
            "rates": list(cfg.cdit.rates),
            "weights": "denoiser.weights",
            "weights_storage": "float16 (parameters rounded to float16 before export; computed in float32)" if half else "float32",
            "layouts": layouts_json,
            **({"warp": {"input": "warp", "channels": cfg.cdit.latent_channels + 1,
                         "frames": wdata.PlannedLatents.WARP_FRAMES,
                         "source": "the `frames` observed stored frames with depth that overlap the target view most, best first, "
                                   "behind one z-buffer (ties to the earlier frame)",
                         "warp": "each source pixel splatted to the target pixel floor(x + 0.5) behind a z-buffer, ties to the earlier "
                                 "pixel; depth 0 is a direction at infinity (rotation only); holes 0 in the [-1, 1] image",
                         "latent": "encoder(image * mask) * latent_scale, then the mask average-pooled by the autoencoder's downsample",
                         "without_source": "all zeros (no frame with depth)",
                         "reference": "reference/warp"}}
               if cfg.cdit.warp else {}),
            **({"context_noise": {"observed_level": 0.0, "generated_level": generated_level,
                                  "meaning": "the level the runtime puts in context_noise_r<rate> for observed and for generated frames"}}
               if cfg.cdit.context_noise else {}),
        },
        "action": {"dim": cfg.cdit.action_dim, "names": ACTION_NAMES[: cfg.cdit.action_dim],
                   "scale_inside_graph": ACTION_SCALE[: cfg.cdit.action_dim],
                   "meaning": "the synthetic world's action (docs/world.md): 0/1 keys, then yaw and pitch change in degrees"},
        "pose_embedding": {"kind": "relative_pose_3x4", "frame": "opencv (x right, y down, z forward)",
                           "definition": "inv(T_target) @ T_context with T camera-to-world; rows [R | t] flattened row-major",
                           "translation_unit": "world units (blocks)",
                           "translation_scale_inside_graph": 1.0 / cfg.cdit.pose_translation_scale},
        "time": {"rope": "real cos/sin over the key's time offset, on the two halves of each head; queries at 0",
                 "rope_base": cfg.cdit.rope_base, "unit": "frames"},
        "diffusion": {"timesteps": cfg.diffusion.timesteps, "schedule": "linear", "beta_start": cfg.diffusion.beta_start,
                      "beta_end": cfg.diffusion.beta_end, "prediction": "epsilon",
                      "ancestral_variance": "posterior beta_tilde = beta_k (1 - abar_{k-1}) / (1 - abar_k), no noise on the last step",
                      "respacing": "kept = unique(round(linspace(0, T-1, steps))); betas recomputed from the kept abar; the model gets the original index",
                      "ddim": "x_{k-1} = sqrt(abar_{k-1}) x0 + sqrt(1 - abar_{k-1} - sigma^2) eps + sigma z, sigma = eta sqrt((1-abar_{k-1})/(1-abar_k) (1 - abar_k/abar_{k-1}))",
                      "precision": "coefficients in float64, state in float32",
                      **({"distilled": {**distilled, "sampler": "ddim, eta 0, on exactly these timesteps (the last step lands on the clean frame)"}}
                         if distilled else {})},
        **({"training": training} if training is not None else {}),
        **({"metrics": measured} if measured is not None else {}),
        "reference": {
            "tolerance": tolerance,
            "graphs": {"encoder": "reference/encoder", "decoder": "reference/decoder",
                       **{f"denoiser_{n}": f"reference/denoiser_{n}" for n in layout_names}},
            "traces": traces,
        },
    }


def encode_chunk(cfg: ModelConfig) -> int:
    """Images per encoder call: 256 at 64x64, fewer for larger frames, so memory stays near 1 GB."""
    return max(1, 256 * 64 * 64 // cfg.autoencoder.image_size ** 2)


@torch.no_grad()
def measure(cfg: ModelConfig, ae, model: CDiT, data: Path, latent_dir: Path, layout_names: list[str], sched: Schedule,
            grid: list[int] | None = None) -> dict:
    """Held-out figures for the manifest: autoencoder PSNR, denoising loss, and
    next-frame PSNR with a short sampler against copying the last frame."""
    out = {"suite": str(data), "autoencoder_psnr_db": round(evaluate_autoencoder(ae, data, torch.device("cpu")), 2)}
    rng = np.random.default_rng(3)
    for name in layout_names:
        layout = LAYOUTS[name]
        source = wdata.PlannedLatents(data, latent_dir, name, layout, warp=cfg.cdit.warp)
        batch = source.batch(rng, 64)
        groups = [tuple(torch.from_numpy(x) for x in g) for g in batch.groups]
        if cfg.cdit.context_noise:  # every context frame observed
            groups = [(*g, torch.zeros_like(g[3])) for g in groups]
        warp = batch_warp(source, batch, ae, torch.device("cpu")) if cfg.cdit.warp else None
        x0 = torch.from_numpy(batch.target)
        act, rel = torch.from_numpy(batch.action), torch.from_numpy(batch.rel_time)
        t = torch.from_numpy(rng.integers(0, cfg.diffusion.timesteps, 64)).float()
        ab = torch.tensor(sched.alphas_cumprod, dtype=torch.float32)[t.long()].view(-1, 1, 1, 1)
        noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(0))
        eps = model(ab.sqrt() * x0 + (1 - ab).sqrt() * noise, t, act, rel, groups, rates=layout.rates, warp=warp)
        entry = {"eps_mse": round(float(((eps - noise) ** 2).mean()), 4)}
        n = 16
        sub = [tuple(x[:n] for x in g) for g in groups]
        w = warp[:n] if warp is not None else None
        fn = lambda x, tt: model(torch.from_numpy(x), torch.from_numpy(tt), act[:n], rel[:n], sub, rates=layout.rates, warp=w).numpy()
        if grid:  # a distilled model: DDIM on its own grid
            tr = sample(fn, sched, rng.standard_normal(x0[:n].shape).astype(np.float32), len(grid), "ddim", rng=rng, timesteps=grid)
        else:
            tr = sample(fn, sched, rng.standard_normal(x0[:n].shape).astype(np.float32), 20, "ancestral", rng=rng)
        pred = ae.decoder(torch.from_numpy(tr.x[-1]) / ae.scale)
        truth = ae.decoder(x0[:n] / ae.scale)
        # The most recent present context frame, decoded: what "copy the last frame" would predict.
        last = []
        for i in range(n):
            best, best_t = None, -1e9
            for g in batch.groups:
                for s in range(g[0].shape[1]):
                    if g[3][i, s] > 0 and g[1][i, s] > best_t:
                        best, best_t = g[0][i, s], g[1][i, s]
            last.append(best)
        copy = ae.decoder(torch.from_numpy(np.stack(last)) / ae.scale)
        entry[f"next_frame_psnr_db_{len(grid)}_steps" if grid else "next_frame_psnr_db_20_steps"] = round(psnr(to_u8(pred), to_u8(truth)), 2)
        entry["copy_last_frame_psnr_db"] = round(psnr(to_u8(copy), to_u8(truth)), 2)
        out[name] = entry
    return out


WARP_GAPS = (1, 4, 12, 40)  # source frames this far before the target: from near-identical to mostly holes


@torch.no_grad()
def warp_cases(suites: tuple[Path, ...], ae) -> dict[str, np.ndarray]:
    """Reference cases for the Rust warp (`model::warp`): source frames with
    depth, both poses, and what `warp.forward_warp` and `warp.warp_input` made.
    One case per gap, the first target from mid-trajectory on whose warp
    covers at least a fifth of the view (a case with nothing warped checks little), from
    the first trajectory that has one for every gap."""
    for d in (d for suite in suites for d in wdata.trajectories(suite)):
        rgb, depth, poses = np.load(d / "rgb.npy"), np.load(d / "depth.npy"), np.load(d / "poses.npy")
        intrinsics = json.loads((d / "meta.json").read_text())["intrinsics"]
        warp = lambda s, t: forward_warp(torch.from_numpy(rgb[s]), torch.from_numpy(depth[s].astype(np.int32)), intrinsics,
                                         torch.from_numpy(poses[s]), torch.from_numpy(poses[t]))
        src, dst = [], []
        for gap in WARP_GAPS:
            targets = np.arange(max(gap, len(rgb) // 2), len(rgb))
            _, mask = warp(targets - gap, targets)
            covered = targets[mask.float().mean(dim=(1, 2)).numpy() >= 0.2]
            if len(covered) == 0:
                break
            src.append(covered[0] - gap)
            dst.append(covered[0])
        if len(src) == len(WARP_GAPS):
            break
    else:
        raise SystemExit(f"export: no trajectory of {', '.join(map(str, suites))} has, for every gap in {WARP_GAPS}, a warp from that many "
                         "frames back covering a fifth of the view (the warp's reference cases)")
    src, dst = np.array(src), np.array(dst)
    warped, mask = warp(src, dst)
    inp = warp_input(ae.encoder, ae.scale, warped, mask, ae.cfg.downsample)
    # One fused case: every gap's source into the first gap's target, behind one z-buffer.
    fsrc = (dst[0] - np.array(WARP_GAPS)).clip(0)
    fused, fmask = forward_warp(torch.from_numpy(rgb[fsrc][None]), torch.from_numpy(depth[fsrc][None].astype(np.int32)), intrinsics,
                                torch.from_numpy(poses[fsrc][None]), torch.from_numpy(poses[dst[:1]]))
    return {"rgb": rgb[src], "depth_mm": depth[src], "src_c2w": poses[src], "dst_c2w": poses[dst],
            "warped": warped.numpy(), "mask": mask.numpy().astype(np.uint8), "input": inp.numpy().astype(np.float32),
            "fused_rgb": rgb[fsrc], "fused_depth_mm": depth[fsrc], "fused_src_c2w": poses[fsrc], "fused_dst_c2w": poses[dst[0]],
            "fused_warped": fused.numpy()[0], "fused_mask": fmask.numpy()[0].astype(np.uint8)}
