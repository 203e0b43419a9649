//! The memory probe: one-step, teacher-forced next-frame prediction on the
//! return legs of a suite. Every earlier frame is ground truth, so a row's
//! score says only how well it uses what it is shown — its weights and its
//! context selection — with no compounding error from its own rollouts.

use std::collections::HashMap;
use std::time::Instant;

use memory::{ContextPlan, FrameMemory, Intrinsics, MemoryFrame, Policy};
use model::generate::frame_to_tensor;
use model::pack::ContextFrame;
use model::warp::Warped;
use model::{Model, ModelError, Request, Sampler, Tensor, WarpSource};
use serde::Serialize;

use crate::metrics::{DepthTally, psnr, psnr_where, sharpness_ratio, sharpness_ratio_where, ssim};
use crate::reproject::{reproject, reproject_fused};
use crate::suite::{SuiteError, Trajectory};

#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    #[error(transparent)]
    Suite(#[from] SuiteError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("{0}")]
    Invalid(String),
}

/// How a row predicts frame `t` from frames `0..t`.
pub enum Predictor<'a> {
    /// A model with a context policy; the policy's packing must match one of
    /// the model's layouts. A policy with co-visibility (its plans and warp
    /// sources chosen from the observed frames' depth) runs in rollouts only.
    Model { model: &'a Model, policy: Policy, sampler: Sampler },
    /// The stored frame of largest overlap with the target view, as is.
    Copy,
    /// That frame warped into the target pose with its depth.
    Reproject,
    /// The `frames` frames of largest overlap warped behind one z-buffer,
    /// cracks filled from their neighbours.
    ReprojectFused { frames: usize },
    /// The composite reference: that fused warp where it lands (no filling),
    /// a model's prediction in its holes.
    Composite { model: &'a Model, policy: Policy, sampler: Sampler },
    /// A geometry model that warps only observed frames its own plan selected,
    /// not the best-overlap frames of all memory: a policy without retrieval
    /// (nearest frame packing) stays without it; rollouts only.
    PlanWarps { model: &'a Model, policy: Policy, sampler: Sampler },
    /// A model row whose frames, on a suite larger than the model's frames,
    /// are brought to the suite's size bicubically and nothing else: the
    /// floor a full-size frame (`model::full_size`) is measured against; rollouts only.
    Upsampled { model: &'a Model, policy: Policy, sampler: Sampler },
    /// The true frame through the model's autoencoder, decode(encode(truth)):
    /// the ceiling under every frame the model makes; rollouts only.
    Reconstruct { model: &'a Model },
}


/// Frames the fused reference warps together, and whose warp makes the
/// holes mask, unless `worldpack eval --probe-frames` says otherwise.
pub const FUSED_FRAMES: usize = 3;

/// How the non-learned rows make a frame when the fused reference warps
/// `frames`; a saved reference row made by another rule is recomputed.
pub fn reference_rules(frames: usize) -> String {
    format!("model::warp (depth 0 at infinity); holes keep the best frame's pixel; fused: {frames} frames, 2 fill rounds")
}

impl<'a> Predictor<'a> {
    /// The model a learned row runs (none for the non-learned references).
    pub fn model(&self) -> Option<&'a Model> {
        match self {
            Predictor::Model { model, .. }
            | Predictor::Composite { model, .. }
            | Predictor::PlanWarps { model, .. }
            | Predictor::Upsampled { model, .. }
            | Predictor::Reconstruct { model } => Some(*model),
            Predictor::Copy | Predictor::Reproject | Predictor::ReprojectFused { .. } => None,
        }
    }

    /// The memory policy a row selects with (references: the best-overlap frames).
    pub fn policy(&self) -> Policy {
        match self {
            Predictor::Model { policy, .. }
            | Predictor::Composite { policy, .. }
            | Predictor::PlanWarps { policy, .. }
            | Predictor::Upsampled { policy, .. } => policy.clone(),
            Predictor::Copy | Predictor::Reproject | Predictor::Reconstruct { .. } => Policy::best_overlap(),
            Predictor::ReprojectFused { frames } => Policy::best_overlap_frames(*frames),
        }
    }

    /// Refuses, naming the row, what only rollouts (`worldpack eval`) run: co-visible,
    /// plan-warp and reconstruction rows (teacher forcing has no observed depth to read).
    fn teacher_forced(&self, row: &str) -> Result<(), ProbeError> {
        let rollouts_only = match self {
            Predictor::PlanWarps { .. } | Predictor::Reconstruct { .. } | Predictor::Upsampled { .. } => true,
            other => other.policy().covisibility.is_some(),
        };
        if rollouts_only {
            return Err(ProbeError::Invalid(format!("{row}: co-visible, plan-warp, upsampled and reconstruction rows run in rollouts (`worldpack eval`) only")));
        }
        Ok(())
    }
}

pub struct Row<'a> {
    pub name: String,
    pub predictor: Predictor<'a>,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct FrameScore {
    pub t: usize,
    pub psnr: f64,
    pub ssim: f64,
    /// Only when a feature network was given (see [`crate::features`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dreamsim: Option<f64>,
    /// Gradient energy of the prediction over the truth's
    /// ([`crate::metrics::sharpness_ratio`]); absent for a flat truth and in
    /// scores saved before it was measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sharpness: Option<f64>,
    /// PSNR over the pixels the fused warp of the best observed frames covers,
    /// and over the rest (the probe's validity mask; absent elsewhere).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_in_warp: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psnr_out_warp: Option<f64>,
    /// The sharpness ratio over the rest, the warp's holes: where memory has
    /// no pixels and the model has to paint (`worldpack eval`'s holes measure).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sharpness_out_warp: Option<f64>,
}

impl FrameScore {
    /// PSNR, SSIM and sharpness of `predicted` against `truth` (RGB, `w`×`h`); no feature-network scores.
    pub fn of(t: usize, predicted: &[u8], truth: &[u8], w: usize, h: usize) -> FrameScore {
        FrameScore {
            t,
            psnr: psnr(predicted, truth),
            ssim: ssim(predicted, truth, w, h).unwrap_or(f64::NAN),
            lpips: None,
            dreamsim: None,
            sharpness: sharpness_ratio(predicted, truth, w, h),
            psnr_in_warp: None,
            psnr_out_warp: None,
            sharpness_out_warp: None,
        }
    }

    /// [`FrameScore::of`] plus the PSNR where the warp `landed` and in its
    /// holes, and the sharpness ratio in the holes.
    pub fn of_with_holes(t: usize, predicted: &[u8], truth: &[u8], w: usize, h: usize, landed: &[bool]) -> FrameScore {
        FrameScore {
            psnr_in_warp: psnr_where(predicted, truth, landed, true, MASK_MIN_PIXELS),
            psnr_out_warp: psnr_where(predicted, truth, landed, false, MASK_MIN_PIXELS),
            sharpness_out_warp: sharpness_ratio_where(predicted, truth, w, h, landed, false, MASK_MIN_PIXELS),
            ..FrameScore::of(t, predicted, truth, w, h)
        }
    }
}

/// One trajectory's scores: `rows[i]` belongs to the i-th row, frames in the
/// same order for every row (so differences pair up).
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct TrajectoryScores {
    pub dir: String,
    pub task: String,
    pub range: i32,
    pub rows: Vec<Vec<FrameScore>>,
    /// The fused warp's depth (the validity mask's) against the true depth of every target.
    pub warped_depth: DepthTally,
}

pub struct Settings {
    pub stride: usize,
    pub batch: usize,
    pub seed: u64,
}

/// Each policy's plan for every target, from one pass over the trajectory.
fn plans(traj: &Trajectory, policies: &[&Policy], targets: &[usize]) -> Result<Vec<Vec<ContextPlan>>, ProbeError> {
    let frusta = traj.frusta()?;
    let mut out: Vec<Vec<ContextPlan>> = policies.iter().map(|_| Vec::with_capacity(targets.len())).collect();
    let mut previous: Vec<Option<ContextPlan>> = policies.iter().map(|_| None).collect();
    let mut store = FrameMemory::new();
    let mut next = targets.iter().peekable();
    for (t, frustum) in frusta.iter().enumerate() {
        if next.peek() == Some(&&t) {
            next.next();
            for (i, policy) in policies.iter().enumerate() {
                let (plan, _) = store.select(policy, frustum, previous[i].as_ref());
                previous[i] = Some(plan.clone());
                out[i].push(plan);
            }
        }
        if next.peek().is_none() {
            break;
        }
        store
            .insert(MemoryFrame { id: t as u64, time: t as u64, frustum: frustum.clone() })
            .map_err(|e| ProbeError::Invalid(format!("{}: frame {t}: {e}", traj.entry.dir)))?;
    }
    Ok(out)
}

/// The scaled latents of every frame of `traj`.
pub fn encode_all(m: &Model, traj: &Trajectory) -> Result<Vec<Vec<f32>>, ProbeError> {
    let frames: Vec<&[u8]> = (0..traj.len()).map(|t| traj.frame(t)).collect();
    let mut latents = Vec::with_capacity(traj.len());
    for chunk in frames.chunks(32) {
        latents.extend(encode_frames(m, chunk, &traj.intrinsics)?);
    }
    Ok(latents)
}

/// The scaled latents of RGB frames taken with intrinsics `k`, in one encoder call.
pub fn encode_frames(m: &Model, frames: &[&[u8]], k: &Intrinsics) -> Result<Vec<Vec<f32>>, ProbeError> {
    let img = &m.manifest().image;
    let tensors = frames
        .iter()
        .map(|f| frame_to_tensor(f, k.width, k.height, k, img.width as u32, img.height as u32).map(|p| p.0))
        .collect::<Result<Vec<_>, _>>()?;
    let mut shape = tensors[0].shape.clone();
    shape[0] = tensors.len();
    let out = m.encode(&Tensor::new(shape, tensors.into_iter().flat_map(|t| t.data).collect()))?;
    let per = out.data.len() / frames.len().max(1);
    Ok(out.data.chunks_exact(per).map(<[f32]>::to_vec).collect())
}

/// The frames of a `Policy::best_overlap_frames` plan (the observed frames
/// that overlap the target view most, best first) with their depth: what a
/// geometry model and the warping references warp.
pub fn warp_sources<'a>(traj: &'a Trajectory, plan: &ContextPlan) -> Vec<WarpSource<'a>> {
    plan.selected()
        .map(|(_, f)| f.id as usize)
        .map(|s| WarpSource { rgb: traj.frame(s), depth_mm: traj.depth(s), pose: &traj.poses[s], intrinsics: &traj.intrinsics })
        .collect()
}

