"""Weights read back from exported ONNX graphs, checked against a model folder's references."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import onnx
import onnx.numpy_helper
import torch
from torch import nn


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


def reference_gap(module: nn.Module, ref: Path, given: str, expected: str) -> float:
    """The largest difference between `module` run on a reference folder's input
    array and its output array. Run on the CPU, where the reference was made:
    a GPU's TF32 convolutions alone differ by about 1e-3."""
    with torch.no_grad():
        got = copy.deepcopy(module).cpu()(torch.from_numpy(np.load(ref / given))).numpy()
    return float(np.abs(got - np.load(ref / expected)).max())


def decoder_from(model_dir: Path, autoencoder: nn.Module) -> None:
    """Loads a model folder's exported decoder into `autoencoder` (a committed
    fine-tune continues from its graph, an export or a student takes a sharpened
    one), checked against the folder's reference. The autoencoder's encoder
    must be the folder's: a decoder fits only the latent space it was trained on."""

    check_same_encoder(autoencoder.encoder, model_dir, "--decoder-from: the run's encoder")
    decoder = autoencoder.decoder
    manifest = json.loads((model_dir / "manifest.json").read_text())
    load_state(decoder, [Graph(model_dir / manifest["autoencoder"]["decoder"]["file"])], "")
    ref = model_dir / "reference" / "decoder"
    worst = reference_gap(decoder, ref, "latent.npy", "image.npy")
    if worst > 1e-3:
        raise SystemExit(f"--decoder-from: the rebuilt decoder differs from {ref} by {worst:.2e}")


def check_same_encoder(encoder: nn.Module, model_dir: Path, what: str) -> None:
    """Refuses to put a decoder and an encoder together that were not trained
    on the same latent space: `encoder` must reproduce `model_dir`'s encoder reference."""
    worst = reference_gap(encoder, model_dir / "reference" / "encoder", "image.npy", "latent.npy")
    if worst > 1e-3:
        raise SystemExit(f"{what} is not {model_dir}'s (latents differ by {worst:.2e}); "
                         "a decoder trained on one would not fit the other's latents")
