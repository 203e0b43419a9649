//! Where a model's graphs run. [`LocalGraphs`] runs them in this process
//! through ONNX Runtime; a remote inference server can take its place by
//! implementing [`Backend`], and the sampler, packing and prediction above it
//! stay as they are.

use std::path::Path;

use crate::error::ModelError;
use crate::graph::Graph;
use crate::tensor::Tensor;
use crate::manifest::Manifest;
use crate::runtime::RuntimeOptions;

/// Which of a model's graphs a call runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GraphRole<'a> {
    Encoder,
    Decoder,
    /// The denoiser of the named context layout.
    Denoiser(&'a str),
    /// A geometry model's fusion head (manifest `fusion`).
    Fusion,
}

/// Runs a model's graphs on named inputs; outputs in the manifest's order.
pub trait Backend: Send + Sync {
    fn run(&self, role: GraphRole, inputs: &[(&str, &Tensor)]) -> Result<Vec<Tensor>, ModelError>;
    /// The execution provider that runs the denoiser (`cpu`, `cuda`, or a server's name).
    fn provider(&self) -> &str;
    /// Whether the graphs can run now (a remote server answering ready); in-process graphs always can.
    fn ready(&self) -> Result<(), ModelError> {
        Ok(())
    }
    /// The in-process graphs, when this backend has them (the parity tests and `bench step` use them).
    fn local(&self) -> Option<&LocalGraphs> {
        None
    }
}

/// A model's graphs opened in ONNX Runtime in this process.
pub struct LocalGraphs {
    pub encoder: Graph,
    pub decoder: Graph,
    pub denoisers: Vec<(String, Graph)>,
    pub fusion: Option<Graph>,
}

impl LocalGraphs {
    /// Opens every graph the manifest lists and checks each against it.
    pub fn open(dir: &Path, manifest: &Manifest, options: RuntimeOptions) -> Result<LocalGraphs, ModelError> {
        let encoder = Graph::open(dir, &manifest.autoencoder.encoder, options)?;
        let decoder = Graph::open(dir, &manifest.autoencoder.decoder, options)?;
        let denoisers = manifest
            .denoiser
            .layouts
            .iter()
            .map(|l| Ok((l.name.clone(), Graph::open(dir, &l.graph(), options)?)))
            .collect::<Result<Vec<_>, ModelError>>()?;
        let fusion = manifest.fusion.as_ref().map(|spec| Graph::open(dir, spec, options)).transpose()?;
        Ok(LocalGraphs { encoder, decoder, denoisers, fusion })
    }

    pub fn denoiser(&self, layout: &str) -> Result<&Graph, ModelError> {
        self.denoisers.iter().find(|(n, _)| n == layout).map(|(_, g)| g).ok_or_else(|| {
            let known: Vec<&str> = self.denoisers.iter().map(|(n, _)| n.as_str()).collect();
            ModelError::input("layout", format!("this model has no {layout:?} layout; it has {known:?}"))
        })
    }
}

impl Backend for LocalGraphs {
    fn run(&self, role: GraphRole, inputs: &[(&str, &Tensor)]) -> Result<Vec<Tensor>, ModelError> {
        match role {
            GraphRole::Encoder => self.encoder.run(inputs),
            GraphRole::Decoder => self.decoder.run(inputs),
            GraphRole::Denoiser(layout) => self.denoiser(layout)?.run(inputs),
            GraphRole::Fusion => self.fusion.as_ref().ok_or_else(no_fusion)?.run(inputs),
        }
    }

    fn provider(&self) -> &str {
        self.denoisers.first().map_or(self.encoder.provider(), |(_, g)| g.provider())
    }

    fn local(&self) -> Option<&LocalGraphs> {
        Some(self)
    }
}

/// The error for a fusion call to a model without a fusion head.
pub fn no_fusion() -> ModelError {
    ModelError::input("fusion", "this model has no fusion head")
}
