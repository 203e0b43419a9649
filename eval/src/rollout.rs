//! Autoregressive rollouts (the LoopNav protocol): every trajectory's
//! exploration is observed as ground truth, then the return leg is generated
//! frame by frame from the known poses and actions, each generated frame
//! joining the memory that later frames select from. Trajectories run in
//! lockstep so one denoiser call serves a whole batch of them.

use std::cell::RefCell;
use std::collections::HashMap;

use memory::covisibility::DepthGrid;
use memory::{ContextPlan, FrameMemory, Frustum, MemoryFrame, Policy};
use model::full_size::FullSize;
use model::warp::{self, fused_reference, stands_at};
use model::pack::ContextFrame;
use model::{Model, Request, Sampler, WarpSource};

use crate::features::{Embedding, FeatureError, Lpips, VideoFeatures, frechet_distance};
use crate::probe::{FUSED_FRAMES, FrameScore, FusionExamples, Predictor, ProbeError, Row, encode_frames, fused_warp, reference_image, warp_sources};
use crate::suite::Trajectory;

/// The frames a rollout generates: the return leg, from the returning point,
/// at most `max_frames` of it.
pub fn rollout_frames(traj: &Trajectory, max_frames: Option<usize>) -> std::ops::Range<usize> {
    let start = traj.entry.returning_point.clamp(1, traj.len());
    let end = max_frames.map_or(traj.len(), |m| (start + m).min(traj.len()));
    start..end
}

fn observed(frusta: &[Frustum], upto: usize) -> Result<FrameMemory, ProbeError> {
    let mut store = FrameMemory::new();
    for (t, f) in frusta.iter().enumerate().take(upto) {
        store.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: f.clone() }).map_err(|e| ProbeError::Invalid(e.to_string()))?;
    }
    Ok(store)
}

/// The observed frames among `plan`'s: all a row without retrieval may warp.
fn within_plan(observed: &FrameMemory, plan: &ContextPlan) -> Result<FrameMemory, ProbeError> {
    let mut store = FrameMemory::new();
    for frame in plan.selected().filter_map(|(_, f)| observed.get(f.id)) {
        store.insert(frame.clone()).map_err(|e| ProbeError::Invalid(e.to_string()))?;
    }
    Ok(store)
}

/// Frames `0..upto` of `traj`, their depth pooled to `cells` columns (metres).
fn exploration_depth(traj: &Trajectory, upto: usize, cells: u32) -> Result<HashMap<u64, DepthGrid>, ProbeError> {
    (0..upto)
        .map(|t| {
            let grid = warp::coarse_depth(traj.depth(t), &traj.intrinsics, cells).map_err(|e| ProbeError::Invalid(e.to_string()))?;
            Ok((t as u64, grid))
        })
        .collect()
}

struct Run<'a> {
    traj: &'a Trajectory,
    /// `traj` at the model's frame size when the suite's is another: the
    /// frames the model is given (warp sources), as a server resamples a
    /// session's; its frames are then shown at the suite's size (`model::full_size`).
    small: Option<Trajectory>,
    /// Co-visible rows: the exploration's coarse depth, by frame.
    depth: HashMap<u64, DepthGrid>,
    frusta: Vec<Frustum>,
    store: FrameMemory,
    /// The exploration alone: where a geometry model's warp sources come from.
    observed: FrameMemory,
    latents: Vec<Vec<f32>>,
    previous: Option<ContextPlan>,
    /// The first generated frame (the return leg's start): the frames before it are observed.
    start: usize,
    next: usize,
    end: usize,
    scores: Vec<FrameScore>,
    frames: Vec<Vec<u8>>,
    /// [`landed_masks`] of `start..end`.
    landed: LandedMasks,
}

