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
import onnx
import onnx.numpy_helper
import torch

from .autoencoder import Autoencoder, build as build_autoencoder
from .cdit import CDiT
from .config import ModelConfig
from .export import context_keys
from .train import save


class Graph:
    """An ONNX graph's initializers (float16 ones widened) and producers."""

    def __init__(self, path: Path):
        proto = onnx.load(str(path))  # external data resolves next to the file
        self.values = {i.name: onnx.numpy_helper.to_array(i) for i in proto.graph.initializer}
        self.nodes = list(proto.graph.node)
        self.producer = {out: n for n in proto.graph.node for out in n.output}
        self.consumers: dict[str, list] = {}
        for n in proto.graph.node:
            for i in n.input:
                self.consumers.setdefault(i, []).append(n)

    def value(self, name: str) -> np.ndarray | None:
        """An initializer, looking through Cast, Transpose and Identity nodes."""
        if name in self.values:
            return self.values[name].astype(np.float32)
        if name + "__f16" in self.values:
            return self.values[name + "__f16"].astype(np.float32)
        node = self.producer.get(name)
        if node is None:
            return None
        if node.op_type in ("Cast", "Identity"):
            return self.value(node.input[0])
        if node.op_type == "Transpose":
            v = self.value(node.input[0])
            perm = next((list(a.ints) for a in node.attribute if a.name == "perm"), None)
            return None if v is None else np.transpose(v, perm)
        return None

    def group_norm_affines(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(scale, shift) of every GroupNorm, in execution order: the exporter
        lowers each to InstanceNormalization, Reshape, Mul(scale), Add(shift)."""
        out = []
        for node in self.nodes:
            if node.op_type != "InstanceNormalization":
                continue
            reshape = self.consumers[node.output[0]][0]
            mul = self.consumers[reshape.output[0]][0]
            add = self.consumers[mul.output[0]][0]
            scale = self.value(next(i for i in mul.input if i != reshape.output[0]))
            shift = self.value(next(i for i in add.input if i != mul.output[0]))
            out.append((scale.reshape(-1), shift.reshape(-1)))
        return out

    def linear_bias(self, weight_name: str) -> np.ndarray | None:
        """The bias of the Gemm that takes `weight_name` (the exporter shares one
        initializer among equal biases, so a bias can go by another's name)."""
        for name in (weight_name, weight_name + "__f16"):
            for user in self.consumers.get(name, []):
                if user.op_type == "Cast":
                    return self.linear_bias(user.output[0])
                if user.op_type == "Gemm" and len(user.input) > 2:
                    return self.value(user.input[2])
        return None

    def linear_weight(self, bias_name: str) -> np.ndarray | None:
        """(out, in) weight of the linear layer whose bias is `bias_name`."""
        for user in self.consumers.get(bias_name, []) + self.consumers.get(bias_name + "__f16", []):
            if user.op_type == "Cast":
                return self.linear_weight(user.output[0])
            if user.op_type == "Gemm":
                w = self.value(user.input[1])
                trans_b = next((a.i for a in user.attribute if a.name == "transB"), 0)
                return None if w is None else (w if trans_b else w.T)
            if user.op_type == "Add":
                other = next(i for i in user.input if i != bias_name)
                mm = self.producer.get(other)
                if mm is not None and mm.op_type == "MatMul":
                    w = self.value(mm.input[1])
                    return None if w is None else w.T
        return None


def load_state(module: torch.nn.Module, graphs: list[Graph], prefix: str, unused: tuple[str, ...] = ()) -> list[str]:
    """Fills every parameter of `module` from the graphs; names what is missing.
    Parameters starting with one of `unused` may be absent (no exported graph
    uses them); they keep their initialisation and are returned."""
    state = module.state_dict()
    missing, found = [], {}
    # GroupNorm affines have no names in the graph: they pair up in module order.
    norms = [n for n, m in module.named_modules() if isinstance(m, torch.nn.GroupNorm)]
    affines = [a for g in graphs for a in g.group_norm_affines()]
    if len(norms) != len(affines):
        raise SystemExit(f"--model: {len(norms)} GroupNorms in the module, {len(affines)} in the graphs")
    for norm, (scale, shift) in zip(norms, affines):
        found[f"{norm}.weight"], found[f"{norm}.bias"] = torch.from_numpy(scale.copy()), torch.from_numpy(shift.copy())
    for name, tensor in state.items():
        if name in found:
            continue
        value = None
        for g in graphs:
            value = g.value(prefix + name)
            if value is None and name.endswith(".weight"):
                value = g.linear_weight(prefix + name[: -len("weight")] + "bias")
            if value is None and name.endswith(".bias"):
                value = g.linear_bias(prefix + name[: -len("bias")] + "weight")
            if value is not None:
                break
        if value is None or tuple(value.shape) != tuple(tensor.shape):
            missing.append(f"{name} {tuple(tensor.shape)}" + ("" if value is None else f" (found {value.shape})"))
        else:
            found[name] = torch.from_numpy(np.ascontiguousarray(value))
    for name, tensor in state.items():
        if name in found and tuple(found[name].shape) != tuple(tensor.shape):
            missing.append(f"{name} {tuple(tensor.shape)} (found {tuple(found[name].shape)})")
    absent = [m.split(" ")[0] for m in missing if m.startswith(unused) and "found" not in m]
    missing = [m for m in missing if m.split(" ")[0] not in absent]
    if missing:
        raise SystemExit(f"--model: these parameters are not in the graphs: {missing}")
    module.load_state_dict(found, strict=not absent)
    return absent


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
        from .diffusion import Schedule
        from .distill import EpsFromV

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