/// A geometry model's warp-source policy: as many best-overlap frames as its manifest fuses.
pub fn warp_policy(m: &Model) -> Option<Policy> {
    m.manifest().denoiser.warp.as_ref().map(|w| Policy::best_overlap_frames(w.frames))
}

/// The fused warp of `plan`'s frames (the best-overlap observed ones) into
/// target `t`: its mask is the probe's validity mask, its depth a depth for
/// `t` made without seeing it. Empty (no pixel) without a frame.
pub fn fused_warp(traj: &Trajectory, plan: &ContextPlan, t: usize) -> Warped {
    let sources = warp_sources(traj, plan);
    if sources.is_empty() {
        let n = traj.intrinsics.width as usize * traj.intrinsics.height as usize;
        return Warped { rgb: vec![0; 3 * n], mask: vec![false; n], depth: vec![0.0; n] };
    }
    model::warp::fused_warp(&sources, &traj.poses[t]).expect("suite frames match their intrinsics")
}

/// A side of the validity mask is scored only when it holds at least this
/// many pixels (1.5% of a 64×64 frame): fewer make a PSNR of noise.
pub const MASK_MIN_PIXELS: usize = 64;

/// What a non-learned reference shows for frame `t`: the first frame of
/// `plan` (the best-overlap one), copied or warped into `t`'s pose.
pub fn reference_image(traj: &Trajectory, how: &Predictor, plan: &ContextPlan, t: usize) -> Vec<u8> {
    let src = plan.selected().next().map_or(t - 1, |(_, f)| f.id as usize);
    match how {
        Predictor::Reproject => reproject(traj.frame(src), traj.depth(src), &traj.intrinsics, &traj.poses[src], &traj.poses[t]).0,
        Predictor::ReprojectFused { .. } => match warp_sources(traj, plan) {
            sources if sources.is_empty() => traj.frame(src).to_vec(),
            sources => reproject_fused(&sources, &traj.poses[t]).0,
        },
        _ => traj.frame(src).to_vec(),
    }
}