/// How generated frames are scored, and whether they are kept (for FVD).
pub struct Scorer<'a> {
    pub lpips: Option<&'a Lpips>,
    pub dreamsim: Option<&'a Embedding>,
    pub keep_frames: bool,
    /// Fusion-head training examples taken on the way (`worldpack fusion-data --rollout-with`).
    pub capture: Option<&'a Capture<'a>>,
    /// [`landed_masks`] by trajectory and frame range: the same for every row,
    /// so made once for all the rows this scorer scores.
    pub landed: RefCell<HashMap<(String, usize, usize), LandedMasks>>,
    /// The best-overlap observed frames whose fused warp makes the holes mask
    /// (and a composite row's overlay).
    pub probe_frames: usize,
    /// On a suite larger than the model's frames: replaces the model's own
    /// full-size rule's agreement (luma levels) and frame count where given.
    pub full_size: (Option<f64>, Option<usize>),
}

impl Default for Scorer<'_> {
    fn default() -> Self {
        Scorer { lpips: None, dreamsim: None, keep_frames: false, capture: None, landed: Default::default(), probe_frames: FUSED_FRAMES, full_size: (None, None) }
    }
}

/// One trajectory's [`landed_masks`], shared by the rows that score it.
pub type LandedMasks = std::rc::Rc<Vec<Vec<bool>>>;

/// Fusion-head examples from a fused model's rollouts, as the head meets
/// them in use: the frame it was given (the same request through `bare`, the
/// model without the head, whose denoiser is the same), the fused reference,
/// where the warp landed, and the truth. Every `stride`-th frame of a return
/// leg; none where the head is not asked (no warp source, or the best source
/// stands at the target's pose).
pub struct Capture<'a> {
    pub bare: &'a Model,
    pub stride: usize,
    pub examples: RefCell<FusionExamples>,
}

impl Capture<'_> {
    fn take<'f>(
        &self,
        requests: &[Request],
        frame: &dyn Fn(usize, u64) -> Option<ContextFrame<'f>>,
        packing: &memory::Packing,
        sampler: &Sampler,
        leg: impl Fn(usize) -> (usize, &'f [u8]),
    ) -> Result<(), ProbeError> {
        let wanted: Vec<usize> = (0..requests.len())
            .filter(|&j| {
                let r = &requests[j];
                leg(j).0.is_multiple_of(self.stride.max(1)) && r.warp.first().is_some_and(|best| !stands_at(best.pose, r.target_pose))
            })
            .collect();
        if wanted.is_empty() {
            return Ok(());
        }
        let subset: Vec<Request> = wanted.iter().map(|&j| requests[j]).collect();
        let bare = self.bare.predict(packing, &subset, &|i, id| frame(wanted[i], id), sampler)?;
        let mut out = self.examples.borrow_mut();
        for ((&j, r), p) in wanted.iter().zip(&subset).zip(bare.frames) {
            let (reference, mask) = fused_reference(r.warp, r.target_pose)?;
            out.predicted.extend(&p.rgb);
            out.reference.extend(reference);
            out.mask.extend(mask.iter().map(|&m| m as u8));
            out.truth.extend(leg(j).1);
            out.count += 1;
        }
        Ok(())
    }
}

/// Where the fused warp of the `probe_frames` best observed frames lands in
/// each frame of `frames` (the probe's validity mask). It depends on the
/// exploration alone, so every row is scored over the same holes and the
/// holes measure pairs.
fn landed_masks(traj: &Trajectory, frames: std::ops::Range<usize>, probe_frames: usize) -> Result<Vec<Vec<bool>>, ProbeError> {
    let frusta = traj.frusta()?;
    let store = observed(&frusta, frames.start)?;
    let policy = Policy::best_overlap_frames(probe_frames);
    Ok(frames.map(|t| fused_warp(traj, &store.select(&policy, &frusta[t], None).0, t).mask).collect())
}

