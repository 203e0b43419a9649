//! The model runtime: loads an exported CDiT and its autoencoder (ONNX graphs
//! described by `manifest.json`) into ONNX Runtime, packs memory plans into
//! the denoiser's inputs, and samples in Rust.
//!
//! ONNX Runtime is loaded at run time (`ort`'s `load-dynamic`): from
//! `ORT_DYLIB_PATH`, else from the `onnxruntime` wheel in the repository's
//! `.venv` (see [`runtime::locate_library`]).

pub mod error;
pub mod generate;
pub mod graph;
pub mod manifest;
pub mod pack;
pub mod runtime;
pub mod sampler;

use std::path::{Path, PathBuf};

pub use error::ModelError;
pub use graph::{Graph, Tensor};
pub use manifest::Manifest;
pub use runtime::{Provider, RuntimeOptions};
pub use sampler::{Method, Sampler};

/// A loaded model folder: manifest, autoencoder and one denoiser per layout.
pub struct Model {
    dir: PathBuf,
    manifest: Manifest,
    encoder: Graph,
    decoder: Graph,
    denoisers: Vec<(String, Graph)>,
}

impl Model {
    /// Reads the manifest, opens every graph and checks each graph's inputs
    /// and outputs against it.
    pub fn load(dir: &Path, options: RuntimeOptions) -> Result<Model, ModelError> {
        let manifest = Manifest::load(dir)?;
        let encoder = Graph::open(dir, &manifest.autoencoder.encoder, options)?;
        let decoder = Graph::open(dir, &manifest.autoencoder.decoder, options)?;
        let denoisers = manifest
            .denoiser
            .layouts
            .iter()
            .map(|l| Ok((l.name.clone(), Graph::open(dir, &l.graph(), options)?)))
            .collect::<Result<Vec<_>, ModelError>>()?;
        Ok(Model { dir: dir.to_path_buf(), manifest, encoder, decoder, denoisers })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The execution provider that runs the denoiser.
    pub fn provider(&self) -> &'static str {
        self.denoisers.first().map_or(self.encoder.provider(), |(_, g)| g.provider())
    }

    pub fn encoder(&self) -> &Graph {
        &self.encoder
    }

    pub fn decoder(&self) -> &Graph {
        &self.decoder
    }

    pub fn denoiser(&self, layout: &str) -> Result<&Graph, ModelError> {
        self.denoisers.iter().find(|(n, _)| n == layout).map(|(_, g)| g).ok_or_else(|| {
            let known: Vec<&str> = self.denoisers.iter().map(|(n, _)| n.as_str()).collect();
            ModelError::input("layout", format!("this model has no {layout:?} layout; it has {known:?}"))
        })
    }

    /// Images (B, 3, H, W) in [-1, 1] to scaled latents (B, C, h, w).
    pub fn encode(&self, images: &Tensor) -> Result<Tensor, ModelError> {
        let name = &self.manifest.autoencoder.encoder.inputs[0].name;
        let mut out = self.encoder.run(&[(name.as_str(), images)])?.remove(0);
        let scale = self.manifest.autoencoder.latent_scale as f32;
        out.data.iter_mut().for_each(|v| *v *= scale);
        Ok(out)
    }

    /// Scaled latents (B, C, h, w) to images (B, 3, H, W), nominally [-1, 1].
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor, ModelError> {
        let scale = self.manifest.autoencoder.latent_scale as f32;
        let raw = Tensor::new(latents.shape.clone(), latents.data.iter().map(|v| v / scale).collect());
        let name = &self.manifest.autoencoder.decoder.inputs[0].name;
        Ok(self.decoder.run(&[(name.as_str(), &raw)])?.remove(0))
    }
}
