"""WorldPack's trainer: a dataset folder to a served model folder.

Laid out by floors, each importing only those below it (tests/test_trainer_layering.py):
  metrics      PSNR and the sharpness ratio in numpy (torch-free; pinned to eval::metrics)
  core/        the model: config, autoencoder, CDiT, diffusion, warp, recipe, losses, data
  io/          files: checkpoints, ONNX graphs written and read back, the manifest
  stages/      one module per stage of the recipe
  settings, card, pipeline, __main__   the product: `worldpack train` (docs/training.md)
"""
