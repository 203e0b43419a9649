//! `worldpack study`: speed against accuracy, stability under pose noise,
//! and the places where methods fail (docs/results.md).
//!
//! Most numbers are the teacher-forced return-leg probe of `eval::probe`
//! (docs/probe.md) run under a *condition*: the suite as it is, with another
//! frustum `far`, or with believed poses that differ from the true ones
//! (Gaussian noise, drifting odometry, or poses estimated by OpenCV visual
//! odometry). Targets and sampler noise are the same in every condition, so
//! all differences pair frame by frame. Under some of the noise conditions
//! it also runs short autoregressive rollouts (`eval::rollout`), paired the
//! same way. Each condition is saved under `OUT/conditions/` (rollouts under
//! `OUT/rollouts/`) and reused while its settings match.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use eval::noise::{Agreement, PoseNoise, pose_error, selection_agreement};
use eval::probe::{FrameScore, Predictor, ProbeError, Row, Settings, TrajectoryScores, encode_all, latency_ms, probe_trajectory};
use eval::stats::{Interval, cluster_bootstrap, mean_std};
use eval::strata::{Stratum, TargetFeatures, features};
use eval::suite::Trajectory;
use memory::overlap::MonteCarlo;
use memory::{Estimator, Policy, PolicyKind};
use model::{Method, Model, RuntimeOptions, Sampler};
use serde::{Deserialize, Serialize};

use eval::digest::{FNV_START, fnv1a, model_key};
use eval::memory_probe::{VARIANTS, variant_policy};
use crate::cli::{Runtime, count, parse_method, parse_named_path};
use crate::sim::bar;

#[derive(clap::Args)]
pub struct Options {
    /// A suite from `worldpack sim loopnav` (test seeds).
    #[arg(long)]
    pub suite: PathBuf,
    /// The variant model folders (all five: baseline, nearest_frame_packing, memory_retrieval, worldpack, worldpack_keep_last).
    #[arg(long, default_value = "fixtures/variants")]
    pub models: PathBuf,
    /// More models to compare, as NAME=DIR (e.g. other sizes), each with the policy its manifest says it was trained on (WorldPack when it does not say).
    #[arg(long = "extra", value_parser = parse_named_path)]
    pub extra: Vec<(String, PathBuf)>,
    /// Sampler steps per predicted frame.
    #[arg(long, default_value_t = 10, value_parser = count(1, 1000))]
    pub steps: usize,
    /// Also run WorldPack and WorldPack keep-last at these step counts (comma-separated).
    #[arg(long, value_delimiter = ',', value_parser = count(1, 1000), default_value = "2,4,20")]
    pub sweep_steps: Vec<usize>,
    /// Sampler: ddim (deterministic) or ancestral.
    #[arg(long, default_value = "ddim", value_parser = parse_method)]
    pub method: model::Method,
    /// Score every n-th return-leg frame.
    #[arg(long, default_value_t = 8, value_parser = count(1, 10_000))]
    pub stride: usize,
    /// Frames predicted per denoiser call.
    #[arg(long, default_value_t = 16, value_parser = count(1, 1024))]
    pub batch: usize,
    /// Batch-1 predictions timed per row for the latency axis.
    #[arg(long, default_value_t = 20, value_parser = count(1, 10_000))]
    pub latency_calls: usize,
    /// Only the first n trajectories of the suite.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Add a condition whose poses come from this file in each trajectory folder
    /// (`scripts/visual_odometry.py` writes poses-vo.npy).
    #[arg(long)]
    pub vo: Option<String>,
    /// Only the noise-free condition and the two mildest noise levels.
    #[arg(long)]
    pub quick: bool,
    /// Frames generated per return leg in the rollouts under pose noise (0: none).
    #[arg(long, default_value_t = 40)]
    pub rollout_frames: usize,
    #[command(flatten)]
    pub runtime: Runtime,
    /// Folder for the saved conditions and study.json.
    #[arg(long, default_value = "runs/study")]
    pub out: PathBuf,
}

/// What a condition changes about the suite.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Change {
    Clean,
    Far { far: f64 },
    Noise { noise: PoseNoise },
    Poses { file: String },
}

/// Trade-off rows are grouped by what they vary, for the chart's legend.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
enum Group {
    Policy,
    KeepLast,
    Steps,
    Estimator,
    Far,
    Size,
    Reference,
}

#[derive(Clone)]
enum What {
    Model { model: usize, policy: Policy, steps: usize },
    Copy,
    Reproject,
}

