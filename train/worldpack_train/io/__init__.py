"""Floor 2, files: run folders and checkpoints, ONNX graphs written and read back, the manifest. Imports core and metrics."""