impl Scorer<'_> {
    /// `traj`'s [`landed_masks`] over `frames`, made on first use.
    fn landed(&self, traj: &Trajectory, frames: std::ops::Range<usize>) -> Result<LandedMasks, ProbeError> {
        let key = (traj.entry.dir.clone(), frames.start, frames.end);
        if let Some(masks) = self.landed.borrow().get(&key) {
            return Ok(masks.clone());
        }
        let masks = std::rc::Rc::new(landed_masks(traj, frames, self.probe_frames)?);
        self.landed.borrow_mut().insert(key, masks.clone());
        Ok(masks)
    }

    /// Scores frame `t` of `traj`; `landed` is its [`landed_masks`] entry,
    /// for the PSNR and sharpness in and out of the warp.
    fn score(&self, traj: &Trajectory, t: usize, predicted: &[u8], landed: &[bool]) -> Result<FrameScore, ProbeError> {
        let (w, h) = (traj.intrinsics.width as usize, traj.intrinsics.height as usize);
        let truth = traj.frame(t);
        let feature = |e: FeatureError| ProbeError::Invalid(e.to_string());
        let lpips = match self.lpips {
            Some(n) => Some(n.distances(&[predicted], &[truth], w, h).map_err(feature)?[0]),
            None => None,
        };
        let dreamsim = match self.dreamsim {
            Some(n) => Some(n.distances(&[predicted], &[truth], w, h).map_err(feature)?[0]),
            None => None,
        };
        Ok(FrameScore { lpips, dreamsim, ..FrameScore::of_with_holes(t, predicted, truth, w, h, landed) })
    }
}

/// A row's rollouts: per trajectory, per generated frame, its scores and
/// (when kept) the frame itself.
pub struct RowOutput {
    pub scores: Vec<Vec<FrameScore>>,
    pub frames: Vec<Vec<Vec<u8>>>,
}

/// The noise seed of trajectory `traj`'s frame `t`: the same whatever the
/// batch, so a rollout does not depend on how trajectories are grouped.
pub fn frame_seed(seed: u64, traj: usize, t: usize) -> u64 {
    crate::probe::target_seed(seed, t) ^ (traj as u64).wrapping_mul(0xd1b5_4a32_d192_ed03)
}

/// One row's rollouts over `trajs`. `observed_latents[i]` holds trajectory
/// i's ground-truth latents under the row's model (unused by the
/// references). Returns every trajectory's per-frame scores, in frame order.
pub fn rollout(
    trajs: &[Trajectory],
    row: &Row,
    observed_latents: &[Vec<Vec<f32>>],
    max_frames: Option<usize>,
    batch: usize,
    seed: u64,
    scorer: &Scorer,
    progress: &dyn Fn(usize),
) -> Result<RowOutput, ProbeError> {
    let all: Vec<usize> = (0..trajs.len()).collect();
    rollout_as(trajs, &all, row, observed_latents, max_frames, batch, seed, scorer, progress)
}

