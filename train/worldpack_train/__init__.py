"""WorldPack's model side in PyTorch: the autoencoder, the CDiT with one input
projection per compression rate, DDPM training, and the ONNX export the Rust
runtime serves. See docs/model.md."""