#[derive(Clone)]
struct RowSpec {
    name: String,
    group: Group,
    what: What,
}

struct Condition {
    name: String,
    change: Change,
    rows: Vec<RowSpec>,
    /// Time each row (only where the condition can change the cost).
    timed: bool,
}

/// What fixes a condition's numbers; a saved one is reused only when it matches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Key {
    condition: String,
    change: Change,
    suite: String,
    trajectories: Vec<String>,
    rows: Vec<String>,
    models: Vec<Option<String>>,
    stride: usize,
    steps: Vec<Option<usize>>,
    method: String,
    batch: usize,
    /// Batch-1 predictions timed per row, on one intra-op thread.
    latency_calls: Option<usize>,
    #[serde(default)]
    latency_threads: Option<usize>,
    /// For poses read from files: a digest of every pose, so new estimates are never mistaken for old ones.
    poses_digest: Option<u64>,
}

#[derive(Serialize, Deserialize)]
struct Saved {
    key: Key,
    latency_ms: Vec<Option<f64>>,
    scores: Vec<TrajectoryScores>,
    /// Per selection policy, per trajectory, per target.
    agreement: Vec<(String, Vec<Vec<Agreement>>)>,
    /// Mean believed-pose error over every frame: (blocks, degrees).
    pose_error: (f64, f64),
    wall_s: f64,
}

const BOOTSTRAP_REPS: usize = 2000;
const NOISE_SEED: u64 = 0x5eed_0f_0d0;

/// The selection policies whose choice pose noise can change (and the two
/// recency policies, as a check that it changes nothing there).
fn selection_policies() -> Vec<(String, Policy)> {
    let mut out: Vec<(String, Policy)> = VARIANTS.iter().map(|n| (n.to_string(), variant_policy(n).expect("a variant"))).collect();
    out.push(("worldmem_greedy".into(), Policy::preset(PolicyKind::WorldMemGreedy)));
    out
}

fn noise_conditions(quick: bool, vo: &Option<String>) -> Vec<(String, Change)> {
    let independent = |t: f64, r: f64| Change::Noise { noise: PoseNoise::Independent { translation: t, rotation_deg: r } };
    let mut out = vec![("translation σ 0.25".to_string(), independent(0.25, 0.0)), ("rotation σ 2.5°".into(), independent(0.0, 2.5))];
    if !quick {
        out.extend([
            ("translation σ 0.5".to_string(), independent(0.5, 0.0)),
            ("translation σ 1".into(), independent(1.0, 0.0)),
            ("rotation σ 5°".into(), independent(0.0, 5.0)),
            ("rotation σ 10°".into(), independent(0.0, 10.0)),
            ("drift 0.02/step, 0.2°/step".into(), Change::Noise { noise: PoseNoise::Drift { translation: 0.02, rotation_deg: 0.2 } }),
        ]);
    }
    if let Some(file) = vo {
        out.push((format!("estimated poses ({file})"), Change::Poses { file: file.clone() }));
    }
    out
}

/// The suite as a condition sees it.
fn transform(traj: &Trajectory, change: &Change, suite: &Path, index: usize) -> Result<Trajectory> {
    let mut t = traj.clone();
    match change {
        Change::Clean => {}
        Change::Far { far } => t.intrinsics = traj.intrinsics.with_range(traj.intrinsics.near, *far).context("far")?,
        Change::Noise { noise } => t.poses = eval::noise::apply(&traj.poses, *noise, NOISE_SEED ^ (index as u64).wrapping_mul(0x9e37_79b9)),
        Change::Poses { file } => t.poses = traj.believed_poses(suite, file)?,
    }
    Ok(t)
}

