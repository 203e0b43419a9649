"""Host a WorldPack model folder's graphs on Triton Inference Server.

Starts PyPI's `tritonserver` (through pytriton) with one Triton model per
graph, named as `worldpack serve --model-backend triton://HOST:PORT` expects:
`<name>-encoder`, `<name>-decoder`, `<name>-denoiser-<layout>` (the manifest's
name and layouts). Each runs the exported ONNX graph in ONNX Runtime behind
Triton's dynamic batcher, so concurrent calls from any number of WorldPack
replicas are gathered into one batched call.

    .venv-triton/bin/python serving/triton/host.py --model fixtures/small --http-port 8000

For GPU deployments `repository.py` writes the same models as a model
repository for Triton's own onnxruntime backend (docs/deployment.md).
"""

import argparse
import json
import logging
import os
import pathlib
import signal
import sys

import numpy as np
import onnxruntime as ort
from pytriton.decorators import batch
from pytriton.model_config import DynamicBatcher, ModelConfig, Tensor
from pytriton.triton import Triton, TritonConfig

from repository import graphs  # one naming of the graphs for both ways of serving

# PyTriton's loggers that tell its start model by model (not its server module, whose DEBUG
# prints the whole environment).
START_LOGGERS = ("pytriton.triton", "pytriton.models.manager", "pytriton.client.utils")


def item_dims(spec):
    """A tensor's shape without its batch axis; a tensor that is only the
    batch axis (the timestep) travels as (batch, 1), since Triton needs an
    axis besides the batch one (the client sends it so, see triton/src/lib.rs)."""
    if spec["dtype"] != "float32" or not spec["shape"] or spec["shape"][0] != "batch":
        sys.exit(f"{spec['name']}: only float32 tensors with a leading batch axis can be batched, got {spec['shape']}")
    return tuple(d if isinstance(d, int) else -1 for d in spec["shape"][1:]) or (1,)


def tensors(specs):
    return [Tensor(name=spec["name"], dtype=np.float32, shape=item_dims(spec)) for spec in specs]


def infer_function(session, spec):
    ranks = {i["name"]: len(i["shape"]) for i in spec["inputs"]}
    outputs = spec["outputs"]

    @batch
    def infer(**inputs):
        feed = {name: np.ascontiguousarray(value.reshape(value.shape[:ranks[name]]) if ranks[name] == 1 else value, dtype=np.float32)
                for name, value in inputs.items()}
        results = session.run([o["name"] for o in outputs], feed)
        return {o["name"]: r.reshape(-1, 1) if len(o["shape"]) == 1 else r for o, r in zip(outputs, results)}

    return infer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=pathlib.Path, help="an exported model folder (manifest.json and its ONNX graphs)")
    ap.add_argument("--http-port", type=int, default=8000)
    ap.add_argument("--grpc-port", type=int, default=8001)
    ap.add_argument("--metrics-port", type=int, default=8002)
    ap.add_argument("--max-batch", type=int, default=64, help="largest batch Triton gathers (default 64)")
    ap.add_argument("--queue-delay-us", type=int, default=1000, help="how long Triton waits to fill a batch (default 1000 µs)")
    ap.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads per graph (default 1)")
    ap.add_argument("--gpu", action="store_true", help="run the graphs with the CUDA provider")
    ap.add_argument("--exit-timeout-secs", type=int, default=30,
                    help="on SIGTERM, how long Triton waits for calls in flight before it stops (default 30, as Triton's)")
    args = ap.parse_args()
    # stdout carries one line, "serving ...", that a caller waits for. tritonserver inherits
    # fd 1 and writes its log there in buffered blocks that can split that line, so its log
    # goes to stderr and the line to a copy of the original stdout.
    announce = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    # The start on stderr, step by step: a start that hangs leaves a trail.
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    for name in START_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG)
    # SIGTERM unwinds `with Triton(...)`, which stops tritonserver and removes its workspace
    # (a copy of the server's binaries), and then main's sweep of this process's shared
    # memory; a kill leaves both behind.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))

    manifest_path = args.model / "manifest.json"
    if not manifest_path.is_file():
        sys.exit(f"--model: {manifest_path} does not exist")
    manifest = json.loads(manifest_path.read_text())
    options = ort.SessionOptions()
    options.intra_op_num_threads = args.threads
    options.inter_op_num_threads = 1
    providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if args.gpu else ["CPUExecutionProvider"]

    config = TritonConfig(http_port=args.http_port, grpc_port=args.grpc_port, metrics_port=args.metrics_port,
                          http_address="127.0.0.1", grpc_address="127.0.0.1",
                          exit_timeout_secs=args.exit_timeout_secs)
    try:
        serve(args, manifest, options, providers, config, announce)
    finally:
        # pytriton leaves the shared memory it made for the calls' tensors (/dev/shm/pytrtion<pid>-*)
        # when it stops; tritonserver has stopped by now, so nothing else can be using them.
        for segment in pathlib.Path("/dev/shm").glob(f"pytrtion{os.getpid()}-*"):
            segment.unlink(missing_ok=True)


def serve(args, manifest, options, providers, config, announce):
    """Binds every graph of the model as a Triton model and serves until SIGTERM."""
    with Triton(config=config) as triton:
        for role, spec in graphs(manifest):
            session = ort.InferenceSession(str(args.model / spec["file"]), options, providers=providers)
            triton.bind(
                model_name=f"{manifest['name']}-{role}",
                infer_func=infer_function(session, spec),
                inputs=tensors(spec["inputs"]),
                outputs=tensors(spec["outputs"]),
                config=ModelConfig(max_batch_size=args.max_batch,
                                   batcher=DynamicBatcher(max_queue_delay_microseconds=args.queue_delay_us)),
                strict=True,
            )
        print(f"serving {manifest['name']} on http://127.0.0.1:{args.http_port} (metrics on :{args.metrics_port})", file=announce, flush=True)
        for name in START_LOGGERS:
            logging.getLogger(name).setLevel(logging.INFO)
        triton.serve()


if __name__ == "__main__":
    main()
