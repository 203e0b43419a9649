//! The model runtime: loads an exported CDiT and its autoencoder (ONNX graphs
//! described by `manifest.json`) into ONNX Runtime, packs memory plans into
//! the denoiser's inputs, and samples in Rust.
//!
//! ONNX Runtime is loaded at run time (`ort`'s `load-dynamic`): from
//! `ORT_DYLIB_PATH`, else from the `onnxruntime` wheel in the repository's
//! `.venv` (see [`runtime::locate_library`]).

pub mod backend;
pub mod error;
pub mod full_size;
pub mod generate;
pub mod graph;
pub mod manifest;
pub mod pack;
pub mod predict;
pub mod runtime;
pub mod sampler;
pub mod tensor;
pub mod warp;

use std::path::{Path, PathBuf};

pub use backend::{Backend, GraphRole, LocalGraphs};
pub use error::ModelError;
pub use graph::Graph;
pub use tensor::Tensor;
pub use manifest::Manifest;
pub use predict::{Predicted, Request};
pub use runtime::{Provider, RuntimeOptions};
pub use sampler::{Method, Sampler};
pub use warp::WarpSource;

/// A loaded model: its folder, manifest, and the backend that runs its graphs.
pub struct Model {
    dir: PathBuf,
    manifest: Manifest,
    backend: Box<dyn Backend>,
    sampled_latents: bool,
    overlay_warp: bool,
}

impl Model {
    /// Reads the manifest, opens every graph in ONNX Runtime and checks each
    /// graph's inputs and outputs against it.
    pub fn load(dir: &Path, options: RuntimeOptions) -> Result<Model, ModelError> {
        let manifest = Manifest::load(dir)?;
        let graphs = LocalGraphs::open(dir, &manifest, options)?;
        Ok(Model::with_backend(dir, manifest, Box::new(graphs)))
    }

    /// A model whose graphs run elsewhere (the manifest still describes them).
    pub fn with_backend(dir: &Path, manifest: Manifest, backend: Box<dyn Backend>) -> Model {
        Model { dir: dir.to_path_buf(), manifest, backend, sampled_latents: false, overlay_warp: false }
    }

    /// With a fusion head: the memory keeps each generated frame's sampled
    /// latent instead of re-encoding the blended frame that is shown, one
    /// encoder call less a step (`serve --sampled-latents`).
    pub fn keep_sampled_latents(&mut self, keep: bool) {
        self.sampled_latents = keep;
    }

    pub fn keeps_sampled_latents(&self) -> bool {
        self.sampled_latents
    }

    /// A geometry model: each frame with warp sources shows their fused warp
    /// wherever it lands, the model's frame only in its holes, and the memory
    /// keeps that frame (`serve --overlay-warp`).
    pub fn overlay_warp(&mut self, on: bool) -> Result<(), ModelError> {
        if on && self.manifest.denoiser.warp.is_none() {
            return Err(ModelError::input("overlay_warp", "only a geometry model (a manifest with denoiser.warp) has a warp to overlay"));
        }
        self.overlay_warp = on;
        Ok(())
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The context policy the weights were trained with: the manifest's
    /// `training.policy` (a [`memory::variant`] name), scoring against the
    /// view its plans were made with. Models exported before plans recorded
    /// their query were all trained with the target-pose query; a manifest
    /// that names no variant gets the paper's WorldPack.
    pub fn trained_policy(&self) -> memory::Policy {
        let paper = || memory::Policy::preset(memory::PolicyKind::WorldPack);
        let Some(training) = self.manifest.training.as_ref() else { return paper() };
        let Ok(variant) = memory::variant(&training.policy) else { return paper() };
        memory::Policy { query: training.plans_query.unwrap_or(memory::Query::Target), ..variant.policy() }
    }

    /// Marks generated context frames with `level` instead of the manifest's
    /// level (to choose it on a validation suite).
    pub fn set_generated_level(&mut self, level: f32) -> Result<(), ModelError> {
        if !(level.is_finite() && level >= 0.0) {
            return Err(ModelError::input("generated_level", format!("must be a finite level ≥ 0, got {level}")));
        }
        match &mut self.manifest.denoiser.context_noise {
            Some(spec) => {
                spec.generated_level = level;
                Ok(())
            }
            None => Err(ModelError::input("generated_level", format!("model {} takes no context noise levels", self.dir.display()))),
        }
    }

    /// The execution provider that runs the denoiser.
    /// Whether the model's graphs can run now ([`Backend::ready`]).
    pub fn ready(&self) -> Result<(), ModelError> {
        self.backend.ready()
    }

    pub fn provider(&self) -> &str {
        self.backend.provider()
    }

    /// The graphs in this process, for callers that time or check one graph
    /// alone; an error when the backend is remote.
    pub fn local(&self) -> Result<&LocalGraphs, ModelError> {
        self.backend.local().ok_or_else(|| ModelError::input("backend", "this model's graphs do not run in this process"))
    }

    /// Runs one graph through the backend.
    pub fn run(&self, role: GraphRole, inputs: &[(&str, &Tensor)]) -> Result<Vec<Tensor>, ModelError> {
        self.backend.run(role, inputs)
    }

    /// Images (B, 3, H, W) in [-1, 1] to scaled latents (B, C, h, w).
    pub fn encode(&self, images: &Tensor) -> Result<Tensor, ModelError> {
        let name = &self.manifest.autoencoder.encoder.inputs[0].name;
        let mut out = self.run(GraphRole::Encoder, &[(name.as_str(), images)])?.remove(0);
        let scale = self.manifest.autoencoder.latent_scale as f32;
        out.data.iter_mut().for_each(|v| *v *= scale);
        Ok(out)
    }

    /// Scaled latents (B, C, h, w) to images (B, 3, H, W), nominally [-1, 1].
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor, ModelError> {
        let scale = self.manifest.autoencoder.latent_scale as f32;
        let raw = Tensor::new(latents.shape.clone(), latents.data.iter().map(|v| v / scale).collect());
        let name = &self.manifest.autoencoder.decoder.inputs[0].name;
        Ok(self.run(GraphRole::Decoder, &[(name.as_str(), &raw)])?.remove(0))
    }
}