pub fn run(o: &Options) -> Result<()> {
    if o.stride == 0 || o.batch == 0 {
        bail!("--stride and --batch must be at least 1");
    }
    let trajectories = eval::suite::load(&o.suite, o.limit)?;
    if let Some(file) = &o.vo {
        // Fail before hours of work, naming the first trajectory without the file.
        for t in &trajectories {
            t.believed_poses(&o.suite, file).with_context(|| format!("--vo {file}"))?;
        }
    }
    let mut models: Vec<(String, Model)> = Vec::new();
    for name in VARIANTS {
        let dir = o.models.join(name);
        if !dir.join("manifest.json").exists() {
            bail!("--models: {} has no {name}/ model folder; the study runs every trained variant", o.models.display());
        }
        models.push((name.to_string(), load(&dir, o.runtime.options())?));
    }
    for (name, dir) in &o.extra {
        models.push((name.clone(), load(dir, o.runtime.options())?));
    }
    let one_thread = RuntimeOptions { threads: 1, ..o.runtime.options() };
    let timing: Vec<(String, Model)> = models.iter().map(|(n, m)| Ok((n.clone(), load(m.dir(), one_thread)?))).collect::<Result<_>>()?;
    let model_index = |name: &str| models.iter().position(|m| m.0 == name).expect("loaded above");
    let variant = |name: &str, group| RowSpec {
        name: name.into(),
        group,
        what: What::Model { model: model_index(name), policy: variant_policy(name).expect("a variant"), steps: o.steps },
    };
    let wp = model_index("worldpack");
    let wp_policy = Policy::preset(PolicyKind::WorldPack);
    let references = [RowSpec { name: "copy".into(), group: Group::Reference, what: What::Copy }, RowSpec { name: "reproject".into(), group: Group::Reference, what: What::Reproject }];
    let mut variants: Vec<RowSpec> = VARIANTS[..4].iter().map(|n| variant(n, Group::Policy)).collect();
    variants.push(variant("worldpack_keep_last", Group::KeepLast));

    // WorldMem's greedy coverage runs with the memory-retrieval weights (both fill 4 full-rate slots).
    variants.push(RowSpec {
        name: "worldmem_greedy".into(),
        group: Group::Policy,
        what: What::Model { model: model_index("memory_retrieval"), policy: Policy::preset(PolicyKind::WorldMemGreedy), steps: o.steps },
    });
    // The noise-free condition carries every speed/accuracy point.
    let mut clean = variants.clone();
    // Step counts for the paper's WorldPack and for the variant that keeps the newest frame.
    for name in ["worldpack", "worldpack_keep_last"] {
        for &s in o.sweep_steps.iter().filter(|&&s| s != o.steps) {
            let what = What::Model { model: model_index(name), policy: variant_policy(name).expect("a variant"), steps: s };
            clean.push(RowSpec { name: format!("{name}, {s} steps"), group: Group::Steps, what });
        }
    }
    for samples in [1000, 10_000] {
        let policy = Policy { estimator: Estimator::MonteCarlo(MonteCarlo { samples, seed: 0 }), ..wp_policy.clone() };
        clean.push(RowSpec { name: format!("worldpack, Monte Carlo {samples}"), group: Group::Estimator, what: What::Model { model: wp, policy, steps: o.steps } });
    }
    for (name, _) in &o.extra {
        let model = model_index(name);
        clean.push(RowSpec { name: name.clone(), group: Group::Size, what: What::Model { model, policy: models[model].1.trained_policy(), steps: o.steps } });
    }
    clean.extend(references.clone());

    let mut conditions = vec![Condition { name: "clean".into(), change: Change::Clean, rows: clean, timed: true }];
    if !o.quick {
        for far in [15.0, 60.0] {
            let row = RowSpec { name: format!("worldpack, far {far}"), group: Group::Far, what: What::Model { model: wp, policy: wp_policy.clone(), steps: o.steps } };
            conditions.push(Condition { name: format!("far {far}"), change: Change::Far { far }, rows: vec![row], timed: true });
        }
    }
    for (name, change) in noise_conditions(o.quick, &o.vo) {
        let mut rows = variants.clone();
        rows.extend(references.clone());
        conditions.push(Condition { name, change, rows, timed: false });
    }

    let model_keys: Vec<String> = models.iter().map(|(_, m)| model_key(m.dir())).collect::<Result<_, _>>()?;
    let dir = o.out.join("conditions");
    std::fs::create_dir_all(&dir).with_context(|| format!("--out {}", o.out.display()))?;
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.stride).len()).sum();
    eprintln!("study: {} trajectories, {} return-leg targets, {} conditions, {} {:?} steps", trajectories.len(), targets, conditions.len(), o.steps, o.method);

    let mut latents: HashMap<(usize, usize), Rc<Vec<Vec<f32>>>> = HashMap::new();
    let mut results: Vec<(Condition, Saved)> = Vec::new();
    for (ci, c) in conditions.into_iter().enumerate() {
        let key = Key {
            condition: c.name.clone(),
            change: c.change.clone(),
            suite: o.suite.display().to_string(),
            trajectories: trajectories.iter().map(|t| t.entry.dir.clone()).collect(),
            rows: c.rows.iter().map(|r| r.name.clone()).collect(),
            models: c.rows.iter().map(|r| if let What::Model { model, .. } = r.what { Some(model_keys[model].clone()) } else { None }).collect(),
            stride: o.stride,
            steps: c.rows.iter().map(|r| if let What::Model { steps, .. } = r.what { Some(steps) } else { None }).collect(),
            method: format!("{:?}", o.method).to_lowercase(),
            batch: o.batch,
            latency_calls: c.timed.then_some(o.latency_calls),
            latency_threads: c.timed.then_some(1),
            poses_digest: match &c.change {
                Change::Poses { file } => Some(poses_digest(&trajectories, &o.suite, file)?),
                _ => None,
            },
        };
        let path = dir.join(format!("{ci:02}.json"));
        if let Some(saved) = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<Saved>(&t).ok()).filter(|s| s.key == key) {
            eprintln!("study: {} reused from {}", c.name, path.display());
            results.push((c, saved));
            continue;
        }
        let saved = run_condition(o, &c, key, &trajectories, &models, &timing, &mut latents)?;
        std::fs::write(&path, serde_json::to_string(&saved)?).with_context(|| format!("writing {}", path.display()))?;
        results.push((c, saved));
    }

    let rollouts = if o.rollout_frames > 0 { noisy_rollouts(o, &results, &trajectories, &models, &mut latents)? } else { Vec::new() };

    let strata: Vec<Vec<TargetFeatures>> = trajectories.iter().map(|t| features(t, &t.return_frames(o.stride))).collect::<Result<_, _>>()?;
    let summary = summarise(&results, &strata, &models);
    print(&summary);
    let rollout_summary = summarise_rollouts(&rollouts);
    let path = o.out.join("study.json");
    let json = serde_json::json!({
        "format": "worldpack-study/1",
        "suite": o.suite,
        "models": o.models,
        "trajectories": trajectories.len(),
        "targets": targets,
        "stride": o.stride,
        "sampler": { "method": format!("{:?}", o.method).to_lowercase(), "steps": o.steps },
        "bootstrap": { "reps": BOOTSTRAP_REPS, "resampled": "trajectories", "level": 0.95 },
        "tradeoff": summary.tradeoff,
        "noise": summary.noise,
        "strata": summary.strata,
        "rollouts": rollout_summary,
        "rollout_frames": o.rollout_frames,
        "wall_s": results.iter().map(|(c, s)| (c.name.clone(), s.wall_s)).collect::<Vec<_>>(),
    });
    std::fs::write(&path, serde_json::to_string_pretty(&json)?).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

