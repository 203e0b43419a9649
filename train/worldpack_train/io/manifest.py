"""Checks a model folder's `manifest.json` without torch: the fields the Rust
runtime relies on, and that shapes and token counts agree with each other.
Errors name the field, e.g. `denoiser.layouts[0].slots[2].tokens_per_frame`."""

from __future__ import annotations

import json
import math
from pathlib import Path
import sys

from ..core.data import PlannedLatents

FORMAT = "worldpack-model/1"


def slot_tokens(height: int, width: int, patch: int, rate: int) -> int | None:
    side = math.isqrt(rate)
    if side * side != rate:
        return None
    k = patch * side
    return -(-height // k) * -(-width // k)


def validate(m: dict) -> list[str]:
    errors: list[str] = []

    def get(path: str, kind=None):
        node = m
        for part in path.split("."):
            if not isinstance(node, dict) or part not in node:
                errors.append(f"{path}: missing")
                return None
            node = node[part]
        if kind is not None and not isinstance(node, kind) or isinstance(node, bool) and kind in (int, float, (int, float)):
            errors.append(f"{path}: expected {getattr(kind, '__name__', kind)}, got {node!r}")
            return None
        return node

    if get("format") != FORMAT:
        errors.append(f"format: expected {FORMAT!r}")
    w, h = get("image.width", int), get("image.height", int)
    c, lh, lw = get("autoencoder.latent.channels", int), get("autoencoder.latent.height", int), get("autoencoder.latent.width", int)
    scale = get("autoencoder.latent_scale", (int, float))
    if scale is not None and not scale > 0:
        errors.append(f"autoencoder.latent_scale: must be > 0, got {scale}")
    for part, key, want in (("encoder", "outputs", [c, lh, lw]), ("decoder", "inputs", [c, lh, lw]),
                            ("encoder", "inputs", [3, h, w]), ("decoder", "outputs", [3, h, w])):
        specs = get(f"autoencoder.{part}.{key}", list)
        if specs and None not in want and specs[0].get("shape", [None])[1:] != want:
            errors.append(f"autoencoder.{part}.{key}[0].shape: expected [batch, {', '.join(map(str, want))}], got {specs[0].get('shape')}")
    get("autoencoder.encoder.file", str)
    get("autoencoder.decoder.file", str)
    patch, rates = get("denoiser.patch", int), get("denoiser.rates", list)
    layouts = get("denoiser.layouts", list) or []
    if not layouts:
        errors.append("denoiser.layouts: at least one layout is needed")
    for i, lay in enumerate(layouts):
        at = f"denoiser.layouts[{i}]"
        if not isinstance(lay.get("file"), str):
            errors.append(f"{at}.file: missing")
        total = 0
        names = {s.get("name") for s in lay.get("inputs", [])}
        for need in ("x_t", "timestep", "action", "rel_time"):
            if need not in names:
                errors.append(f"{at}.inputs: no {need!r}")
        for j, slot in enumerate(lay.get("slots", [])):
            r, n = slot.get("rate"), slot.get("count")
            if rates is not None and r not in rates:
                errors.append(f"{at}.slots[{j}].rate: {r} is not one of denoiser.rates {rates}")
                continue
            want = slot_tokens(lh or 0, lw or 0, patch or 1, r) if isinstance(r, int) else None
            if want is None:
                errors.append(f"{at}.slots[{j}].rate: {r!r} must be a square whole number (1, 4, 16, ...)")
                continue
            if slot.get("tokens_per_frame") != want:
                errors.append(f"{at}.slots[{j}].tokens_per_frame: expected {want}, got {slot.get('tokens_per_frame')}")
            if not isinstance(n, int) or n < 1:
                errors.append(f"{at}.slots[{j}].count: expected a whole number >= 1, got {n!r}")
                continue
            total += n * want
            for key in (f"context_r{r}", f"context_time_r{r}", f"context_pose_r{r}", f"context_mask_r{r}"):
                if key not in names:
                    errors.append(f"{at}.inputs: no {key!r}")
        if lay.get("context_tokens") != total:
            errors.append(f"{at}.context_tokens: expected {total}, got {lay.get('context_tokens')}")
    steps = get("diffusion.timesteps", int)
    b0, b1 = get("diffusion.beta_start", (int, float)), get("diffusion.beta_end", (int, float))
    if steps is not None and steps < 1:
        errors.append("diffusion.timesteps: must be >= 1")
    if b0 is not None and b1 is not None and not 0 < b0 < b1 < 1:
        errors.append(f"diffusion.beta_start/beta_end: need 0 < start < end < 1, got {b0}, {b1}")
    if get("diffusion.prediction") not in (None, "epsilon"):
        errors.append("diffusion.prediction: only 'epsilon' is supported")
    get("action.dim", int)
    return errors


def set_warp_frames(model: Path, frames: int) -> None:
    """Sets, in place, how many best-overlap observed frames the runtime warps
    behind one z-buffer into `model`'s warp input (`denoiser.warp.frames`).
    Training drew 1 to `PlannedLatents.WARP_FRAMES` of them per target; the
    denoiser and the head see one fused image and where it landed, so more
    frames land more of memory's own pixels and leave fewer holes. The
    manifest keeps the training count beside the served one."""

    path = model / "manifest.json"
    if not path.is_file():
        raise SystemExit(f"--model: {model} has no manifest.json")
    manifest = json.loads(path.read_text())
    warp = manifest.get("denoiser", {}).get("warp")
    if warp is None:
        raise SystemExit(f"--model: {model} has no warp input (not a geometry model)")
    if frames < 1:
        raise SystemExit(f"--frames: at least 1, got {frames}")
    warp.setdefault("trained_frames", f"1 to {PlannedLatents.WARP_FRAMES}")
    warp["frames"] = frames
    path.write_text(json.dumps(manifest, indent=1))
    print(f"{model}: fuses the {frames} best-overlap observed frames (trained on {warp['trained_frames']})")


def main() -> None:
    for arg in sys.argv[1:]:
        path = Path(arg)
        path = path / "manifest.json" if path.is_dir() else path
        errors = validate(json.loads(path.read_text()))
        print(f"{path}: " + ("ok" if not errors else "\n  " + "\n  ".join(errors)))


if __name__ == "__main__":
    main()
