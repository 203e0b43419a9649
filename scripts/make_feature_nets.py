"""Makes the tiny feature networks and golden values in fixtures/metrics/
that test the Rust LPIPS, DreamSim-style and FVD arithmetic (eval::features).
The networks are random and mean nothing; they have the shapes and tensor
names of the real ones (docs/metrics.md says how to export those). Features
come from ONNX Runtime, the metric arithmetic from NumPy, independently of
the Rust code under test.

    .venv/bin/python scripts/make_feature_nets.py fixtures/metrics
"""

import json
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

OPSET, IR = 18, 10
rng = np.random.default_rng(20261121)


def save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="worldpack tests")
    model.ir_version = IR
    onnx.checker.check_model(model)
    onnx.save(model, path)


def init(name, a):
    return numpy_helper.from_array(np.asarray(a, np.float32), name)


def lpips_net(path):
    w0, w1 = rng.normal(0, 0.5, (4, 3, 3, 3)), rng.normal(0, 0.5, (5, 4, 3, 3))
    lin0, lin1 = rng.uniform(0.1, 1.0, 4), rng.uniform(0.1, 1.0, 5)
    nodes = [
        helper.make_node("Conv", ["image", "w0"], ["c0"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c0"], ["feat0"]),
        helper.make_node("Conv", ["feat0", "w1"], ["c1"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["feat1"]),
        helper.make_node("Identity", ["lin0"], ["weight0"]),
        helper.make_node("Identity", ["lin1"], ["weight1"]),
    ]
    g = helper.make_graph(nodes, "lpips_tiny", [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", 3, "h", "w"])],
                          [helper.make_tensor_value_info("feat0", TensorProto.FLOAT, ["batch", 4, "h0", "w0"]), helper.make_tensor_value_info("feat1", TensorProto.FLOAT, ["batch", 5, "h1", "w1"]),
                           helper.make_tensor_value_info("weight0", TensorProto.FLOAT, [4]), helper.make_tensor_value_info("weight1", TensorProto.FLOAT, [5])],
                          [init("w0", w0), init("w1", w1), init("lin0", lin0), init("lin1", lin1)])
    save(g, path)


def embed_net(path):
    w = rng.normal(0, 0.5, (8, 3, 4, 4))
    nodes = [helper.make_node("Conv", ["image", "w"], ["c"], kernel_shape=[4, 4], strides=[4, 4]),
             helper.make_node("Relu", ["c"], ["r"]),
             helper.make_node("GlobalAveragePool", ["r"], ["p"]),
             helper.make_node("Flatten", ["p"], ["embedding"], axis=1)]
    g = helper.make_graph(nodes, "embed_tiny", [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", 3, "h", "w"])],
                          [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["batch", 8])], [init("w", w)])
    save(g, path)


def video_net(path, frames=4, dim=6):
    w = rng.normal(0, 1.0, (3 * frames, dim))
    nodes = [helper.make_node("ReduceMean", ["video", "axes"], ["m"], keepdims=0),
             helper.make_node("Flatten", ["m"], ["f"], axis=1),
             helper.make_node("MatMul", ["f", "w"], ["z"]),
             helper.make_node("Tanh", ["z"], ["features"])]
    g = helper.make_graph(nodes, "video_tiny", [helper.make_tensor_value_info("video", TensorProto.FLOAT, ["batch", 3, frames, "h", "w"])],
                          [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["batch", dim])],
                          [init("w", w), numpy_helper.from_array(np.array([3, 4], np.int64), "axes")])
    save(g, path)


def to_unit(u8):  # (..., H, W, 3) uint8 -> (..., 3, H, W) in [-1, 1]
    return np.moveaxis(u8.astype(np.float32) / 127.5 - 1.0, -1, -3)


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "fixtures/metrics")
    out.mkdir(parents=True, exist_ok=True)
    lpips_net(out / "lpips_tiny.onnx")
    embed_net(out / "embed_tiny.onnx")
    video_net(out / "video_tiny.onnx")

    # Pairs of 32x32 images, the second of each pair a perturbed copy; videos of 4 frames at 16x16.
    a = rng.integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    b = np.clip(a.astype(np.int16) + rng.integers(-60, 61, a.shape), 0, 255).astype(np.uint8)
    b[2] = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    real = rng.integers(0, 256, (12, 4, 16, 16, 3), dtype=np.uint8)
    fake = np.clip(real.astype(np.int16) + rng.integers(-40, 80, real.shape), 0, 255).astype(np.uint8)
    for name, arr in (("images_a", a), ("images_b", b), ("videos_real", real), ("videos_fake", fake)):
        np.save(out / f"{name}.npy", arr)

    run = lambda f, feed: ort.InferenceSession(str(out / f), providers=["CPUExecutionProvider"]).run(None, feed)
    fa, fb = run("lpips_tiny.onnx", {"image": to_unit(a)}), run("lpips_tiny.onnx", {"image": to_unit(b)})
    norm = lambda x: x / (np.sqrt((x.astype(np.float64) ** 2).sum(axis=1, keepdims=True)) + 1e-10)
    lpips = sum(((norm(fa[i]) - norm(fb[i])) ** 2 * fa[2 + i][None, :, None, None]).sum(axis=1).mean(axis=(1, 2)) for i in range(2))
    ea, eb = run("embed_tiny.onnx", {"image": to_unit(a)})[0].astype(np.float64), run("embed_tiny.onnx", {"image": to_unit(b)})[0].astype(np.float64)
    cos = (ea * eb).sum(1) / (np.linalg.norm(ea, axis=1) * np.linalg.norm(eb, axis=1))
    vr = run("video_tiny.onnx", {"video": np.moveaxis(to_unit(real), 1, 2)})[0].astype(np.float64)  # (B,T,3,H,W) -> (B,3,T,H,W)
    vf = run("video_tiny.onnx", {"video": np.moveaxis(to_unit(fake), 1, 2)})[0].astype(np.float64)
    mr, mf = vr.mean(0), vf.mean(0)
    sr, sf = np.cov(vr, rowvar=False), np.cov(vf, rowvar=False)
    trace_sqrt = np.sqrt(np.clip(np.linalg.eigvals(sr @ sf).real, 0, None)).sum()
    fvd = float(((mr - mf) ** 2).sum() + np.trace(sr) + np.trace(sf) - 2 * trace_sqrt)
    golden = {"lpips": lpips.tolist(), "dreamsim": (1 - cos).tolist(), "fvd": fvd,
              "note": "features from ONNX Runtime, arithmetic from NumPy (scripts/make_feature_nets.py)"}
    (out / "golden.json").write_text(json.dumps(golden, indent=2))
    print(json.dumps(golden))


if __name__ == "__main__":
    main()