/// FNV-1a over the bits of every pose in `file` across the suite.
fn poses_digest(trajectories: &[Trajectory], suite: &Path, file: &str) -> Result<u64> {
    let mut h = FNV_START;
    for t in trajectories {
        for p in t.believed_poses(suite, file)? {
            for v in p.matrix_rows().as_flattened() {
                h = fnv1a(h, &v.to_bits().to_le_bytes());
            }
        }
    }
    Ok(h)
}

/// The probe rows of a condition, running on `models`.
fn build_rows<'m>(c: &Condition, models: &'m [(String, Model)], method: Method) -> Result<Vec<Row<'m>>> {
    c.rows
        .iter()
        .map(|r| {
            let predictor = match &r.what {
                What::Model { model, policy, steps } => {
                    let m = &models[*model].1;
                    Predictor::Model { model: m, policy: policy.clone(), sampler: Sampler::new(&m.manifest().diffusion, *steps, method, 0.0)? }
                }
                What::Copy => Predictor::Copy,
                What::Reproject => Predictor::Reproject,
            };
            Ok(Row { name: r.name.clone(), predictor })
        })
        .collect()
}

/// Trajectory `ti`'s latents under model `mi`, encoded once. Latents depend
/// on the frames only, never on the poses, so every condition shares them.
fn cached_latents(
    cache: &mut HashMap<(usize, usize), Rc<Vec<Vec<f32>>>>,
    ti: usize,
    traj: &Trajectory,
    models: &[(String, Model)],
    mi: usize,
) -> Result<Rc<Vec<Vec<f32>>>, ProbeError> {
    if let Some(l) = cache.get(&(ti, mi)) {
        return Ok(l.clone());
    }
    let l = Rc::new(encode_all(&models[mi].1, traj)?);
    cache.insert((ti, mi), l.clone());
    Ok(l)
}