/// [`rollout`] where `trajs[i]` draws its noise as trajectory `suite_index[i]`
/// of its suite: one trajectory rolled out again alone makes the same frames.
pub fn rollout_as(
    trajs: &[Trajectory],
    suite_index: &[usize],
    row: &Row,
    observed_latents: &[Vec<Vec<f32>>],
    max_frames: Option<usize>,
    batch: usize,
    seed: u64,
    scorer: &Scorer,
    progress: &dyn Fn(usize),
) -> Result<RowOutput, ProbeError> {
    assert_eq!(trajs.len(), suite_index.len(), "one suite index per trajectory");
    match &row.predictor {
        Predictor::Copy | Predictor::Reproject | Predictor::ReprojectFused { .. } => {
            let (scores, frames) = trajs.iter().map(|t| reference(t, &row.predictor, max_frames, scorer, progress)).collect::<Result<Vec<_>, _>>()?.into_iter().unzip();
            Ok(RowOutput { scores, frames })
        }
        Predictor::Reconstruct { model } => {
            let (scores, frames) = trajs
                .iter()
                .zip(observed_latents)
                .map(|(t, latents)| reconstruct(t, model, latents, max_frames, batch, scorer, progress))
                .collect::<Result<Vec<_>, _>>()?
                .into_iter()
                .unzip();
            Ok(RowOutput { scores, frames })
        }
        Predictor::Model { model, policy, sampler }
        | Predictor::Composite { model, policy, sampler }
        | Predictor::PlanWarps { model, policy, sampler }
        | Predictor::Upsampled { model, policy, sampler } => {
            model.layout_for(&policy.packing)?; // before any work: a policy the model cannot take fails at once
            let warp_policy = crate::probe::warp_policy(model);
            let plan_warps = matches!(row.predictor, Predictor::PlanWarps { .. });
            if plan_warps && warp_policy.is_none() {
                return Err(ProbeError::Invalid(format!("{}: a plan-warp row needs a model with the warp input", row.name)));
            }
            let covisibility = policy.covisibility.map(|c| c.validated().map_err(|e| ProbeError::Invalid(e.to_string()))).transpose()?;
            // A composite overlays the fused warp of the best observed frames and re-encodes the result.
            let composite = matches!(row.predictor, Predictor::Composite { .. }).then(|| Policy::best_overlap_frames(scorer.probe_frames));
            let warps = warp_policy.is_some() || composite.is_some();
            let image = &model.manifest().image;
            let model_size = (image.width as u32, image.height as u32);
            let upsampled = matches!(row.predictor, Predictor::Upsampled { .. });
            let rule = FullSize::of(model.manifest().serving.as_ref()).with(scorer.full_size.0, scorer.full_size.1);
            let mut runs = trajs
                .iter()
                .zip(observed_latents)
                .map(|(traj, lat)| {
                    let range = rollout_frames(traj, max_frames);
                    let frusta = traj.frusta()?;
                    // Co-visibility reads the exploration's depth; generated frames have none.
                    let depth = match &covisibility {
                        Some(c) => exploration_depth(traj, range.start, c.cells)?,
                        None => HashMap::new(),
                    };
                    let small = ((traj.intrinsics.width, traj.intrinsics.height) != model_size).then(|| traj.at_size(model_size.0, model_size.1)).transpose()?;
                    if upsampled && small.is_none() {
                        return Err(ProbeError::Invalid(format!("{}: the suite's frames are the model's size; there is nothing to upsample", row.name)));
                    }
                    // A frame shown larger than the model's warps observed frames at the suite's size.
                    let warps = warps || small.is_some();
                    Ok(Run {
                        small,
                        depth,
                        store: observed(&frusta, range.start)?,
                        observed: observed(&frusta, if warps { range.start } else { 0 })?,
                        latents: lat[..range.start].to_vec(),
                        frusta,
                        traj,
                        previous: None,
                        start: range.start,
                        next: range.start,
                        end: range.end,
                        scores: Vec::with_capacity(range.len()),
                        frames: Vec::new(),
                        landed: scorer.landed(traj, range)?,
                    })
                })
                .collect::<Result<Vec<_>, ProbeError>>()?;
            loop {
                let active: Vec<usize> = (0..runs.len()).filter(|&i| runs[i].next < runs[i].end).collect();
                if active.is_empty() {
                    break;
                }
                for chunk in active.chunks(batch.max(1)) {
                    let mut plans = Vec::with_capacity(chunk.len());
                    let mut sources = Vec::with_capacity(chunk.len());
                    for &i in chunk {
                        let r = &mut runs[i];
                        let target = &r.frusta[r.next];
                        let invalid = |e: memory::InputError| ProbeError::Invalid(e.to_string());
                        let depth_of = |id| r.depth.get(&id);
                        let plan = r.store.plan(policy, target, r.previous.as_ref(), depth_of).map_err(invalid)?.plan;
                        // Warp sources are chosen as the plan is: by co-visibility when the policy asks.
                        let source = match &warp_policy {
                            None => None,
                            Some(p) if plan_warps => Some(within_plan(&r.observed, &plan)?.select(p, target, None).0),
                            Some(p) => Some(r.observed.plan(&Policy { covisibility, ..p.clone() }, target, None, depth_of).map_err(invalid)?.plan),
                        };
                        r.previous = Some(plan.clone());
                        plans.push(plan);
                        sources.push(source);
                    }
                    // The model warps its sources at its own size.
                    let warp_sources: Vec<Vec<WarpSource>> = chunk
                        .iter()
                        .zip(&sources)
                        .map(|(&i, s)| s.as_ref().map_or_else(Vec::new, |p| warp_sources(runs[i].small.as_ref().unwrap_or(runs[i].traj), p)))
                        .collect();
                    let requests: Vec<Request> = chunk
                        .iter()
                        .zip(&plans)
                        .zip(&warp_sources)
                        .map(|((&i, plan), source)| {
                            let (r, t) = (&runs[i], runs[i].next);
                            Request {
                                plan,
                                target_time: t as u64,
                                target_pose: &r.traj.poses[t],
                                action: &r.traj.actions[t],
                                seed: frame_seed(seed, suite_index[i], t),
                                warp: source,
                            }
                        })
                        .collect();
                    // Frames from the returning point on are the model's own.
                    let frame = |j: usize, id: u64| {
                        let r = &runs[chunk[j]];
                        let generated = id as usize >= r.start;
                        r.latents.get(id as usize).map(|l| ContextFrame { latent: l, time: id, pose: &r.traj.poses[id as usize], generated })
                    };
                    let mut prediction = model.predict(&policy.packing, &requests, &frame, sampler)?;
                    if let Some(c) = scorer.capture {
                        // Request j's place on its return leg and its true frame.
                        let leg = |j: usize| {
                            let r = &runs[chunk[j]];
                            (r.next - r.start, r.traj.frame(r.next))
                        };
                        c.take(&requests, &frame, &policy.packing, sampler, leg)?;
                    }
                    drop(requests);
                    for ((&i, p), source) in chunk.iter().zip(&mut prediction.frames).zip(&sources) {
                        let r = &runs[i];
                        if r.small.is_some() {
                            let how = if upsampled || composite.is_some() { Upscale::Bicubic } else { Upscale::FullSize };
                            p.rgb = at_suite_size(r, std::mem::take(&mut p.rgb), model_size, source.as_ref(), how, &rule)?;
                        }
                    }
                    if let Some(fused) = &composite {
                        for (&i, p) in chunk.iter().zip(&mut prediction.frames) {
                            let r = &runs[i];
                            let plan = r.observed.select(fused, &r.frusta[r.next], None).0;
                            p.rgb = fused_warp(r.traj, &plan, r.next).overlay(std::mem::take(&mut p.rgb));
                        }
                        let images: Vec<&[u8]> = prediction.frames.iter().map(|p| p.rgb.as_slice()).collect();
                        let latents = encode_frames(model, &images, &runs[chunk[0]].traj.intrinsics)?;
                        for (p, latent) in prediction.frames.iter_mut().zip(latents) {
                            p.latent = latent;
                        }
                    }
                    for (&i, p) in chunk.iter().zip(prediction.frames) {
                        let r = &mut runs[i];
                        let t = r.next;
                        r.scores.push(scorer.score(r.traj, t, &p.rgb, &r.landed[t - r.start])?);
                        if scorer.keep_frames {
                            r.frames.push(p.rgb);
                        }
                        r.latents.push(p.latent);
                        r.store
                            .insert(MemoryFrame { id: t as u64, time: t as u64, frustum: r.frusta[t].clone() })
                            .map_err(|e| ProbeError::Invalid(e.to_string()))?;
                        r.next += 1;
                    }
                    progress(chunk.len());
                }
            }
            let (scores, frames) = runs.into_iter().map(|r| (r.scores, r.frames)).unzip();
            Ok(RowOutput { scores, frames })
        }
    }
}

