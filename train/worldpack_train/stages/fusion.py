"""The fusion head of a geometry model: a small convolutional net in pixel
space that takes the decoded frame, the fused reference of the model's warp
sources (the stored frames warped into the target view, best first, a later
one taking a pixel only when clearly nearer; cracks filled, what is still
empty the best frame's own pixel: `model::warp::fused_reference`, made by
`worldpack fusion-data`) and where the warp landed, and returns the frame the
model shows.

It learns, per pixel, how far to trust the warp against the model: the warp
is exact where it landed on the right surface, the decoder is blurred by the
autoencoder, and in the warp's holes neither is right alone. The output is a
convex blend of the two plus a small correction, so the head cannot drift
far from both.

    worldpack fusion-data --suite data/train120 --model M --out runs/fusion/train
    ./scripts/model.sh fusion-train --data runs/fusion/train --run runs/fusion
    ./scripts/model.sh fusion-export --run runs/fusion --model M --out M_fused

`fusion-export` writes a copy of the model with `fusion.onnx` added and the
manifest's `fusion` entry; the Rust runtime runs the head after the decoder
in `Model::predict` (model/src/predict.rs). `fusion-pair` joins two exported
heads into one graph (`HeadPair`): one makes the frame shown, the other the
frame the memory keeps.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
import shutil
import tempfile
import time

import numpy as np
import onnx
from onnx import numpy_helper
import torch
from torch import nn
import torch.nn.functional as F

from ..core.losses import (LUMA, PatchDiscriminator, adaptive_weight, detail_energy_difference, gradient_difference,
                           hinge_discriminator)
from ..io.checkpoints import resume
from ..io.onnx_files import to_onnx
from ..metrics import psnr, sharpness_ratio, to_u8

INPUTS = ("predicted", "reference", "landed")  # the order model/src/manifest.rs expects
CORRECTION = 0.25  # the largest per-channel correction beyond the blend, in [-1, 1] units


class FusionHead(nn.Module):
    def __init__(self, width: int = 24, dilations: tuple[int, ...] = (1, 2, 4, 8)):
        super().__init__()
        self.width, self.dilations = width, dilations
        layers, c = [], 10  # predicted, reference, landed, predicted - reference
        for d in dilations:
            layers += [nn.Conv2d(c, width, 3, padding=d, dilation=d), nn.ReLU()]
            c = width
        self.body = nn.Sequential(*layers)
        self.out = nn.Conv2d(width, 4, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)  # starts as the plain average of the two

    def forward(self, predicted, reference, landed):
        x = torch.cat([predicted, reference, landed, predicted - reference], dim=1)
        o = self.out(self.body(x))
        w = torch.sigmoid(o[:, :1])
        return w * reference + (1 - w) * predicted + CORRECTION * torch.tanh(o[:, 1:])


class HeadPair(nn.Module):
    """Two trained heads on the same inputs: `shown` makes the frame the
    model shows, `kept` the frame the memory keeps (the runtime re-encodes
    it as the context of the frames after it; model/src/predict.rs). A frame
    shown is judged on its own, one kept by the frames conditioned on it, and
    different losses win each: MSE for the one, MSE with the gradient
    difference term, which keeps edges, for the other. `hole_fill` K > 0:
    the kept frame's holes next to where the warp landed take the warp's
    colours (`fill_holes_from_warp`). `hole_detail` K > 0: the frame shown
    takes the decoded frame's detail in the warp's holes
    (`detail_in_holes`). `warp_detail` T > 0: where the warp landed and
    agrees with the frame shown to within about T 8-bit levels, the frame
    shown takes the warp's luma detail (`warp_detail_where_agreed`).
    `holes`, a third head (one trained for detail where no stored frame has
    the pixels, `train`'s `texture_weight`): in the warp's holes the frame
    shown takes its luma detail (`luma_detail_in_holes`)."""

    def __init__(self, shown: FusionHead, kept: FusionHead, hole_fill: int = 0, hole_detail: int = 0,
                 warp_detail: float = 0.0, holes: FusionHead | None = None):
        super().__init__()
        self.shown, self.kept, self.hole_fill, self.hole_detail = shown, kept, hole_fill, hole_detail
        self.warp_detail, self.holes = warp_detail, holes

    def forward(self, predicted, reference, landed):
        head = self.kept(predicted, reference, landed)
        kept = fill_holes_from_warp(head, reference, landed, self.hole_fill) if self.hole_fill else head
        # One head for both frames (the same module twice) runs once.
        shown = head if self.shown is self.kept else self.shown(predicted, reference, landed)
        if self.hole_detail:
            shown = detail_in_holes(shown, predicted, landed, self.hole_detail)
        if self.holes is not None:
            shown = luma_detail_in_holes(shown, self.holes(predicted, reference, landed), landed)
        if self.warp_detail:
            shown = warp_detail_where_agreed(shown, reference, landed, self.warp_detail)
        return shown, kept


def local_mean(x, k: int):
    """The k x k mean around each pixel of NCHW `x`, over the pixels inside the frame."""
    return F.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)


def fill_holes_from_warp(frame, reference, landed, k: int):
    """`frame` with, in the warp's holes that lie within k // 2 pixels of
    where it landed, its k x k local mean replaced by the warp's own colours
    diffused into the hole (a normalised convolution), its detail kept.

    A head fills a hole with what its training frames had there on average;
    in a world unlike that average (a bright ground near the camera) the
    kept frame comes out darker, and every later frame conditioned on it
    inherits the smear (docs/benchmarks.md, world 3). The nearest landed
    pixels carry this world's colours instead."""
    pool = lambda x: local_mean(x, k)
    near = pool(landed)
    diffused = pool(reference * landed) / (near + 1e-3)
    reach = (near > 1e-3).float()
    return frame + (diffused - pool(frame)) * (1 - landed) * reach


def detail_in_holes(frame, predicted, landed, k: int):
    """`frame` whose detail (what its k x k local mean leaves) in the warp's
    holes is the decoded frame's instead, its local mean kept: detail
    transfer between a base and a detail layer (Petschnigg et al. 2004,
    Eisemann & Durand 2004).

    Where the warp has no pixels a head trained for MSE paints the mean of
    what could be there, and the decoded frame, the student's sample, has
    the edges. The head's local mean keeps the colours MSE gets right; the
    decoded frame's detail is what a frame there looks like."""
    pool = lambda x: local_mean(x, k)
    return frame + ((predicted - pool(predicted)) - (frame - pool(frame))) * (1 - landed)


def luma_detail_in_holes(frame, painted, landed):
    """`frame` whose luma detail (beyond its 3x3 local mean) in the warp's
    holes is `painted`'s, its colours and local mean kept.

    `painted` comes from a head trained to put detail as strong as the
    truth's where no stored frame has the pixels; its colours there are
    less sure than its edges (a luma-only detail term leaves them free), so
    only its luma detail is taken, as the warp's is where it agrees."""
    return frame + (luma_detail(painted) - luma_detail(frame)) * (1 - landed)


def luma_detail(x):
    """What the 3x3 local mean leaves of NCHW `x`'s luma, (N, 1, H, W): the
    detail the rules move between frames. Luma only: the eye, and the
    sharpness ratio, see edges in luma."""
    luma = (x * LUMA.to(x.dtype)).sum(1, keepdim=True)
    return luma - local_mean(luma, 3)


def warp_detail_where_agreed(frame, reference, landed, tolerance: float):
    """`frame` that, where the warp landed, takes the warp's luma detail
    (beyond its 3x3 local mean) in the measure that the two frames' 5x5
    local means agree: fully where they match, a half where they differ by
    `tolerance` 8-bit levels (the RGB distance), little beyond.

    A head trained for MSE blends the warp with the decoded frame wherever
    the warp might be misplaced, and the blend averages two textures into
    blur. Where the warp's local colours match the frame shown, the warp lies
    on the right surface, and its pixels, the memory's own, have the edges.
    Luma only: the eye, and the sharpness ratio, see edges in luma; the
    colours stay the head's, which costs less where the warp is off."""
    distance2 = (local_mean(reference, 5) - local_mean(frame, 5)).pow(2).sum(1, keepdim=True) * 127.5**2
    agree = torch.exp(-math.log(2) * distance2 / tolerance**2)
    return frame + (luma_detail(reference) - luma_detail(frame)) * agree * landed


def head_of(model: Path, part: str = "kept") -> tuple[FusionHead, dict]:
    """The fusion head of an exported model folder, rebuilt from its
    fusion.onnx (the initializers keep the PyTorch names), and its manifest
    entry as a single head's. Of a head pair, the head `part` ("shown",
    "kept" or "holes"), with the model and training the pair records for it."""
    manifest = json.loads((model / "manifest.json").read_text())
    spec = manifest.get("fusion")
    if spec is None:
        raise SystemExit(f"{model}: has no fusion head")
    proto = onnx.load(model / spec["file"])
    prefix = f"{part}." if "pair" in spec else ""
    if prefix and not any(i.name.startswith(prefix) for i in proto.graph.initializer):
        prefix = "kept."  # a pair of one head stores it once, as the frame kept's
    weights = {i.name[len(prefix):]: torch.from_numpy(numpy_helper.to_array(i).copy())
               for i in proto.graph.initializer if i.name.startswith(prefix)}
    dilation_of = {n.input[1]: next((list(a.ints)[0] for a in n.attribute if a.name == "dilations"), 1)
                   for n in proto.graph.node if n.op_type == "Conv"}
    body = sorted(int(k.split(".")[1]) for k in weights if k.startswith("body.") and k.endswith(".weight"))
    head = FusionHead(weights["body.0.weight"].shape[0], tuple(dilation_of[f"{prefix}body.{i}.weight"] for i in body))
    head.load_state_dict({k: v for k, v in weights.items() if k.startswith(("body.", "out."))})
    if "pair" in spec:
        spec = {k: v for k, v in spec.items() if k != "pair"} | {
            "outputs": spec["outputs"][:1], "architecture": architecture(head),
            "parameters": sum(p.numel() for p in head.parameters()), "trained": spec["pair"][part]["trained"],
            "model": spec["pair"][part]["model"]}
    return head.eval(), spec


def trained_head(run: Path) -> tuple[FusionHead, dict]:
    """The head a `fusion-train` run saved (run/fusion.pt), and that checkpoint."""
    state = torch.load(run / "fusion.pt", weights_only=False)
    cfg = state["config"]
    head = FusionHead(cfg["width"], tuple(cfg["dilations"]))
    head.load_state_dict(state["head"])
    return head, state


def architecture(head: FusionHead) -> str:
    """How a manifest describes one head."""
    return (f"{len(head.dilations)} dilated 3x3 convolutions of width {head.width} (dilations {list(head.dilations)}); "
            f"output: a per-pixel convex blend of reference and decoded frame plus {CORRECTION} tanh(correction)")


def load_examples(folder: Path):
    """The arrays `worldpack fusion-data` wrote, as float tensors in [-1, 1], NCHW."""
    def rgb(name):
        a = np.load(folder / f"{name}.npy")
        return torch.from_numpy(a).permute(0, 3, 1, 2).float() / 127.5 - 1
    landed = torch.from_numpy(np.load(folder / "landed.npy")).float()[:, None]
    return rgb("predicted"), rgb("reference"), landed, rgb("truth")


def examples_of(data: list[Path]):
    """Every folder's examples, the last tenth of each (its suite's last trajectories) held
    out at the end: predicted, reference, landed, truth, and where the held-out part starts."""
    folders = [load_examples(d) for d in data]
    fit = [[x[: len(x) - max(1, len(x) // 10)] for x in f] for f in folders]
    held = [[x[len(x) - max(1, len(x) // 10):] for x in f] for f in folders]
    pred, ref, landed, truth = (torch.cat([f[i] for f in fit] + [h[i] for h in held]) for i in range(4))
    return pred, ref, landed, truth, sum(len(f[0]) for f in fit)


def head_config(width, head, data, n, cut, edge_weight, edge_landed, adversarial_weight, adversarial_start, texture_weight,
                landed_weight, init_from) -> dict:
    """What a run was trained with: a resumed run must match it."""
    config = {"width": width, "dilations": list(head.dilations), "data": [str(d) for d in data], "examples": n, "held_out": n - cut,
              "edge_weight": edge_weight, "edge_landed": edge_landed}
    if adversarial_weight > 0:
        config |= {"adversarial_weight": adversarial_weight, "adversarial_start": adversarial_start}
    if texture_weight > 0:
        config["texture_weight"] = texture_weight
    if landed_weight != 1:
        config["landed_weight"] = landed_weight
    if init_from is not None:
        config["init_from"] = str(init_from)
    return config


def score_held_out(head, pred, ref, landed, truth, cut: int) -> dict:
    """PSNR and sharpness of the head's frames on the held-out examples, beside its inputs'."""
    n = len(pred)
    with torch.no_grad():
        out = torch.cat([head(pred[i:i + 256], ref[i:i + 256], landed[i:i + 256]) for i in range(cut, n, 256)])
    t, holes = to_u8(truth[cut:]), (landed[cut:, 0] < 0.5).cpu().numpy()
    return {"fused": psnr(to_u8(out), t), "decoder": psnr(to_u8(pred[cut:]), t), "reference": psnr(to_u8(ref[cut:]), t),
            "average": psnr(to_u8((pred[cut:] + ref[cut:]) / 2), t), "sharpness": sharpness_ratio(to_u8(out), t),
            "holes_sharpness": sharpness_ratio(to_u8(out), t, holes, min_pairs=64),
            "decoder_sharpness": sharpness_ratio(to_u8(pred[cut:]), t)}


def regression_loss(out, t, m, landed_weight: float, edge_weight: float, edge_landed: float, texture_weight: float):
    """MSE (weighted by `landed_weight` where the warp landed), the gradient difference
    term and, in the holes, the detail energy term."""
    if landed_weight == 1:
        loss = F.mse_loss(out, t)
    else:
        weight_map = 1 - (1 - landed_weight) * m
        loss = ((out - t).pow(2) * weight_map).sum() / (weight_map.sum() * out.shape[1]).clamp(min=1e-6)
    if edge_weight > 0:
        where = None if edge_landed == 1 and landed_weight == 1 else (1 - (1 - edge_landed) * m) * (1 - (1 - landed_weight) * m)
        loss = loss + edge_weight * gradient_difference(out, t, where)
    if texture_weight > 0:
        loss = loss + texture_weight * detail_energy_difference(out, t, 1 - m)
    return loss


def train(data: list[Path], run: Path, steps: int, batch: int, lr: float, minutes: float | None, width: int, seed: int = 0,
          edge_weight: float = 0.0, edge_landed: float = 1.0, adversarial_weight: float = 0.0,
          adversarial_start: int = 500, init_from: Path | None = None, texture_weight: float = 0.0,
          landed_weight: float = 1.0) -> None:
    """Trains the head on `data` (`worldpack fusion-data` folders); the last
    tenth of each folder's examples (its suite's last trajectories) is held
    out and scored against the decoder's frame, the reference and their
    average. Resumes from run/fusion.pt. `edge_weight` > 0 adds the gradient
    difference loss against the truth (losses.py), which keeps the warp's
    edges where an MSE-only head would blend them away; `edge_landed` (in
    [0, 1]) weighs it per pixel where the warp landed (1 in its holes).

    `adversarial_weight` > 0 trains the head as pix2pix's generator (Isola et
    al. 2017): a conditional PatchGAN sees the frame with the reference and
    the landed mask it was made from, under the hinge loss, its term scaled by
    VQGAN's adaptive weight (losses.py) from `adversarial_start` on. Where the
    warp has no pixels the regression terms settle for the mean of what could
    be there; the discriminator asks for something that could be.

    `texture_weight` > 0 adds, in the warp's holes only, the patch-wise
    detail energy term (losses.detail_energy_difference): where no stored
    frame has the pixels, a head for the frame shown is asked for detail as
    strong as the truth's rather than its mean. `landed_weight` (in [0, 1])
    weighs the regression terms where the warp landed: 0 trains a head
    whose frame is used in the holes only (`HeadPair`'s `holes`).

    `init_from` (a run folder, or a model folder: its kept head) starts a new run from that head, with a
    fresh optimiser: a pix2pix head fine-tuned from a regression one."""
    if not 0 <= landed_weight <= 1:
        raise SystemExit(f"--landed-weight: a weight in [0, 1]; got {landed_weight}")
    if not texture_weight >= 0:
        raise SystemExit(f"--texture-weight: a weight of at least 0 (0: off); got {texture_weight}")
    run.mkdir(parents=True, exist_ok=True)
    pred, ref, landed, truth, cut = examples_of(data)
    n = len(pred)
    torch.manual_seed(seed)
    head = FusionHead(width)
    adversarial = adversarial_weight > 0
    # Adam's betas as pix2pix and VQGAN train their generators when a discriminator is in the loop.
    betas = (0.5, 0.999) if adversarial else (0.9, 0.999)
    opt = torch.optim.Adam(head.parameters(), lr=lr, betas=betas)
    disc = PatchDiscriminator(channels=3 + 3 + 1) if adversarial else None
    opt_d = torch.optim.Adam(disc.parameters(), lr=lr, betas=betas) if adversarial else None
    ckpt = run / "fusion.pt"
    step = resume(ckpt, head, opt, "the fusion head", key="head")
    if init_from is not None and not step:
        # A model folder's kept head, or a fusion-train run's.
        start, saved = ((head_of(init_from, "kept")[0], {"step": "exported"}) if (init_from / "manifest.json").exists()
                        else trained_head(init_from))
        if architecture(start) != architecture(head):
            raise SystemExit(f"--init-from: {init_from}'s head is {architecture(start)}, not {architecture(head)}")
        head.load_state_dict(start.state_dict())
        print(f"starting from the head of {init_from} (its step {saved['step']})")
    config = head_config(width, head, data, n, cut, edge_weight, edge_landed, adversarial_weight, adversarial_start,
                         texture_weight, landed_weight, init_from)
    if step:
        state = torch.load(ckpt, weights_only=False)
        if state["config"] != config:
            raise SystemExit(f"--run: {ckpt} was trained with {state['config']}, not {config}; use another run folder")
        if adversarial:
            disc.load_state_dict(state["disc"])
            opt_d.load_state_dict(state["opt_d"])

    def save():
        extra = {"disc": disc.state_dict(), "opt_d": opt_d.state_dict()} if adversarial else {}
        torch.save({"head": head.state_dict(), "opt": opt.state_dict(), "step": step, "config": config, **extra}, ckpt)

    started, last_print = time.time(), time.time()
    gen = torch.Generator().manual_seed(seed + step)
    log = open(run / "fusion.log", "a")
    while step < steps:
        idx = torch.randint(0, cut, (batch,), generator=gen)
        p, r, m, t = pred[idx], ref[idx], landed[idx], truth[idx]
        if torch.rand(1, generator=gen).item() < 0.5:  # mirror: the head's task has no handedness
            p, r, m, t = (x.flip(-1) for x in (p, r, m, t))
        for g in opt.param_groups:
            g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * step / steps))
        out = head(p, r, m)
        loss = regression_loss(out, t, m, landed_weight, edge_weight, edge_landed, texture_weight)
        weight = 0.0
        if adversarial and step >= adversarial_start:
            g_adv = -disc(torch.cat([out, r, m], 1)).mean()
            weight = adversarial_weight * adaptive_weight(loss, g_adv, head.out.weight)
            loss = loss + weight * g_adv
        opt.zero_grad()
        loss.backward()
        opt.step()
        d_loss = 0.0
        if adversarial:
            d = hinge_discriminator(disc(torch.cat([t, r, m], 1)), disc(torch.cat([out.detach(), r, m], 1)))
            opt_d.zero_grad()
            d.backward()
            opt_d.step()
            d_loss = d.item()
        step += 1
        if time.time() - last_print > 30 or step == steps:
            last_print = time.time()
            line = f"step {step}/{steps} loss {loss.item():.5f} ({(time.time() - started) / 60:.1f} min)"
            if adversarial:
                line += f" d_loss {d_loss:.3f} adversarial weight {float(weight):.4f}"
            print(line, flush=True)
            log.write(line + "\n")
            log.flush()
            save()
        if minutes is not None and time.time() - started > 60 * minutes:
            print(f"stopping after {minutes} min at step {step}; run again to resume")
            break
    save()
    scores = score_held_out(head, pred, ref, landed, truth, cut)
    line = "held out ({} examples): ".format(n - cut) + ", ".join(f"{k} {v:.2f}" for k, v in scores.items())
    print(line)
    log.write(line + "\n")
    (run / "fusion-held-out.json").write_text(json.dumps({"step": step, **config, "scores": scores}, indent=1))


def loss_name(cfg: dict) -> str:
    """The training loss as the manifest names it (heads from before the edge term have none in `cfg`)."""
    name = "MSE"
    if cfg.get("edge_weight"):
        name += f" + {cfg['edge_weight']} x gradient difference (Mathieu et al. 2016)"
        if cfg.get("edge_landed", 1) != 1:
            name += f", weighted {cfg['edge_landed']} where the warp landed"
    if cfg.get("landed_weight", 1) != 1:
        name += f" (these weighted {cfg['landed_weight']} where the warp landed)"
    if cfg.get("texture_weight"):
        name += f" + {cfg['texture_weight']} x patch detail energy in the warp's holes (after EnhanceNet's texture loss)"
    if cfg.get("adversarial_weight"):
        name += (f" + {cfg['adversarial_weight']} x conditional PatchGAN hinge (pix2pix, spectral norm) under VQGAN's adaptive weight, "
                 f"from step {cfg['adversarial_start']}")
    return name


def reference_images(data: Path | None, h: int, w: int) -> tuple:
    """A head's reference inputs (predicted, reference, landed) for two
    items: the last held-out examples when at hand, else seeded noise."""
    if data is not None:
        p, r, m, _ = load_examples(data)
        return p[-2:], r[-2:], m[-2:]
    g = torch.Generator().manual_seed(0)
    return (torch.rand(2, 3, h, w, generator=g) * 2 - 1, torch.rand(2, 3, h, w, generator=g) * 2 - 1,
            (torch.rand(2, 1, h, w, generator=g) > 0.3).float())


def export(run: Path, model: Path, out: Path, data: Path | None = None) -> None:
    """A copy of the model folder `model` at `out` with the head as
    `fusion.onnx`, its manifest entry and references for the parity tests."""

    head, state = trained_head(run)
    cfg = state["config"]
    head.eval()
    manifest = json.loads((model / "manifest.json").read_text())
    if "warp" not in manifest["denoiser"]:
        raise SystemExit(f"--model: {model} takes no warp input, so there is nothing to fuse")
    if "fusion" in manifest:
        raise SystemExit(f"--model: {model} has a fusion head already")
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(model, out)
    h, w = manifest["image"]["height"], manifest["image"]["width"]
    args = reference_images(data, h, w)
    proto = to_onnx(head, args, list(INPUTS), ["image"])

    onnx.save(proto, out / "fusion.onnx")
    folder = out / "reference" / "fusion"
    folder.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        image = head(*args)
    for name, t in zip(INPUTS + ("image",), args + (image,)):
        np.save(folder / f"{name}.npy", t.numpy().astype(np.float32))
    image_spec = lambda name, meaning: {"name": name, "shape": ["batch", 3, h, w], "dtype": "float32", "meaning": meaning}
    manifest["name"] = out.name
    manifest["fusion"] = {
        "file": "fusion.onnx",
        "inputs": [
            image_spec("predicted", "the decoded frame, RGB in [-1, 1]"),
            image_spec("reference", "the fused reference of the warp sources (model::warp::fused_reference), RGB in [-1, 1]"),
            {"name": "landed", "shape": ["batch", 1, h, w], "dtype": "float32", "meaning": "1 where the warp itself landed, else 0"},
        ],
        "outputs": [image_spec("image", "the frame shown, RGB, nominally [-1, 1]; clamp before converting")],
        "architecture": architecture(head),
        "parameters": sum(p.numel() for p in head.parameters()),
        "trained": {"steps": state["step"], "examples": cfg["examples"], "data": cfg["data"], "loss": loss_name(cfg)},
    }
    manifest["reference"]["graphs"]["fusion"] = "reference/fusion"
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"wrote {out} ({manifest['fusion']['parameters']} fusion parameters)")


def pair(kept: Path, shown: Path, out: Path, data: Path | None = None, hole_fill: int = 0, hole_detail: int = 0,
         warp_detail: float = 0.0, holes: Path | None = None) -> None:
    """A copy of the model folder `kept` at `out` whose head is a `HeadPair`:
    the frame shown is `shown`'s head's, with the decoded frame's detail in
    the warp's holes when `hole_detail` (an odd window) is set; the frame
    the memory keeps is `kept`'s own head's (the graph's second output,
    `kept`), its holes filled from the warp when `hole_fill` is set.
    `warp_detail` T > 0: the frame shown takes the warp's luma detail where the
    warp landed and agrees with it to within about T 8-bit levels.
    `holes`: a model folder whose head's luma detail the frame shown takes
    in the warp's holes."""
    for flag, k in (("--hole-fill", hole_fill), ("--hole-detail", hole_detail)):
        if k and (k < 3 or k % 2 == 0):
            raise SystemExit(f"{flag}: an odd window of at least 3 pixels, or 0 for none; got {k}")
    if not (warp_detail >= 0 and math.isfinite(warp_detail)):
        raise SystemExit(f"--warp-detail: a tolerance in 8-bit levels, at least 0 (0: off); got {warp_detail}")
    kept_head, kept_spec = head_of(kept, "kept")
    shown_head, shown_spec = head_of(shown, "shown")
    manifest = json.loads((kept / "manifest.json").read_text())
    h, w = manifest["image"]["height"], manifest["image"]["width"]
    shown_image = json.loads((shown / "manifest.json").read_text())["image"]
    if (shown_image["height"], shown_image["width"]) != (h, w):
        raise SystemExit(f"--shown: {shown} makes {shown_image['width']}x{shown_image['height']} frames, {kept} {w}x{h}")
    with tempfile.TemporaryDirectory() as tmp:
        staged = Path(tmp) / out.name
        shutil.copytree(kept, staged)
        same = architecture(shown_head) == architecture(kept_head) and all(
            torch.equal(a, b) for a, b in zip(shown_head.state_dict().values(), kept_head.state_dict().values()))
        holes_head, holes_spec = head_of(holes, "holes") if holes is not None else (None, None)
        heads = HeadPair(kept_head if same else shown_head, kept_head, hole_fill, hole_detail, warp_detail,
                         holes_head).eval()
        args = reference_images(data, h, w)
        outputs = ("image", "kept")
        onnx.save(to_onnx(heads, args, list(INPUTS), list(outputs)), staged / kept_spec["file"])
        with torch.no_grad():
            got = heads(*args)
        for name, t in zip(INPUTS + outputs, args + got):
            np.save(staged / "reference" / "fusion" / f"{name}.npy", t.numpy().astype(np.float32))
        spec = {k: v for k, v in kept_spec.items() if k not in ("trained", "architecture", "parameters", "model")}
        spec["outputs"] = [kept_spec["outputs"][0], dict(kept_spec["outputs"][0], name="kept",
                                                         meaning="the frame the memory keeps (re-encoded as later frames' context), RGB")]
        spec["architecture"] = (f"one head for both frames: {kept_spec['architecture']}" if same else
                                f"two heads on the same inputs, one for the frame shown and one for the frame kept; each: {kept_spec['architecture']}") + (
            f"; the kept frame's {hole_fill}x{hole_fill} local mean in the warp's holes replaced by the warp's colours diffused into them"
            if hole_fill else "") + (
            f"; the frame shown takes the decoded frame's detail (beyond its {hole_detail}x{hole_detail} local mean) in the warp's holes"
            if hole_detail else "") + (
            f"; where the warp landed, the frame shown takes the warp's luma detail (beyond its 3x3 local mean) in the measure "
            f"that their 5x5 local means agree (a half at {warp_detail:g} 8-bit levels apart)" if warp_detail else "") + (
            f"; in the warp's holes the frame shown takes the luma detail (beyond its 3x3 local mean) of a third head "
            f"on the same inputs ({holes_spec['architecture']})" if holes is not None else "")
        spec["parameters"] = kept_spec["parameters"] + (0 if same else shown_spec["parameters"]) + (
            holes_spec["parameters"] if holes is not None else 0)
        spec["pair"] = {"shown": {"model": shown_spec.get("model", shown.name), "trained": shown_spec.get("trained")},
                        "kept": {"model": kept_spec.get("model", kept.name), "trained": kept_spec.get("trained")},
                        "hole_fill": hole_fill, "hole_detail": hole_detail, "warp_detail": warp_detail}
        if holes is not None:
            spec["pair"]["holes"] = {"model": holes_spec.get("model", holes.name), "trained": holes_spec.get("trained")}
        manifest["name"] = out.name
        manifest["fusion"] = spec
        (staged / "manifest.json").write_text(json.dumps(manifest, indent=1))
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(staged, out)
    print(f"wrote {out}: shows {shown.name}'s head's frame, keeps {kept.name}'s")


def without_head(model: Path, out: Path) -> None:
    """A copy of the fused model folder `model` at `out` with its fusion head
    (graph, manifest entry, references) taken out: the bare model a head's
    training examples are made with (`worldpack fusion-data --model`)."""
    manifest = json.loads((model / "manifest.json").read_text())
    spec = manifest.pop("fusion", None)
    if spec is None:
        raise SystemExit(f"--model: {model} has no fusion head to take out")
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(model, out)
    (out / spec["file"]).unlink()
    shutil.rmtree(out / "reference" / "fusion", ignore_errors=True)
    manifest["reference"]["graphs"].pop("fusion", None)
    manifest["name"] = out.name
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"wrote {out}: {model.name} without its fusion head")