/// `timing` holds the same models with one intra-op thread: on this 2-core
/// machine one batch-1 prediction was both faster and far steadier on one
/// thread (10-step rows: 28–33 ms against 31–57 ms on two).
fn run_condition(
    o: &Options,
    c: &Condition,
    key: Key,
    trajectories: &[Trajectory],
    models: &[(String, Model)],
    timing: &[(String, Model)],
    latents: &mut HashMap<(usize, usize), Rc<Vec<Vec<f32>>>>,
) -> Result<Saved> {
    let start = Instant::now();
    let rows = build_rows(c, models, o.method)?;
    let model_of = |m: &Model| models.iter().position(|(_, x)| std::ptr::eq(x, m)).expect("a loaded model");
    let mut latents_of = |ti: usize, traj: &Trajectory, m: &Model| cached_latents(latents, ti, traj, models, model_of(m));

    let mut latency = vec![None; rows.len()];
    if c.timed {
        let first = transform(&trajectories[0], &c.change, &o.suite, 0)?;
        for (i, (row, spec)) in build_rows(c, timing, o.method)?.iter().zip(&c.rows).enumerate() {
            let l = match &spec.what {
                What::Model { model, .. } => latents_of(0, &first, &models[*model].1)?,
                _ => Rc::default(),
            };
            latency[i] = Some(latency_ms(&first, row, &l, o.latency_calls)?);
        }
    }

    let settings = Settings { stride: o.stride, batch: o.batch, seed: 20261121 };
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.stride).len()).sum();
    let progress = bar(targets * rows.len(), &format!("study: {}", c.name));
    let policies = selection_policies();
    let mut scores = Vec::new();
    let mut agreement: Vec<(String, Vec<Vec<Agreement>>)> = policies.iter().map(|(n, _)| (n.clone(), Vec::new())).collect();
    let (mut err_d, mut err_r, mut frames) = (0.0, 0.0, 0usize);
    for (ti, traj) in trajectories.iter().enumerate() {
        progress.set_message(traj.entry.dir.clone());
        let seen = transform(traj, &c.change, &o.suite, ti)?;
        scores.push(probe_trajectory(&seen, &rows, &settings, &mut |m| latents_of(ti, traj, m), &|n| progress.inc(n as u64))?);
        if matches!(c.change, Change::Noise { .. } | Change::Poses { .. }) {
            let (truth, believed) = (traj.frusta()?, seen.frusta()?);
            let at = traj.return_frames(o.stride);
            for ((_, policy), (_, out)) in policies.iter().zip(agreement.iter_mut()) {
                out.push(selection_agreement(policy, &truth, &believed, &at));
            }
            let (d, r) = pose_error(&traj.poses, &seen.poses);
            err_d += d * traj.len() as f64;
            err_r += r * traj.len() as f64;
            frames += traj.len();
        }
    }
    progress.finish();
    if frames == 0 {
        agreement.clear();
    }
    let n = frames.max(1) as f64;
    Ok(Saved { key, latency_ms: latency, scores, agreement, pose_error: (err_d / n, err_r / n), wall_s: start.elapsed().as_secs_f64() })
}

/// Rows and conditions of the noisy rollouts: autoregressive generation of
/// the first frames of each return leg, where a wrong pose compounds.
const ROLLOUT_ROWS: [&str; 8] =
    ["baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldpack_keep_last", "worldmem_greedy", "copy", "reproject"];
const ROLLOUT_CONDITIONS: [&str; 4] = ["clean", "translation σ 0.5", "rotation σ 5°", "drift 0.02/step, 0.2°/step"];

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RolloutKey {
    condition: Key,
    rows: Vec<String>,
    frames: usize,
}

#[derive(Serialize, Deserialize)]
struct SavedRollout {
    key: RolloutKey,
    /// Per row, per trajectory, per generated frame.
    scores: Vec<Vec<Vec<FrameScore>>>,
    wall_s: f64,
}

