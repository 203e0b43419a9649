//! `worldpack fusion-data`: the examples a geometry model's fusion head is
//! trained on (`./scripts/model.sh fusion-train`), from a suite's
//! return legs, written as .npy beside each other: each frame predicted from
//! the true frames before it, or (`--rollout-with`) from a fused model's own
//! rollouts, as the head meets its frames in use.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use eval::probe::{FusionExamples, Predictor, Row, SEED, Settings, encode_all, fusion_examples};
use eval::rollout::{Capture, Scorer, rollout};
use eval::noise::PoseNoise;
use eval::suite::{Trajectory, entries};

use crate::cli::{Runtime, bar, count, parse_method};

/// Seeds the pose noise (per trajectory, xor its index); not the study's seed.
const NOISE_SEED: u64 = 0xf05e_d0a7;

fn non_negative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("expected a finite number >= 0, got {s:?}")),
    }
}

fn share(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a share in [0, 1], got {s:?}")),
    }
}

#[derive(clap::Args)]
pub struct Options {
    /// A suite or dataset from `worldpack sim` (training seeds, not the ones you evaluate on).
    #[arg(long)]
    pub suite: PathBuf,
    /// A geometry model (its manifest has `denoiser.warp`) without a fusion head.
    #[arg(long)]
    pub model: PathBuf,
    /// Take every n-th return-leg frame.
    #[arg(long, default_value_t = 2, value_parser = count(1, 10_000))]
    pub stride: usize,
    /// Sampler steps per predicted frame.
    #[arg(long, default_value_t = 10, value_parser = count(1, 1000))]
    pub steps: usize,
    #[arg(long, default_value = "ddim", value_parser = parse_method)]
    pub method: model::Method,
    /// Frames predicted per denoiser call.
    #[arg(long, default_value_t = 16, value_parser = count(1, 1024))]
    pub batch: usize,
    /// Independent pose noise (blocks per axis) on every pose of the noisy trajectories, as
    /// `worldpack study` applies it: the head then learns how far to trust a misplaced warp.
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub pose_noise_translation: f64,
    /// Rotation noise (degrees per axis) on the same poses.
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub pose_noise_degrees: f64,
    /// Which share of the trajectories (every k-th, spread evenly) gets that pose noise.
    #[arg(long, default_value_t = 1.0, value_parser = share)]
    pub noisy_share: f64,
    /// Only the first n trajectories of the suite.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Roll the return legs out with this fused model (co-visible selection, as served)
    /// and take the examples from its own frames; --model must be the same model
    /// without its head. --stride then counts along each return leg.
    #[arg(long)]
    pub rollout_with: Option<PathBuf>,
    #[command(flatten)]
    pub runtime: Runtime,
    /// Folder for predicted.npy, reference.npy, landed.npy and truth.npy.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(o: &Options) -> Result<()> {
    let mut list = entries(&o.suite)?;
    list.truncate(o.limit.unwrap_or(usize::MAX));
    if list.is_empty() {
        bail!("--suite: {} lists no trajectories", o.suite.display());
    }
    let model = model::Model::load(&o.model, o.runtime.options()).with_context(|| format!("--model: loading {}", o.model.display()))?;
    let sampler = model::Sampler::new(&model.manifest().diffusion, o.steps, o.method, 0.0)?;
    if let Some(fused) = &o.rollout_with {
        return from_rollouts(o, &list, &model, &sampler, fused);
    }
    let settings = Settings { stride: o.stride, batch: o.batch, seed: SEED };
    let mut examples = FusionExamples::default();
    let progress = bar(list.len(), "fusion-data");
    let noise = PoseNoise::Independent { translation: o.pose_noise_translation, rotation_deg: o.pose_noise_degrees };
    let noisy = |i: usize| (o.pose_noise_translation > 0.0 || o.pose_noise_degrees > 0.0) && ((i + 1) as f64 * o.noisy_share).floor() > (i as f64 * o.noisy_share).floor();
    for (i, entry) in list.iter().enumerate() {
        let mut traj = Trajectory::load(&o.suite, entry)?;
        if noisy(i) {
            traj.poses = eval::noise::apply(&traj.poses, noise, NOISE_SEED ^ i as u64);
        }
        fusion_examples(&traj, &model, &sampler, &settings, &mut examples).with_context(|| entry.dir.clone())?;
        progress.inc(1);
    }
    progress.finish_and_clear();
    write(o, &model, &examples, list.len())
}