enum Upscale {
    /// `model::full_size`: the stored frames where they land and agree, the model's frame elsewhere.
    FullSize,
    /// The model's frame alone, bicubic.
    Bicubic,
}

/// Run `r`'s model frame (at `model_size`) shown at its suite's size: with
/// the full-size frames of the model's warp sources (`plan`), or, for a model
/// that warps none, of the best-overlap observed frames.
fn at_suite_size(r: &Run, small: Vec<u8>, model_size: (u32, u32), plan: Option<&ContextPlan>, how: Upscale, rule: &FullSize) -> Result<Vec<u8>, ProbeError> {
    let k = &r.traj.intrinsics;
    let (sw, sh) = model_size;
    if let Upscale::Bicubic = how {
        return Ok(model::full_size::bicubic(&small, sw as usize, sh as usize, k.width as usize, k.height as usize));
    }
    let best;
    let plan = match plan {
        Some(p) => p,
        None => {
            best = r.observed.select(&Policy::best_overlap_frames(rule.frames), &r.frusta[r.next], None).0;
            &best
        }
    };
    let sources = warp_sources(r.traj, plan);
    Ok(model::full_size::full_size_frame(&small, sw, sh, &sources, &r.traj.poses[r.next], k.width, k.height, rule)?.rgb)
}