fn noisy_rollouts(
    o: &Options,
    results: &[(Condition, Saved)],
    trajectories: &[Trajectory],
    models: &[(String, Model)],
    latents: &mut HashMap<(usize, usize), Rc<Vec<Vec<f32>>>>,
) -> Result<Vec<(String, SavedRollout)>> {
    let dir = o.out.join("rollouts");
    std::fs::create_dir_all(&dir).with_context(|| format!("--out {}", o.out.display()))?;
    let mut out = Vec::new();
    for (ci, (c, saved)) in results.iter().enumerate() {
        let wanted = ROLLOUT_CONDITIONS.contains(&c.name.as_str()) || matches!(c.change, Change::Poses { .. });
        if !wanted {
            continue;
        }
        let specs: Vec<&RowSpec> = ROLLOUT_ROWS.iter().filter_map(|n| c.rows.iter().find(|r| r.name == *n)).collect();
        let key = RolloutKey { condition: saved.key.clone(), rows: specs.iter().map(|r| r.name.clone()).collect(), frames: o.rollout_frames };
        let path = dir.join(format!("{ci:02}.json"));
        if let Some(s) = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<SavedRollout>(&t).ok()).filter(|s| s.key == key) {
            eprintln!("study: rollouts under {} reused from {}", c.name, path.display());
            out.push((c.name.clone(), s));
            continue;
        }
        let start = Instant::now();
        let seen: Vec<Trajectory> = trajectories.iter().enumerate().map(|(i, t)| transform(t, &c.change, &o.suite, i)).collect::<Result<_>>()?;
        let sub = Condition { name: c.name.clone(), change: c.change.clone(), rows: specs.iter().map(|r| (*r).clone()).collect(), timed: false };
        let rows = build_rows(&sub, models, o.method)?;
        let frames: usize = seen.iter().map(|t| eval::rollout::rollout_frames(t, Some(o.rollout_frames)).len()).sum();
        let progress = bar(frames * rows.len(), &format!("study rollouts: {}", c.name));
        let scorer = eval::rollout::Scorer { lpips: None, dreamsim: None, keep_frames: false };
        let mut scores = Vec::new();
        for (row, spec) in rows.iter().zip(&sub.rows) {
            let observed: Vec<Vec<Vec<f32>>> = match &spec.what {
                What::Model { model, .. } => (0..seen.len())
                    .map(|ti| Ok(cached_latents(latents, ti, &trajectories[ti], models, *model)?.as_ref().clone()))
                    .collect::<Result<_, ProbeError>>()?,
                _ => vec![Vec::new(); seen.len()],
            };
            let r = eval::rollout::rollout(&seen, row, &observed, Some(o.rollout_frames), o.batch, 20261121, &scorer, &|n| progress.inc(n as u64))?;
            scores.push(r.scores);
        }
        progress.finish();
        let s = SavedRollout { key, scores, wall_s: start.elapsed().as_secs_f64() };
        std::fs::write(&path, serde_json::to_string(&s)?).with_context(|| format!("writing {}", path.display()))?;
        out.push((c.name.clone(), s));
    }
    Ok(out)
}

#[derive(Serialize)]
struct RolloutRow {
    row: String,
    psnr: f64,
    /// Against the same row's noise-free rollout, frame by frame.
    psnr_vs_clean: Option<Interval>,
}

#[derive(Serialize)]
struct RolloutCondition {
    condition: String,
    frames: usize,
    wall_s: f64,
    rows: Vec<RolloutRow>,
}

fn summarise_rollouts(all: &[(String, SavedRollout)]) -> Vec<RolloutCondition> {
    let Some((_, clean)) = all.iter().find(|(n, _)| n == "clean") else { return Vec::new() };
    all.iter()
        .map(|(name, s)| RolloutCondition {
            condition: name.clone(),
            frames: s.scores.first().map_or(0, |r| r.iter().map(Vec::len).sum()),
            wall_s: s.wall_s,
            rows: s
                .key
                .rows
                .iter()
                .enumerate()
                .map(|(i, row)| {
                    let flat: Vec<f64> = s.scores[i].iter().flatten().map(|f| f.psnr).collect();
                    let j = clean.key.rows.iter().position(|r| r == row);
                    let vs = j.filter(|_| name != "clean").map(|j| {
                        let diffs: Vec<Vec<f64>> = s.scores[i].iter().zip(&clean.scores[j]).map(|(a, b)| a.iter().zip(b).map(|(x, y)| x.psnr - y.psnr).collect()).collect();
                        cluster_bootstrap(&diffs, BOOTSTRAP_REPS, 17)
                    });
                    RolloutRow { row: row.clone(), psnr: mean_std(&flat).0, psnr_vs_clean: vs }
                })
                .collect(),
        })
        .collect()
}

#[derive(Serialize)]
struct TradeoffPoint {
    name: String,
    group: Group,
    condition: String,
    latency_ms: f64,
    psnr: f64,
    ssim: f64,
    psnr_vs_baseline: Interval,
    parameters: Option<u64>,
    steps: Option<usize>,
    /// No other point is both at least as fast and at least as accurate (and better in one).
    pareto: bool,
}

#[derive(Serialize)]
struct NoiseRow {
    row: String,
    psnr: f64,
    /// Against the same row without noise, frame by frame.
    psnr_vs_clean: Interval,
}

#[derive(Serialize)]
struct NoiseSelection {
    policy: String,
    jaccard: f64,
    rank: f64,
}

