"""The Triton model repository for GPU deployments (serving/triton/repository.py).

Triton cannot run its onnxruntime backend here, so each written config.pbtxt
is parsed into Triton's own model-config schema (tritonclient's
model_config_pb2, strict protobuf text format) and checked against the
manifest, and each written model.onnx is opened in ONNX Runtime beside its
copied external weights.
"""

import json
import pathlib
import sys

import onnxruntime as ort
import pytest
from google.protobuf import text_format
from tritonclient.grpc import model_config_pb2

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "serving" / "triton"))
import repository  # noqa: E402


def parse(path):
    return text_format.Parse(path.read_text(), model_config_pb2.ModelConfig())


@pytest.mark.parametrize("model", ["fixtures/small", "fixtures/variants/worldpack_geometry", "fixtures/variants/worldpack_geometry_fused",
                                   "fixtures/variants/worldpack_geometry_fused_1step"])
def test_the_repository_parses_as_triton_model_configs_matching_the_manifest(tmp_path, model):
    model_dir = ROOT / model
    manifest = json.loads((model_dir / "manifest.json").read_text())
    names = repository.write(model_dir, tmp_path, max_batch=32, queue_delay_us=500, gpu=True)
    assert names[:2] == [f"{manifest['name']}-encoder", f"{manifest['name']}-decoder"]
    assert len(names) == 2 + len(manifest["denoiser"]["layouts"]) + ("fusion" in manifest)
    for (role, spec), name in zip(repository.graphs(manifest), names):
        config = parse(tmp_path / name / "config.pbtxt")
        assert (config.name, config.platform, config.max_batch_size) == (name, "onnxruntime_onnx", 32)
        assert config.dynamic_batching.max_queue_delay_microseconds == 500
        assert config.instance_group[0].kind == model_config_pb2.ModelInstanceGroup.KIND_GPU
        for declared, served in [(spec["inputs"], config.input), (spec["outputs"], config.output)]:
            assert [t["name"] for t in declared] == [t.name for t in served]
            for t, s in zip(declared, served):
                assert s.data_type == model_config_pb2.TYPE_FP32
                item = [d if isinstance(d, int) else -1 for d in t["shape"][1:]]
                assert list(s.dims) == (item or [1]), t["name"]
                assert s.HasField("reshape") == (not item), t["name"]  # (batch,) travels as (batch, 1)
        # The graph opens where Triton will open it, its weights beside it.
        session = ort.InferenceSession(str(tmp_path / name / "1" / "model.onnx"), providers=["CPUExecutionProvider"])
        assert [i.name for i in session.get_inputs()] == [t["name"] for t in spec["inputs"]]


def test_the_config_parser_is_strict(tmp_path):
    """A misspelt field is an error, so the test above could fail."""
    repository.write(ROOT / "fixtures/small", tmp_path)
    path = tmp_path / "small-encoder" / "config.pbtxt"
    path.write_text(path.read_text().replace("max_batch_size", "max_batch"))
    with pytest.raises(text_format.ParseError):
        parse(path)


def test_a_graph_without_a_batch_axis_is_refused():
    with pytest.raises(ValueError, match="leading batch axis"):
        repository.tensor_block({"name": "x", "shape": [4, 16], "dtype": "float32"})