/// The non-learned references draw only on observed frames: each return
/// frame copies (or warps with depth) the observed frame of largest overlap.
fn reference(
    traj: &Trajectory,
    how: &Predictor,
    max_frames: Option<usize>,
    scorer: &Scorer,
    progress: &dyn Fn(usize),
) -> Result<(Vec<FrameScore>, Vec<Vec<u8>>), ProbeError> {
    let range = rollout_frames(traj, max_frames);
    let frusta = traj.frusta()?;
    let store = observed(&frusta, range.start)?;
    let policy = how.policy();
    let landed = scorer.landed(traj, range.clone())?;
    let mut out = Vec::with_capacity(range.len());
    let mut frames = Vec::new();
    for (t, landed) in range.zip(landed.iter()) {
        let (plan, _) = store.select(&policy, &frusta[t], None);
        let img = reference_image(traj, how, &plan, t);
        out.push(scorer.score(traj, t, &img, landed)?);
        if scorer.keep_frames {
            frames.push(img);
        }
        progress(1);
    }
    Ok((out, frames))
}

/// The return leg's true frames through `model`'s autoencoder: its
/// `latents` (the truth encoded, one per frame) decoded, `batch` at a time.
fn reconstruct(
    traj: &Trajectory,
    model: &Model,
    latents: &[Vec<f32>],
    max_frames: Option<usize>,
    batch: usize,
    scorer: &Scorer,
    progress: &dyn Fn(usize),
) -> Result<(Vec<FrameScore>, Vec<Vec<u8>>), ProbeError> {
    let image = &model.manifest().image;
    if (image.width, image.height) != (traj.intrinsics.width as usize, traj.intrinsics.height as usize) {
        return Err(ProbeError::Invalid(format!(
            "{}: the model makes {}x{} frames, the suite has {}x{}",
            model.dir().display(),
            image.width,
            image.height,
            traj.intrinsics.width,
            traj.intrinsics.height
        )));
    }
    let spec = &model.manifest().autoencoder.latent;
    let range = rollout_frames(traj, max_frames);
    let landed = scorer.landed(traj, range.clone())?;
    let (mut out, mut frames) = (Vec::with_capacity(range.len()), Vec::new());
    for chunk in range.clone().collect::<Vec<_>>().chunks(batch.max(1)) {
        let shape = vec![chunk.len(), spec.channels, spec.height, spec.width];
        let decoded = model.decode(&model::Tensor::new(shape, chunk.iter().flat_map(|&t| latents[t].iter().copied()).collect()))?;
        for (j, &t) in chunk.iter().enumerate() {
            let rgb = model::generate::tensor_to_frame(&decoded, j)?;
            out.push(scorer.score(traj, t, &rgb, &landed[t - range.start])?);
            if scorer.keep_frames {
                frames.push(rgb);
            }
        }
        progress(chunk.len());
    }
    Ok((out, frames))
}

