"""Write a Triton model repository for a WorldPack model folder (GPU deployments).

One Triton model per graph, named as `worldpack serve --model-backend` expects
(`<name>-encoder`, `<name>-decoder`, `<name>-denoiser-<layout>`), each run by
Triton's own onnxruntime backend with dynamic batching:

    python serving/triton/repository.py --model fixtures/small --out model_repository --gpu
    tritonserver --model-repository model_repository      # then:
    worldpack serve --model fixtures/small --model-backend triton://HOST:8000

Tensors that are only the batch axis (the timestep) are declared with dims [1]
and reshaped to [] for the graph: Triton needs an axis besides the batch one,
and WorldPack sends them as (batch, 1). Standard library only.
"""

import argparse
import json
import pathlib
import shutil
import sys


def graphs(manifest):
    """(role, graph spec) for every graph the manifest lists; role as in the Triton model name."""
    yield "encoder", manifest["autoencoder"]["encoder"]
    yield "decoder", manifest["autoencoder"]["decoder"]
    for layout in manifest["denoiser"]["layouts"]:
        yield f"denoiser-{layout['name']}", layout
    if "fusion" in manifest:
        yield "fusion", manifest["fusion"]


def tensor_block(spec):
    if spec["dtype"] != "float32" or not spec["shape"] or spec["shape"][0] != "batch":
        raise ValueError(f"{spec['name']}: only float32 tensors with a leading batch axis can be batched, got {spec['shape']}")
    dims = [d if isinstance(d, int) else -1 for d in spec["shape"][1:]]
    reshape = "" if dims else " reshape: { shape: [ ] }"
    return f'  {{ name: "{spec["name"]}" data_type: TYPE_FP32 dims: [ {", ".join(map(str, dims or [1]))} ]{reshape} }}'


def config_text(name, spec, max_batch, queue_delay_us, gpu):
    inputs = ",\n".join(tensor_block(t) for t in spec["inputs"])
    outputs = ",\n".join(tensor_block(t) for t in spec["outputs"])
    kind = "KIND_GPU" if gpu else "KIND_CPU"
    return (f'name: "{name}"\nplatform: "onnxruntime_onnx"\nmax_batch_size: {max_batch}\n'
            f"input [\n{inputs}\n]\noutput [\n{outputs}\n]\n"
            f"dynamic_batching {{ max_queue_delay_microseconds: {queue_delay_us} }}\n"
            f"instance_group [ {{ count: 1 kind: {kind} }} ]\n")


def write(model_dir, out, max_batch=64, queue_delay_us=1000, gpu=False):
    manifest = json.loads((model_dir / "manifest.json").read_text())
    # Graphs keep their weights in external files next to them (the denoiser
    # layouts share one); each Triton model's version folder gets a copy.
    external = [f for f in [manifest["denoiser"].get("weights")] if f]
    written = []
    for role, spec in graphs(manifest):
        name = f"{manifest['name']}-{role}"
        version = out / name / "1"
        version.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(model_dir / spec["file"], version / "model.onnx")
        for f in external if role.startswith("denoiser") else []:
            shutil.copyfile(model_dir / f, version / f)
        (out / name / "config.pbtxt").write_text(config_text(name, spec, max_batch, queue_delay_us, gpu))
        written.append(name)
    return written


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=pathlib.Path, help="an exported model folder (manifest.json and its ONNX graphs)")
    ap.add_argument("--out", required=True, type=pathlib.Path, help="the repository folder to write")
    ap.add_argument("--max-batch", type=int, default=64)
    ap.add_argument("--queue-delay-us", type=int, default=1000)
    ap.add_argument("--gpu", action="store_true", help="instance_group KIND_GPU (default KIND_CPU)")
    args = ap.parse_args()
    if not (args.model / "manifest.json").is_file():
        sys.exit(f"--model: {args.model / 'manifest.json'} does not exist")
    for name in write(args.model, args.out, args.max_batch, args.queue_delay_us, args.gpu):
        print(f"{args.out / name}")


if __name__ == "__main__":
    main()