#[derive(Serialize)]
struct NoiseCondition {
    condition: String,
    change: Change,
    pose_error_blocks: f64,
    pose_error_deg: f64,
    rows: Vec<NoiseRow>,
    selection: Vec<NoiseSelection>,
}

#[derive(Serialize)]
struct StratumRow {
    row: String,
    psnr: f64,
    psnr_vs_baseline: Option<Interval>,
    /// Against Nearest Frame Packing: the same 22-frame packing chosen by
    /// recency, so what geometric selection adds (the paper's TP-only control).
    psnr_vs_recency: Option<Interval>,
}

#[derive(Serialize)]
struct StratumSummary {
    stratum: &'static str,
    description: &'static str,
    targets: usize,
    trajectories: usize,
    rows: Vec<StratumRow>,
}

struct Summary {
    tradeoff: Vec<TradeoffPoint>,
    noise: Vec<NoiseCondition>,
    strata: Vec<StratumSummary>,
}

/// Per-trajectory paired differences of row `a` in `x` and row `b` in `y`,
/// over the targets that `keep` selects.
fn paired(x: &[TrajectoryScores], a: usize, y: &[TrajectoryScores], b: usize, keep: &dyn Fn(usize, &FrameScore) -> bool) -> Vec<Vec<f64>> {
    x.iter()
        .zip(y)
        .enumerate()
        .map(|(ti, (tx, ty))| tx.rows[a].iter().zip(&ty.rows[b]).filter(|(f, _)| keep(ti, f)).map(|(f, g)| f.psnr - g.psnr).collect())
        .collect()
}

fn column(x: &[TrajectoryScores], a: usize, metric: fn(&FrameScore) -> f64, keep: &dyn Fn(usize, &FrameScore) -> bool) -> Vec<f64> {
    x.iter().enumerate().flat_map(|(ti, t)| t.rows[a].iter().filter(move |f| keep(ti, f)).map(metric)).collect()
}

fn summarise(results: &[(Condition, Saved)], strata: &[Vec<TargetFeatures>], models: &[(String, Model)]) -> Summary {
    let all = |_: usize, _: &FrameScore| true;
    let (clean_c, clean) = &results[0];
    let row_index = |c: &Condition, name: &str| c.rows.iter().position(|r| r.name == name);
    let base = row_index(clean_c, "baseline").expect("the clean condition runs the baseline");
    let recency = row_index(clean_c, "nearest_frame_packing").expect("the clean condition runs nearest frame packing");

    let mut tradeoff: Vec<TradeoffPoint> = Vec::new();
    for (c, s) in results.iter().filter(|(c, _)| c.timed) {
        for (i, r) in c.rows.iter().enumerate() {
            let (parameters, steps) = match &r.what {
                What::Model { model, steps, .. } => (models[*model].1.manifest().denoiser.parameters, Some(*steps)),
                _ => (None, None),
            };
            tradeoff.push(TradeoffPoint {
                name: r.name.clone(),
                group: r.group,
                condition: c.name.clone(),
                latency_ms: s.latency_ms[i].unwrap_or(f64::NAN),
                psnr: mean_std(&column(&s.scores, i, |f| f.psnr, &all)).0,
                ssim: mean_std(&column(&s.scores, i, |f| f.ssim, &all)).0,
                psnr_vs_baseline: cluster_bootstrap(&paired(&s.scores, i, &clean.scores, base, &all), BOOTSTRAP_REPS, 3),
                parameters,
                steps,
                pareto: false,
            });
        }
    }
    let dominated = |p: &TradeoffPoint, q: &TradeoffPoint| q.latency_ms <= p.latency_ms && q.psnr >= p.psnr && (q.latency_ms < p.latency_ms || q.psnr > p.psnr);
    let front: Vec<bool> = tradeoff.iter().map(|p| !tradeoff.iter().any(|q| dominated(p, q))).collect();
    for (p, f) in tradeoff.iter_mut().zip(front) {
        p.pareto = f;
    }

    let noise = results
        .iter()
        .filter(|(c, _)| matches!(c.change, Change::Noise { .. } | Change::Poses { .. }))
        .map(|(c, s)| NoiseCondition {
            condition: c.name.clone(),
            change: c.change.clone(),
            pose_error_blocks: s.pose_error.0,
            pose_error_deg: s.pose_error.1,
            rows: c
                .rows
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    let j = row_index(clean_c, &r.name).expect("noise rows also run clean");
                    NoiseRow {
                        row: r.name.clone(),
                        psnr: mean_std(&column(&s.scores, i, |f| f.psnr, &all)).0,
                        psnr_vs_clean: cluster_bootstrap(&paired(&s.scores, i, &clean.scores, j, &all), BOOTSTRAP_REPS, 5),
                    }
                })
                .collect(),
            selection: s
                .agreement
                .iter()
                .map(|(policy, per)| {
                    let flat: Vec<&Agreement> = per.iter().flatten().collect();
                    let ranks: Vec<f64> = flat.iter().filter_map(|a| a.rank).collect();
                    NoiseSelection {
                        policy: policy.clone(),
                        jaccard: mean_std(&flat.iter().map(|a| a.jaccard).collect::<Vec<_>>()).0,
                        rank: mean_std(&ranks).0,
                    }
                })
                .collect(),
        })
        .collect();

    let strata = Stratum::ALL
        .iter()
        .map(|&st| {
            let keep = |ti: usize, f: &FrameScore| strata[ti].iter().find(|x| x.t == f.t).is_some_and(|x| st.contains(x));
            let count = column(&clean.scores, base, |f| f.psnr, &keep).len();
            let trajectories = strata.iter().filter(|s| s.iter().any(|x| st.contains(x))).count();
            StratumSummary {
                stratum: st.name(),
                description: st.describe(),
                targets: count,
                trajectories,
                rows: clean_c
                    .rows
                    .iter()
                    .enumerate()
                    .filter(|(_, r)| matches!(r.group, Group::Policy | Group::KeepLast | Group::Size | Group::Reference))
                    .map(|(i, r)| StratumRow {
                        row: r.name.clone(),
                        psnr: mean_std(&column(&clean.scores, i, |f| f.psnr, &keep)).0,
                        psnr_vs_baseline: (i != base && count > 0).then(|| cluster_bootstrap(&paired(&clean.scores, i, &clean.scores, base, &keep), BOOTSTRAP_REPS, 9)),
                        psnr_vs_recency: (matches!(r.group, Group::Policy | Group::KeepLast) && i != base && i != recency && count > 0)
                            .then(|| cluster_bootstrap(&paired(&clean.scores, i, &clean.scores, recency, &keep), BOOTSTRAP_REPS, 10)),
                    })
                    .collect(),
            }
        })
        .collect();
    Summary { tradeoff, noise, strata }
}

