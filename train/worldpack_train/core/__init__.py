"""Floor 1, the model: configuration, autoencoder, CDiT, diffusion, the warp, the recipe, losses, the data reader. Imports only the standard library, numpy, torch and itself."""
