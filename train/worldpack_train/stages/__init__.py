"""Floor 3, the stages: each trains or writes one part of a model (autoencoder, denoiser, student, heads, decoder, export, recovery). Imports io, core and metrics; a stage may use an earlier one."""
