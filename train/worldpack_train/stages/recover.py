"""Checkpoints back from an exported model folder.

Run folders are not committed, but the exported models are: this reads a
model folder's ONNX graphs and rebuilds the PyTorch checkpoints a run folder
holds (`config.json`, `autoencoder.pt`, `cdit-<policy>.pt`), so a committed
model can be fine-tuned or continued on any machine. Every parameter must be
found, and the rebuilt model must reproduce the folder's reference outputs,
or nothing is written.

Parameters are found by name. The exporter folds most linear weights into
anonymous transposed constants; those are traced from their bias: the `Add`
that consumes `<module>.bias` takes a `MatMul` whose weight input is the
transposed weight."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..core.autoencoder import Autoencoder
from ..core.autoencoder import build as build_autoencoder
from ..core.cdit import CDiT
from ..core.config import ModelConfig
from ..core.diffusion import Schedule
from ..core.student import EpsFromV
from ..io.checkpoints import save
from ..io.graphs import Graph, load_state
from ..io.onnx_files import context_keys


def reference(folder: Path, name: str) -> dict[str, np.ndarray]:
    return {p.stem: np.load(p) for p in (folder / name).glob("*.npy")}


@torch.no_grad()
def check_against_references(model_dir: Path, manifest: dict, cfg: ModelConfig, ae: Autoencoder, cdit: torch.nn.Module) -> float:
    """Largest absolute difference between the rebuilt modules and the
    folder's reference outputs."""
    ref = model_dir / "reference"
    worst = 0.0
    enc = reference(ref, "encoder")
    worst = max(worst, float(np.abs(ae.encoder(torch.from_numpy(enc["image"])).numpy() - enc["latent"]).max()))
    dec = reference(ref, "decoder")
    worst = max(worst, float(np.abs(ae.decoder(torch.from_numpy(dec["latent"])).numpy() - dec["image"]).max()))
    for layout in manifest["denoiser"]["layouts"]:
        r = reference(ref, f"denoiser_{layout['name']}")
        rates = [s["rate"] for s in layout["slots"]]
        t = lambda k: torch.from_numpy(r[k])
        groups = [tuple(t(f"{k}_r{rate}") for k in context_keys(cfg)) for rate in rates]
        warp = t("warp") if cfg.cdit.warp else None
        eps = cdit(t("x_t"), t("timestep"), t("action"), t("rel_time"), groups, rates=tuple(rates), warp=warp).numpy()
        worst = max(worst, float(np.abs(eps - r["eps"]).max()))
    return worst


def recover(model_dir: Path, run: Path, policy: str | None) -> None:
    manifest = json.loads((model_dir / "manifest.json").read_text())
    cfg = ModelConfig.from_json(manifest["config"])
    trained = manifest.get("training", {})
    distilled = manifest["diffusion"].get("distilled")
    policy = policy or trained.get("policy") or manifest["denoiser"]["layouts"][0]["name"]
    run.mkdir(parents=True, exist_ok=True)
    # Compared as JSON: the config's tuples come back from the file as lists.
    if (run / "config.json").exists() and json.loads((run / "config.json").read_text()) != json.loads(json.dumps(cfg.to_json())):
        raise SystemExit(f"--run: {run}/config.json differs from {model_dir}'s config; use an empty run folder")
    if distilled is not None and not (run / f"cdit-{policy}.pt").exists():
        raise SystemExit(f"--model: {model_dir} is a distilled student; recover its teacher into {run} first "
                         f"(its manifest names {distilled.get('teacher')})")
    ae = build_autoencoder(cfg.autoencoder).eval()
    load_state(ae.encoder, [Graph(model_dir / manifest["autoencoder"]["encoder"]["file"])], "")
    load_state(ae.decoder, [Graph(model_dir / manifest["autoencoder"]["decoder"]["file"])], "")
    ae.scale.fill_(float(manifest["autoencoder"]["latent_scale"]))
    cdit = CDiT(cfg.cdit).eval()
    # A student's graph holds its v-predicting CDiT inside `EpsFromV` (distill.py).
    prefix = "model.model." if distilled is not None else "model."
    # A baseline's graph has no rate projections: re-derived from the base patchify, as a fine-tune starts.
    absent = load_state(cdit, [Graph(model_dir / layout["file"]) for layout in manifest["denoiser"]["layouts"]], prefix,
                        unused=("rate_proj.",))
    if absent:
        cdit.init_rate_projections_from_base()
        print(f"not in any exported layout, derived from the base patchify: {absent}")
    exported = cdit
    if distilled is not None:

        exported = EpsFromV(cdit, Schedule(cfg.diffusion).alphas_cumprod)
    worst = check_against_references(model_dir, manifest, cfg, ae, exported)
    if worst > 1e-3:
        raise SystemExit(f"--model: the rebuilt model differs from {model_dir}/reference by {worst:.2e}; nothing written")
    (run / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))
    steps = int(trained.get("steps") or 0)
    weights = cdit.state_dict()
    common = dict(model=weights, ema=weights, step=steps, policy=policy, memory_focus=float(trained.get("memory_focus") or 0.0),
                  init_from=trained.get("init_from"), recipe=trained.get("recipe", {}), recovered_from=str(model_dir))
    if distilled is not None:
        # The student continues with `distill` (same --grid): its weights, not its optimiser's moments.
        name = f"distilled-{policy}-{len(distilled['timesteps'])}.pt"
        record = {k: v for k, v in distilled.items() if k != "sampler"}
        save(run / name, distilled=record, plans_query=trained.get("plans_query", "target"), **common)
        print(f"recovered the student {model_dir} into {run}/{name} (step {steps}); "
              f"largest difference from the references {worst:.1e}")
        return
    save(run / "autoencoder.pt", model=ae.state_dict(), step=int(trained.get("autoencoder_steps") or 0), recovered_from=str(model_dir))
    save(run / f"cdit-{policy}.pt", **common)
    print(f"recovered {model_dir} into {run}: autoencoder.pt, cdit-{policy}.pt (step {steps}); "
          f"largest difference from the references {worst:.1e}")
