"""Run folders: their config, checkpoints, logs and the autoencoder in them."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ..core.autoencoder import Autoencoder
from ..core.autoencoder import build as build_autoencoder
from ..core.config import ModelConfig


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: this torch sees no CUDA device (use --device cpu or auto)")
    return torch.device(name)


def run_config(run: Path) -> ModelConfig:
    path = run / "config.json"
    if path.exists():
        return ModelConfig.from_json(json.loads(path.read_text()))
    cfg = ModelConfig()
    run.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cfg.to_json(), indent=2))
    return cfg


def log(run: Path, record: dict) -> None:
    with open(run / "log.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


def save(path: Path, **state) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)  # a crash mid-save never leaves a torn checkpoint


def load_optimiser(opt: torch.optim.Optimizer, state: dict, ckpt: Path, key: str = "opt") -> None:
    """Restores `opt`'s moments from checkpoint `ckpt`'s `state[key]`, keeping the
    learning rates `opt` was built with: a resumed run takes the `--lr` it is
    given, not the one it was saved with. A checkpoint recovered from an export
    has no moments (the weights survive, the optimiser does not): it says so."""
    if key not in state:
        print(f"{ckpt.name} has no optimiser state (recovered from an export): AdamW starts afresh")
        return
    asked = [g["lr"] for g in opt.param_groups]
    opt.load_state_dict(state[key])
    for group, lr in zip(opt.param_groups, asked):
        group["lr"] = lr


def resume(ckpt: Path, model: torch.nn.Module, opt: torch.optim.Optimizer, what: str, device="cpu", key: str = "model") -> int:
    """Loads `model` (saved under `key`) and its optimiser from `ckpt` when
    it exists; returns the step it was saved at (0 without a checkpoint)."""
    if not ckpt.exists():
        return 0
    state = torch.load(ckpt, map_location=device, weights_only=False)
    model.load_state_dict(state[key])
    load_optimiser(opt, state, ckpt)
    print(f"resuming {what} at step {state['step']}")
    return state["step"]


def load_autoencoder(run: Path, dev: torch.device) -> Autoencoder:
    cfg = run_config(run)
    ckpt = run / "autoencoder.pt"
    if not ckpt.exists():
        raise SystemExit(f"--run: no autoencoder.pt in {run}; run `train-ae` first")
    ae = build_autoencoder(cfg.autoencoder).to(dev)
    ae.load_state_dict(torch.load(ckpt, map_location=dev)["model"])
    return ae.eval()


def checkpoint_step(path: Path) -> int:
    return int(torch.load(path, map_location="cpu")["step"]) if path.exists() else 0