/// The base of every probe's and rollout's noise seeds, so the same target
/// gets the same noise in every program.
pub const SEED: u64 = 20261121;

/// The seed of the noise for target `t`: the same in every row and every
/// batch, so rows differ only in what they are shown.
pub fn target_seed(seed: u64, t: usize) -> u64 {
    seed ^ (t as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
}

/// Predicts `targets` of `traj` for one model row, `batch` at a time; every
/// earlier frame is observed.
fn predict_model(
    m: &Model,
    policy: &Policy,
    sampler: &Sampler,
    traj: &Trajectory,
    latents: &[Vec<f32>],
    targets: &[usize],
    plans: &[ContextPlan],
    warp_plans: &[ContextPlan],
    settings: &Settings,
    mut done: impl FnMut(usize, Vec<u8>),
) -> Result<(), ProbeError> {
    let frame = |_: usize, id: u64| latents.get(id as usize).map(|l| ContextFrame { latent: l, time: id, pose: &traj.poses[id as usize], generated: false });
    let size = settings.batch.max(1);
    let warps = m.manifest().denoiser.warp.is_some();
    let sources: Vec<Vec<WarpSource>> = if warps { warp_plans.iter().map(|p| warp_sources(traj, p)).collect() } else { vec![Vec::new(); targets.len()] };
    for ((chunk, plans), sources) in targets.chunks(size).zip(plans.chunks(size)).zip(sources.chunks(size)) {
        let requests: Vec<Request> = chunk
            .iter()
            .zip(plans)
            .zip(sources)
            .map(|((&t, plan), source)| Request {
                plan,
                target_time: t as u64,
                target_pose: &traj.poses[t],
                action: &traj.actions[t],
                seed: target_seed(settings.seed, t),
                warp: source,
            })
            .collect();
        let prediction = m.predict(&policy.packing, &requests, &frame, sampler)?;
        for (&t, p) in chunk.iter().zip(prediction.frames) {
            done(t, p.rgb);
        }
    }
    Ok(())
}

/// A trajectory's latents under one model, one per frame, shared by the rows on that model.
pub type SharedLatents = std::rc::Rc<Vec<Vec<f32>>>;

/// Scores every row on the return legs of one trajectory. `latents_for(m)`
/// gives the trajectory's latents under model `m` (rows sharing a model
/// share them). `progress(n)` is told of each `n` frames scored.
pub fn probe_trajectory(
    traj: &Trajectory,
    rows: &[Row],
    settings: &Settings,
    latents_for: &mut dyn FnMut(&Model) -> Result<SharedLatents, ProbeError>,
    progress: &dyn Fn(usize),
) -> Result<TrajectoryScores, ProbeError> {
    for row in rows {
        row.predictor.teacher_forced(&row.name)?;
    }
    let targets = traj.return_frames(settings.stride);
    // Each row's plans, then the validity mask's frames, then each geometry
    // row's warp sources (empty plans for other rows).
    let warp_policies: Vec<Option<Policy>> = rows
        .iter()
        .map(|r| match &r.predictor {
            Predictor::Model { model, .. } | Predictor::Composite { model, .. } => warp_policy(model),
            _ => None,
        })
        .collect();
    let owned: Vec<Policy> = rows
        .iter()
        .map(|r| r.predictor.policy())
        .chain([Policy::best_overlap_frames(FUSED_FRAMES)])
        .chain(warp_policies.iter().flatten().cloned())
        .collect();
    let policies: Vec<&Policy> = owned.iter().collect();
    let mut plans = plans(traj, &policies, &targets)?;
    let mut warp_plans = plans.split_off(rows.len() + 1).into_iter();
    let mask_plans = plans.pop().expect("the validity mask's plans");
    let warp_plans: Vec<Vec<ContextPlan>> = warp_policies.iter().map(|p| if p.is_some() { warp_plans.next().unwrap_or_default() } else { Vec::new() }).collect();
    let (w, h) = (traj.intrinsics.width as usize, traj.intrinsics.height as usize);
    let mut warped_depth = DepthTally::default();
    let fused: HashMap<usize, Warped> = targets
        .iter()
        .zip(&mask_plans)
        .map(|(&t, p)| {
            let warped = fused_warp(traj, p, t);
            warped_depth.add(&DepthTally::of(&warped.depth, traj.depth(t)));
            (t, warped)
        })
        .collect();
    let score = |t: usize, predicted: &[u8]| FrameScore::of_with_holes(t, predicted, traj.frame(t), w, h, &fused[&t].mask);
    let mut scores = Vec::with_capacity(rows.len());
    for (row_index, (row, plans)) in rows.iter().zip(&plans).enumerate() {
        let mut out = Vec::with_capacity(targets.len());
        match &row.predictor {
            Predictor::Model { model, policy, sampler } | Predictor::Composite { model, policy, sampler } => {
                let composite = matches!(row.predictor, Predictor::Composite { .. });
                let latents = latents_for(model)?;
                if (model.manifest().image.width, model.manifest().image.height) != (w, h) {
                    return Err(ProbeError::Invalid(format!(
                        "model {} makes {}x{} frames but the suite has {w}x{h}",
                        model.dir().display(),
                        model.manifest().image.width,
                        model.manifest().image.height
                    )));
                }
                predict_model(model, policy, sampler, traj, &latents, &targets, plans, &warp_plans[row_index], settings, |t, img| {
                    let img = if composite { fused[&t].overlay(img) } else { img };
                    out.push(score(t, &img));
                    progress(1);
                })?;
            }
            Predictor::Copy | Predictor::Reproject | Predictor::ReprojectFused { .. } => {
                for (&t, plan) in targets.iter().zip(plans) {
                    out.push(score(t, &reference_image(traj, &row.predictor, plan, t)));
                    progress(1);
                }
            }
            Predictor::PlanWarps { .. } | Predictor::Reconstruct { .. } | Predictor::Upsampled { .. } => row.predictor.teacher_forced(&row.name)?,
        }
        scores.push(out);
    }
    Ok(TrajectoryScores { dir: traj.entry.dir.clone(), task: traj.entry.task.clone(), range: traj.entry.range, rows: scores, warped_depth })
}

/// Untimed predictions before the timed ones: a model's first batch-1 calls
/// can be slower: with two intra-op threads, rows that ran a model first
/// came out 9–21 ms slower than later rows on the same model and steps.
const WARM_UP_CALLS: usize = 3;

/// Median wall time (ms) of one prediction, batch 1, selection through
/// decoded frame, over `calls` return frames of `traj` after a few untimed ones.
pub fn latency_ms(traj: &Trajectory, row: &Row, latents: &[Vec<f32>], calls: usize) -> Result<f64, ProbeError> {
    row.predictor.teacher_forced(&row.name)?;
    let all = traj.return_frames(1);
    let warm_up: Vec<usize> = all.iter().copied().take(WARM_UP_CALLS.min(all.len().saturating_sub(1))).collect();
    let targets: Vec<usize> = all.iter().copied().skip(warm_up.len()).take(calls.max(1)).collect();
    let policy = row.predictor.policy();
    let frusta = traj.frusta()?;
    let mut store = FrameMemory::new();
    let last = *targets.last().unwrap_or(&0);
    let mut times = Vec::new();
    let settings = Settings { stride: 1, batch: 1, seed: 0 };
    for (t, frustum) in frusta.iter().enumerate().take(last + 1) {
        let timed = targets.contains(&t);
        if timed || warm_up.contains(&t) {
            let start = Instant::now();
            let (plan, _) = store.select(&policy, frustum, None);
            match &row.predictor {
                Predictor::Model { model, policy, sampler } | Predictor::Composite { model, policy, sampler } => {
                    // A geometry model's warp sources are chosen within the timed call too.
                    // (A composite's overlay is not timed: it costs what the fused reference does.)
                    let source = warp_policy(model).map_or_else(|| plan.clone(), |p| store.select(&p, frustum, None).0);
                    predict_model(model, policy, sampler, traj, latents, &[t], &[plan], &[source], &settings, |_, img| {
                        std::hint::black_box(img);
                    })?;
                }
                Predictor::PlanWarps { .. } | Predictor::Reconstruct { .. } | Predictor::Upsampled { .. } => row.predictor.teacher_forced(&row.name)?,
                reference => {
                    std::hint::black_box(reference_image(traj, reference, &plan, t));
                }
            }
            if timed {
                times.push(start.elapsed().as_secs_f64() * 1e3);
            }
        }
        store
            .insert(MemoryFrame { id: t as u64, time: t as u64, frustum: frustum.clone() })
            .map_err(|e| ProbeError::Invalid(e.to_string()))?;
    }
    times.sort_by(f64::total_cmp);
    Ok(times.get(times.len() / 2).copied().unwrap_or(f64::NAN))
}

/// What a geometry model's fusion head learns from, for one trajectory: at
/// each return-leg target (every `stride`-th) the model's own prediction
/// (its fusion head left out), the fused reference of its warp sources
/// (`model::warp::fused_reference`), where that warp landed, and the truth.
/// RGB rows of `w`×`h`×3 bytes, masks `w`×`h` bytes of 0 or 1.
#[derive(Default)]
pub struct FusionExamples {
    pub count: usize,
    pub predicted: Vec<u8>,
    pub reference: Vec<u8>,
    pub mask: Vec<u8>,
    pub truth: Vec<u8>,
}

pub fn fusion_examples(traj: &Trajectory, model: &Model, sampler: &Sampler, settings: &Settings, out: &mut FusionExamples) -> Result<(), ProbeError> {
    let Some(warp) = warp_policy(model) else {
        return Err(ProbeError::Invalid(format!("model {} takes no warp input", model.dir().display())));
    };
    if model.manifest().fusion.is_some() {
        return Err(ProbeError::Invalid(format!("model {} has a fusion head already: give the model it was added to", model.dir().display())));
    }
    let targets = traj.return_frames(settings.stride);
    let policy = model.trained_policy();
    let mut plans = plans(traj, &[&policy, &warp], &targets)?;
    let warp_plans = plans.pop().expect("the warp plans");
    let latents = encode_all(model, traj)?;
    let mut predicted = HashMap::new();
    predict_model(model, &policy, sampler, traj, &latents, &targets, &plans[0], &warp_plans, settings, |t, img| {
        predicted.insert(t, img);
    })?;
    for (&t, plan) in targets.iter().zip(&warp_plans) {
        let sources = warp_sources(traj, plan);
        if sources.is_empty() {
            continue; // no stored frame with depth: the head is not run
        }
        let (reference, mask) = model::warp::fused_reference(&sources, &traj.poses[t])?;
        out.predicted.extend(&predicted[&t]);
        out.reference.extend(reference);
        out.mask.extend(mask.iter().map(|&m| m as u8));
        out.truth.extend(traj.frame(t));
        out.count += 1;
    }
    Ok(())
}
