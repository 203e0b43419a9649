//! The one prediction path: memory plans in, next frames out. Packing each
//! plan into its layout's slots, the action and time tensors, sampling with a
//! seed per item and decoding all happen here, so the server's step, the
//! probe and the rollouts predict a frame the same way.

use std::time::Instant;

use memory::{ContextPlan, Packing, Pose};

use crate::error::ModelError;
use crate::generate::{Conditioning, tensor_to_frame};
use crate::graph::Tensor;
use crate::manifest::LayoutSpec;
use crate::pack::{ContextFrame, pack, stack};
use crate::sampler::Sampler;
use crate::Model;

/// One next frame to predict.
#[derive(Clone, Copy, Debug)]
pub struct Request<'a> {
    /// The frames to condition on, in the policy's slot order.
    pub plan: &'a ContextPlan,
    pub target_time: u64,
    pub target_pose: &'a Pose,
    /// The action leading to the target, raw units, as wide as the manifest's `action.dim`.
    pub action: &'a [f32],
    /// Seeds this item's noise alone: the same seed gives the same frame in any batch.
    pub seed: u64,
}

/// A predicted frame: its scaled latent (for the memory) and its RGB pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Predicted {
    pub latent: Vec<f32>,
    pub rgb: Vec<u8>,
}

/// A batch's frames, in request order, and where the time went.
#[derive(Clone, Debug)]
pub struct Prediction {
    pub frames: Vec<Predicted>,
    pub layout: String,
    pub sample_ms: f64,
    pub decode_ms: f64,
}

impl Model {
    /// The denoiser layout whose slots are `packing`'s tiers, rate and count in order.
    pub fn layout_for(&self, packing: &Packing) -> Result<&LayoutSpec, ModelError> {
        self.manifest().layout_for_packing(packing).ok_or_else(|| {
            let want: Vec<(u32, usize)> = packing.tiers().iter().map(|t| (t.rate, t.slots)).collect();
            let have: Vec<String> = self
                .manifest()
                .denoiser
                .layouts
                .iter()
                .map(|l| format!("{} {:?}", l.name, l.slots.iter().map(|s| (s.rate, s.count)).collect::<Vec<_>>()))
                .collect();
            ModelError::input("policy", format!("model {} has no context layout with slots {want:?} (rate, count); it has {}", self.dir().display(), have.join(", ")))
        })
    }

    /// Predicts one next frame per request, all in one batch. `frame(i, id)`
    /// looks up stored frame `id` for request `i` (requests may come from
    /// different sessions or trajectories).
    pub fn predict<'a>(
        &self,
        packing: &Packing,
        requests: &[Request],
        frame: &dyn Fn(usize, u64) -> Option<ContextFrame<'a>>,
        sampler: &Sampler,
    ) -> Result<Prediction, ModelError> {
        let layout = self.layout_for(packing)?;
        let manifest = self.manifest();
        let width = manifest.action.dim;
        if requests.is_empty() {
            return Err(ModelError::input("requests", "nothing to predict"));
        }
        let mut packed = Vec::with_capacity(requests.len());
        let mut actions = Vec::with_capacity(requests.len() * width);
        for (i, r) in requests.iter().enumerate() {
            if r.action.len() != width {
                return Err(ModelError::input("action", format!("the model takes {width} action values, got {}", r.action.len())));
            }
            actions.extend_from_slice(r.action);
            let noise = manifest.denoiser.context_noise.as_ref();
            packed.push(pack(layout, &manifest.autoencoder.latent, noise, r.plan, r.target_time, r.target_pose, |id| frame(i, id))?);
        }
        let contexts: Vec<&[(String, Tensor)]> = packed.iter().map(|p| p.tensors.as_slice()).collect();
        let context = stack(&contexts);
        let action = Tensor::new(vec![requests.len(), width], actions);
        let rel_time = Tensor::new(vec![requests.len()], packed.iter().map(|p| p.rel_time).collect());
        let seeds: Vec<u64> = requests.iter().map(|r| r.seed).collect();
        let started = Instant::now();
        let cond = Conditioning { context: &context, action: &action, rel_time: &rel_time };
        let latent = self.sample(&layout.name, &cond, sampler, &seeds)?;
        let sample_ms = started.elapsed().as_secs_f64() * 1e3;
        let started = Instant::now();
        let images = self.decode(&latent)?;
        let per = latent.data.len() / requests.len();
        let frames = (0..requests.len())
            .map(|j| Ok(Predicted { latent: latent.data[j * per..(j + 1) * per].to_vec(), rgb: tensor_to_frame(&images, j)? }))
            .collect::<Result<Vec<_>, ModelError>>()?;
        Ok(Prediction { frames, layout: layout.name.clone(), sample_ms, decode_ms: started.elapsed().as_secs_f64() * 1e3 })
    }
}