/// The examples of `fused`'s co-visible rollouts over the suite, the head's
/// input made again by `bare` (`o.model`).
fn from_rollouts(o: &Options, list: &[eval::suite::Entry], bare: &model::Model, sampler: &model::Sampler, fused: &std::path::Path) -> Result<()> {
    if o.pose_noise_translation > 0.0 || o.pose_noise_degrees > 0.0 {
        bail!("--rollout-with: pose noise is for the teacher-forced examples; leave it out");
    }
    let served = model::Model::load(fused, o.runtime.options()).with_context(|| format!("--rollout-with: loading {}", fused.display()))?;
    if served.manifest().fusion.is_none() {
        bail!("--rollout-with: {} has no fusion head to roll out with", fused.display());
    }
    same_denoiser(bare, &served)?;
    let trajs = list.iter().map(|e| Trajectory::load(&o.suite, e)).collect::<Result<Vec<_>, _>>()?;
    let latents = trajs.iter().map(|t| encode_all(&served, t)).collect::<Result<Vec<_>, _>>()?;
    let row = Row {
        name: "rollout".into(),
        predictor: Predictor::Model { model: &served, policy: served.trained_policy().covisible(), sampler: sampler.clone() },
    };
    let capture = Capture { bare, stride: o.stride, examples: Default::default() };
    let scorer = Scorer { capture: Some(&capture), ..Default::default() };
    let frames: usize = trajs.iter().map(|t| eval::rollout::rollout_frames(t, None).len()).sum();
    let progress = bar(frames, "fusion-data (rollouts)");
    rollout(&trajs, &row, &latents, None, o.batch, SEED, &scorer, &|n| progress.inc(n as u64))?;
    progress.finish_and_clear();
    write(o, bare, &capture.examples.borrow(), trajs.len())
}

/// The head is trained on frames `bare` makes in `served`'s place: the two must share their denoiser and decoder.
fn same_denoiser(bare: &model::Model, served: &model::Model) -> Result<()> {
    let files = |m: &model::Model| -> Vec<String> {
        let mut f: Vec<String> = m.manifest().denoiser.layouts.iter().map(|l| l.file.clone()).collect();
        f.push(m.manifest().autoencoder.decoder.file.clone());
        f.push("denoiser.weights".into());
        f
    };
    for (a, b) in files(bare).iter().zip(files(served)) {
        let read = |m: &model::Model, f: &str| std::fs::read(m.dir().join(f)).ok();
        if read(bare, a) != read(served, &b) {
            bail!("--model: {} is not {} without its head ({a} differs from {b})", bare.dir().display(), served.dir().display());
        }
    }
    Ok(())
}

fn write(o: &Options, model: &model::Model, examples: &FusionExamples, trajectories: usize) -> Result<()> {
    let (w, h) = (model.manifest().image.width, model.manifest().image.height);
    std::fs::create_dir_all(&o.out).with_context(|| format!("--out: {}", o.out.display()))?;
    let n = examples.count;
    if n == 0 {
        bail!("no examples: no generated frame had a warp source (does the suite store depth?)");
    }
    for (name, data, channels) in [("predicted", &examples.predicted, 3), ("reference", &examples.reference, 3), ("landed", &examples.mask, 1), ("truth", &examples.truth, 3)] {
        let shape: Vec<usize> = if channels == 1 { vec![n, h, w] } else { vec![n, h, w, channels] };
        world::npy::write(&o.out.join(format!("{name}.npy")), &shape, data).with_context(|| format!("--out: writing {name}.npy"))?;
    }
    println!("wrote {n} examples from {trajectories} trajectories to {}", o.out.display());
    Ok(())
}