/// FVD of one group of rollouts, with its bootstrap interval.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FvdEstimate {
    pub clips: usize,
    pub fvd: f64,
    pub lo: f64,
    pub hi: f64,
}

/// FVD between generated and ground-truth clips: each trajectory's
/// generated leg cut into non-overlapping windows of the network's clip
/// length, paired with the true frames at the same times. The interval
/// resamples clip pairs. `None` with fewer than two clips.
pub fn clip_fvd(
    net: &VideoFeatures,
    trajs: &[&Trajectory],
    scores: &[&Vec<FrameScore>],
    frames: &[&Vec<Vec<u8>>],
    reps: usize,
    seed: u64,
) -> Result<Option<FvdEstimate>, ProbeError> {
    let len = net.clip_len();
    let mut fake: Vec<Vec<&[u8]>> = Vec::new();
    let mut real: Vec<Vec<&[u8]>> = Vec::new();
    for ((traj, s), f) in trajs.iter().zip(scores).zip(frames) {
        for start in (0..f.len().saturating_sub(len - 1)).step_by(len) {
            fake.push(f[start..start + len].iter().map(Vec::as_slice).collect());
            real.push(s[start..start + len].iter().map(|x| traj.frame(x.t)).collect());
        }
    }
    if fake.len() < 2 {
        return Ok(None);
    }
    let (w, h) = (trajs[0].intrinsics.width as usize, trajs[0].intrinsics.height as usize);
    let feature = |e: FeatureError| ProbeError::Invalid(e.to_string());
    let mut ff = Vec::new();
    let mut fr = Vec::new();
    for (a, b) in fake.chunks(32).zip(real.chunks(32)) {
        ff.extend(net.features(a, w, h).map_err(feature)?);
        fr.extend(net.features(b, w, h).map_err(feature)?);
    }
    let fvd = frechet_distance(&fr, &ff);
    let mut rng = memory::rng::SplitMix64::new(seed);
    let n = ff.len();
    let mut boots: Vec<f64> = (0..reps)
        .map(|_| {
            let pick: Vec<usize> = (0..n).map(|_| (rng.next_u64() % n as u64) as usize).collect();
            let take = |v: &[Vec<f64>]| pick.iter().map(|&i| v[i].clone()).collect::<Vec<_>>();
            frechet_distance(&take(&fr), &take(&ff))
        })
        .collect();
    boots.sort_by(f64::total_cmp);
    let at = |q: f64| boots.get(((q * (boots.len().max(1) - 1) as f64).round()) as usize).copied().unwrap_or(f64::NAN);
    Ok(Some(FvdEstimate { clips: n, fvd, lo: at(0.025), hi: at(0.975) }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use memory::policy::{SelectedFrame, Slot};
    use memory::{Intrinsics, Pose};

    #[test]
    fn a_plan_warp_row_warps_only_the_observed_frames_of_its_plan() {
        let k = Intrinsics::from_fov(70.0, None, 64, 64).unwrap();
        let frusta: Vec<Frustum> = (0..12).map(|x| Frustum::new(Pose::from_position(glam::DVec3::new(x as f64, 0.0, 0.0)), k).unwrap()).collect();
        let observed = observed(&frusta, 8).unwrap(); // frames 8.. are generated
        let pick = |id: u64| Some(SelectedFrame { id, time: id, overlap: 0.5, score: 0.5 });
        let plan = ContextPlan { slots: [11, 3, 9, 6].into_iter().map(|id| Slot { rate: 1, frame: pick(id) }).chain([Slot { rate: 4, frame: None }]).collect() };
        let pool = within_plan(&observed, &plan).unwrap();
        let mut ids: Vec<u64> = pool.frames().iter().map(|f| f.id).collect();
        ids.sort();
        assert_eq!(ids, [3, 6], "frames 11 and 9 are generated, the rest of memory is not in the plan");
    }
}
