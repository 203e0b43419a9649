"""Writing ONNX graphs and reference arrays: tracing, shared and half-precision weights."""

from __future__ import annotations

import hashlib
import inspect
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from ..core.config import ModelConfig

OPSET = 18


IR_VERSION = 10  # what opset 18 needs; ONNX Runtime 1.31 loads it (the parity tests check)


def context_keys(cfg: ModelConfig) -> tuple[str, ...]:
    """A context group's inputs, in the model's order."""
    keys = ("context", "context_time", "context_pose", "context_mask")
    return keys + ("context_noise",) if cfg.cdit.context_noise else keys


def to_onnx(module: nn.Module, args: tuple, names: list[str], outputs: list[str]) -> onnx.ModelProto:
    module.eval()  # an inference graph (a wrapper such as LayoutGraph is built in training mode)
    batch = torch.export.Dim("batch", min=1, max=1024)
    shapes = [{0: batch} for _ in args]
    fixed = [p for p in inspect.signature(module.forward).parameters.values() if p.kind != p.VAR_POSITIONAL]
    if len(fixed) < len(args):  # torch.export wants *args' shapes as one nested tuple
        shapes = shapes[: len(fixed)] + [tuple(shapes[len(fixed):])]
    program = torch.onnx.export(module, args, input_names=names, output_names=outputs, dynamic_shapes=tuple(shapes),
                                opset_version=OPSET, dynamo=True, verbose=False)
    proto = program.model_proto
    proto.ir_version = IR_VERSION
    for node in proto.graph.node:  # the exporter's per-node stack traces: most of the file, no use at runtime
        del node.metadata_props[:]
    onnx.checker.check_model(proto)
    return proto


def share_weights(protos: dict[str, onnx.ModelProto], weights: Path) -> None:
    """Moves every initializer of 1 KiB or more into one external-data file,
    storing identical tensors once (the layouts share all their weights)."""
    offsets: dict[str, tuple[int, int]] = {}
    with open(weights, "wb") as f:
        for proto in protos.values():
            for init in proto.graph.initializer:
                raw = onnx.numpy_helper.to_array(init).tobytes()
                if len(raw) < 1024:
                    continue
                # By content alone: the exporter names folded constants differently per graph.
                key = hashlib.sha256(raw).hexdigest()
                if key not in offsets:
                    f.write(b"\0" * ((-f.tell()) % 64))  # 64-byte alignment lets the runtime map it
                    offsets[key] = (f.tell(), len(raw))
                    f.write(raw)
                offset, length = offsets[key]
                init.ClearField("raw_data")
                for field in ("float_data", "int64_data", "int32_data", "double_data"):
                    init.ClearField(field)
                init.data_location = onnx.TensorProto.EXTERNAL
                del init.external_data[:]
                for k, v in (("location", weights.name), ("offset", str(offset)), ("length", str(length))):
                    entry = init.external_data.add()
                    entry.key, entry.value = k, v


def round_to_half(*modules: nn.Module) -> None:
    """Rounds every parameter to the nearest float16 value (kept as float32),
    so that the model the references come from is exactly the one stored."""
    with torch.no_grad():
        for m in modules:
            for p in m.parameters():
                p.copy_(p.half().float())


def store_half(proto: onnx.ModelProto) -> None:
    """Stores each float32 initializer that float16 holds exactly as float16
    behind a Cast back to float32 (ONNX Runtime folds the Cast when it loads
    the graph), halving the file. Initializers that would lose a bit, such as
    folded constants, stay float32, so the graph computes what it did."""
    casts = []
    for init in proto.graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT:
            continue
        a = onnx.numpy_helper.to_array(init)
        if a.size < 256 or not np.array_equal(a.astype(np.float16).astype(np.float32), a):
            continue
        name = init.name
        init.CopyFrom(onnx.numpy_helper.from_array(a.astype(np.float16), name + "__f16"))
        casts.append(onnx.helper.make_node("Cast", [name + "__f16"], [name], to=onnx.TensorProto.FLOAT, name=name + "__cast"))
    nodes = casts + list(proto.graph.node)  # casts first keeps the graph topologically sorted
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)


def save_arrays(folder: Path, arrays: dict[str, np.ndarray]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, a in arrays.items():
        np.save(folder / f"{name}.npy", a)


def tensor_spec(name: str, shape: list, dtype: str, meaning: str) -> dict:
    return {"name": name, "shape": shape, "dtype": dtype, "meaning": meaning}
