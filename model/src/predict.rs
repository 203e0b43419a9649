//! The one prediction path: memory plans in, next frames out. Packing each
//! plan into its layout's slots, the action and time tensors, sampling with a
//! seed per item and decoding all happen here, so the server's step, the
//! probe and the rollouts predict a frame the same way.

use std::time::Instant;

use memory::{ContextPlan, Packing, Pose};

use crate::error::ModelError;
use crate::generate::{Conditioning, tensor_to_frame};
use crate::tensor::Tensor;
use crate::manifest::LayoutSpec;
use crate::pack::{ContextFrame, pack, stack};
use crate::sampler::Sampler;
use crate::manifest::FUSION_INPUTS;
use crate::warp::{Landings, REFERENCE_MARGIN, WarpSource, Warped, coverage_grid, stands_at, warped_image};
use crate::{GraphRole, Model};

/// Interleaved RGB bytes as (3, n) planar values in [-1, 1].
fn planar(rgb: &[u8], n: usize) -> impl Iterator<Item = f32> + '_ {
    (0..3).flat_map(move |c| (0..n).map(move |p| rgb[3 * p + c] as f32 / 127.5 - 1.0))
}

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
    /// The stored frames with depth, best first, that a geometry model warps
    /// into the target view behind one z-buffer (empty: none at hand, and the
    /// model gets an empty warp, as in training). Models without the warp
    /// input ignore them.
    pub warp: &'a [WarpSource<'a>],
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
    /// Warping and encoding the geometry model's warp input, and with a
    /// fusion head its reference warp (0 without a warp input).
    pub warp_ms: f64,
    pub sample_ms: f64,
    /// Decoding, and with a fusion head its blend and the re-encoding of the
    /// blended frames.
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
        self.predict_with(packing, requests, frame, sampler, true)
    }

    /// As [`Model::predict`], but stops at the sampled latents: nothing is
    /// decoded, fused or re-encoded, and each frame's `rgb` is empty. For a
    /// frame nobody looks at and nothing reads again (an imagined rollout's
    /// last step scored in latent space); its latent is the sampler's, not the
    /// re-encoded frame a step's memory keeps.
    pub fn predict_latents<'a>(
        &self,
        packing: &Packing,
        requests: &[Request],
        frame: &dyn Fn(usize, u64) -> Option<ContextFrame<'a>>,
        sampler: &Sampler,
    ) -> Result<Prediction, ModelError> {
        self.predict_with(packing, requests, frame, sampler, false)
    }

    fn predict_with<'a>(
        &self,
        packing: &Packing,
        requests: &[Request],
        frame: &dyn Fn(usize, u64) -> Option<ContextFrame<'a>>,
        sampler: &Sampler,
        decode: bool,
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
        let mut context = stack(&contexts);
        // Each request's sources are projected into its target once: the warp
        // input resolves them plainly, a fusion head's reference by margin.
        let mut references = Vec::new();
        let warp_ms = match &manifest.denoiser.warp {
            Some(spec) => {
                let started = Instant::now();
                let mut warps = Vec::with_capacity(requests.len());
                for r in requests {
                    let landings = self.landings_of(r.warp, r.target_pose)?;
                    warps.push(landings.as_ref().map(|l| l.resolve(0.0)));
                    // warp::fused_reference, from the same projection.
                    references.push(landings.filter(|_| manifest.fusion.is_some()).map(|l| l.resolve(REFERENCE_MARGIN).into_reference(&r.warp[0])));
                }
                context.push((spec.input.clone(), self.encode_warps(&warps)?));
                started.elapsed().as_secs_f64() * 1e3
            }
            None => 0.0,
        };
        let action = Tensor::new(vec![requests.len(), width], actions);
        let rel_time = Tensor::new(vec![requests.len()], packed.iter().map(|p| p.rel_time).collect());
        let seeds: Vec<u64> = requests.iter().map(|r| r.seed).collect();
        let started = Instant::now();
        let cond = Conditioning { context: &context, action: &action, rel_time: &rel_time };
        let latent = self.sample(&layout.name, &cond, sampler, &seeds)?;
        let sample_ms = started.elapsed().as_secs_f64() * 1e3;
        let per = latent.data.len() / requests.len();
        if !decode {
            let frames = (0..requests.len()).map(|j| Predicted { latent: latent.data[j * per..(j + 1) * per].to_vec(), rgb: Vec::new() }).collect();
            return Ok(Prediction { frames, layout: layout.name.clone(), warp_ms, sample_ms, decode_ms: 0.0 });
        }
        let started = Instant::now();
        let mut images = self.decode(&latent)?;
        let mut latent = latent;
        let fused: Vec<usize> = (0..references.len()).filter(|&j| references[j].is_some()).collect();
        if !fused.is_empty() {
            let (shown, kept) = self.fuse(images, requests, &references, &fused)?;
            images = shown;
            // With the warp overlaid (below) the memory keeps that frame instead, encoded there.
            if !self.sampled_latents && !self.overlay_warp {
                // The memory keeps the frame shown (or the one the head names for it): the
                // blended ones re-encoded, the others as sampled.
                let kept = kept.as_ref().unwrap_or(&images);
                let n = kept.data.len() / requests.len();
                let blended = Tensor::new(
                    [vec![fused.len()], kept.shape[1..].to_vec()].concat(),
                    fused.iter().flat_map(|&j| kept.data[j * n..(j + 1) * n].iter().copied()).collect(),
                );
                let encoded = self.encode(&blended)?;
                for (i, &j) in fused.iter().enumerate() {
                    latent.data[j * per..(j + 1) * per].copy_from_slice(&encoded.data[i * per..(i + 1) * per]);
                }
            }
        }
        if self.overlay_warp {
            self.overlay_warps(&mut images, &mut latent, requests)?;
        }
        let frames = (0..requests.len())
            .map(|j| Ok(Predicted { latent: latent.data[j * per..(j + 1) * per].to_vec(), rgb: tensor_to_frame(&images, j)? }))
            .collect::<Result<Vec<_>, ModelError>>()?;
        Ok(Prediction { frames, layout: layout.name.clone(), warp_ms, sample_ms, decode_ms: started.elapsed().as_secs_f64() * 1e3 })
    }

    /// [`Model::overlay_warp`]: each request with warp sources shows their fused
    /// warp wherever it lands, and its latent becomes that frame's, re-encoded.
    fn overlay_warps(&self, images: &mut Tensor, latent: &mut Tensor, requests: &[Request]) -> Result<(), ModelError> {
        let with: Vec<usize> = (0..requests.len()).filter(|&j| !requests[j].warp.is_empty()).collect();
        if with.is_empty() {
            return Ok(());
        }
        let n = images.data.len() / requests.len();
        let plane = n / 3;
        let mut shown = Vec::with_capacity(with.len() * n);
        for &j in &with {
            let rgb = crate::warp::fused_warp(requests[j].warp, requests[j].target_pose)?.overlay(tensor_to_frame(images, j)?);
            // The frame as the encoder would take it from bytes (frame_to_tensor's scale).
            let frame: Vec<f32> = (0..n).map(|i| (rgb[(i % plane) * 3 + i / plane] as f64 / 127.5 - 1.0) as f32).collect();
            images.data[j * n..(j + 1) * n].copy_from_slice(&frame);
            shown.extend(frame);
        }
        let encoded = self.encode(&Tensor::new([vec![with.len()], images.shape[1..].to_vec()].concat(), shown))?;
        let per = latent.data.len() / requests.len();
        for (i, &j) in with.iter().enumerate() {
            latent.data[j * per..(j + 1) * per].copy_from_slice(&encoded.data[i * per..(i + 1) * per]);
        }
        Ok(())
    }

    /// The fusion head over a batch of decoded `images`: each request's
    /// decoded frame blended with the fused reference of its warp sources
    /// (`warp::fused_reference`). A request without sources keeps its
    /// decoded frame (it has no reference; the head is not asked), and one
    /// whose best source stands at its target's pose shows that source
    /// (`warp::stands_at`: a static world seen again from where it was
    /// observed). `with` lists the requests that have sources. Returns the
    /// frames shown and, from a head with a second output, the frames the
    /// memory keeps instead (a head pair's second head). `references` holds
    /// each request's fused reference and where its warp landed.
    fn fuse(&self, images: Tensor, requests: &[Request], references: &[Option<(Vec<u8>, Vec<bool>)>], with: &[usize]) -> Result<(Tensor, Option<Tensor>), ModelError> {
        let (w, h) = (self.manifest().image.width, self.manifest().image.height);
        let n = w * h;
        let mut out = images;
        let (mut blend, mut predicted, mut reference, mut landed) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for &j in with {
            let best = &requests[j].warp[0];
            if stands_at(best.pose, requests[j].target_pose) {
                for (o, v) in out.data[j * 3 * n..(j + 1) * 3 * n].iter_mut().zip(planar(best.rgb, n)) {
                    *o = v;
                }
                continue;
            }
            let Some((rgb, mask)) = &references[j] else { continue };
            // Clamped, as the frames the head was trained on were.
            predicted.extend(out.data[j * 3 * n..(j + 1) * 3 * n].iter().map(|v| v.clamp(-1.0, 1.0)));
            reference.extend(planar(rgb, n));
            landed.extend(mask.iter().map(|&m| m as u8 as f32));
            blend.push(j);
        }
        if blend.is_empty() {
            return Ok((out, None));
        }
        let b = blend.len();
        let predicted = Tensor::new(vec![b, 3, h, w], predicted);
        let reference = Tensor::new(vec![b, 3, h, w], reference);
        let landed = Tensor::new(vec![b, 1, h, w], landed);
        let [p, r, l] = FUSION_INPUTS;
        let mut outputs = self.run(GraphRole::Fusion, &[(p, &predicted), (r, &reference), (l, &landed)])?.into_iter();
        let place = |into: &mut Tensor, from: &Tensor| {
            for (i, &j) in blend.iter().enumerate() {
                for (o, v) in into.data[j * 3 * n..(j + 1) * 3 * n].iter_mut().zip(&from.data[i * 3 * n..(i + 1) * 3 * n]) {
                    *o = v.clamp(-1.0, 1.0);
                }
            }
        };
        let shown = outputs.next().ok_or_else(|| ModelError::input("fusion", "the head returned nothing"))?;
        // A head with a second output names the frame the memory keeps.
        let kept = outputs.next().map(|k| {
            let mut kept = out.clone();
            place(&mut kept, &k);
            kept
        });
        place(&mut out, &shown);
        Ok((out, kept))
    }

    /// The geometry model's warp input for a batch, (B, C + 1, h, w): each
    /// item's source warped into its target pose and encoded, then the share
    /// of each latent cell the warp covers. No source: an empty warp.
    pub fn warp_input(&self, items: &[(&[WarpSource], &Pose)]) -> Result<Tensor, ModelError> {
        let warps = items.iter().map(|(source, target)| Ok(self.landings_of(source, target)?.map(|l| l.resolve(0.0)))).collect::<Result<Vec<_>, ModelError>>()?;
        self.encode_warps(&warps)
    }

    /// `source` projected into `target`; `None` without a source.
    fn landings_of(&self, source: &[WarpSource], target: &Pose) -> Result<Option<Landings>, ModelError> {
        let Some(src) = source.first() else { return Ok(None) };
        let (w, h) = (self.manifest().image.width, self.manifest().image.height);
        let k = src.intrinsics;
        if (k.width as usize, k.height as usize) != (w, h) {
            return Err(ModelError::input("warp", format!("the source frame is {}x{}, the model takes {w}x{h}", k.width, k.height)));
        }
        Ok(Some(Landings::of(source, target)?))
    }

    /// The warp input of [`Model::warp_input`] from warps already made.
    fn encode_warps(&self, warps: &[Option<Warped>]) -> Result<Tensor, ModelError> {
        let m = self.manifest();
        let (w, h) = (m.image.width, m.image.height);
        let l = &m.autoencoder.latent;
        let cells = l.height * l.width;
        let mut images = Vec::with_capacity(warps.len() * 3 * w * h);
        let mut cover = Vec::with_capacity(warps.len());
        for warped in warps {
            if let Some(warped) = warped {
                images.extend(warped_image(warped));
                cover.push(coverage_grid(&warped.mask, w, h, h / l.height));
            } else {
                images.extend(std::iter::repeat_n(0.0, 3 * w * h));
                cover.push(vec![0.0; cells]);
            }
        }
        let latents = self.encode(&Tensor::new(vec![warps.len(), 3, h, w], images))?;
        let per = l.len();
        let mut data = Vec::with_capacity(warps.len() * (per + cells));
        for (j, c) in cover.iter().enumerate() {
            data.extend_from_slice(&latents.data[j * per..(j + 1) * per]);
            data.extend_from_slice(c);
        }
        Ok(Tensor::new(vec![warps.len(), l.channels + 1, l.height, l.width], data))
    }
}