fn interval(i: &Interval) -> String {
    format!("{:+.2} [{:+.2}, {:+.2}]", i.mean, i.lo, i.hi)
}

fn print(s: &Summary) {
    println!("\nSpeed against accuracy (noise-free; PSNR on return-leg targets; Δ vs the baseline, 95% over trajectories)");
    println!("{:<32} {:>10} {:>8} {:>7} {:>24} {:>7}", "row", "ms/frame", "PSNR", "SSIM", "ΔPSNR vs baseline", "front");
    for p in &s.tradeoff {
        println!("{:<32} {:>10.2} {:>8.2} {:>7.3} {:>24} {:>7}", p.name, p.latency_ms, p.psnr, p.ssim, interval(&p.psnr_vs_baseline), if p.pareto { "*" } else { "" });
    }
    println!("\nPose noise: PSNR change against the same row without noise; selection agreement with the noise-free selection");
    for c in &s.noise {
        println!("{} (mean pose error {:.2} blocks, {:.2}°)", c.condition, c.pose_error_blocks, c.pose_error_deg);
        for r in &c.rows {
            println!("  {:<28} {:>7.2} dB  {}", r.row, r.psnr, interval(&r.psnr_vs_clean));
        }
        for a in &c.selection {
            println!("  selection {:<20} Jaccard {:.3}  rank ρ {:.3}", a.policy, a.jaccard, a.rank);
        }
    }
    println!("\nWhere methods fail (noise-free): PSNR, Δ vs the baseline and Δ vs nearest frame packing per stratum");
    for st in &s.strata {
        println!("{} — {} ({} targets, {} trajectories)", st.stratum, st.description, st.targets, st.trajectories);
        for r in &st.rows {
            let vs = |i: &Option<Interval>| i.as_ref().map_or("—".into(), interval);
            println!("  {:<28} {:>7.2}  {:>24}  vs NFP {}", r.row, r.psnr, vs(&r.psnr_vs_baseline), vs(&r.psnr_vs_recency));
        }
    }
}

fn load(dir: &Path, runtime: model::RuntimeOptions) -> Result<Model> {
    Model::load(dir, runtime).with_context(|| format!("loading the model in {}", dir.display()))
}
