//! The study behind `worldpack study`: speed against accuracy, stability under pose noise,
//! and the places where methods fail (docs/cli.md; `./scripts/results.sh` with STUDY=1).
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

use crate::noise::{Agreement, PoseNoise, pose_error, selection_agreement};
use crate::probe::{FrameScore, Predictor, ProbeError, Row, Settings as ProbeSettings, SharedLatents, TrajectoryScores, encode_all, latency_ms, probe_trajectory};
use crate::stats::{Interval, cluster_bootstrap, mean_std};
use crate::strata::{Stratum, TargetFeatures, features};
use crate::suite::Trajectory;
use memory::overlap::MonteCarlo;
use memory::{Estimator, Policy, PolicyKind};
use model::{Method, Model, RuntimeOptions, Sampler};
use serde::{Deserialize, Serialize};

use crate::digest::{FNV_START, fnv1a, model_key};
use crate::memory_probe::{Settings as ProbeRun, VARIANTS, variant_policy};
use crate::program::{ProgramError, io, load_model, setting, write_atomically};

type Result<T, E = ProgramError> = std::result::Result<T, E>;

/// What one study does; `worldpack study`'s flags, one field each.
#[derive(Clone, Debug)]
pub struct Settings {
    /// The probe every condition runs: suite, models (all five variants), extra models, sampler,
    /// stride, batch, latency calls, limit, runtime; its `out` is unused.
    pub probe: ProbeRun,
    /// A condition whose poses come from this file in each trajectory folder.
    pub vo: Option<String>,
    /// Only the noise-free condition and the two mildest noise levels.
    pub quick: bool,
    /// Frames generated per return leg in the rollouts under pose noise (0: none).
    pub rollout_frames: usize,
    /// Folder for the saved conditions and study.json.
    pub out: PathBuf,
}

/// What the study is doing, for a progress display.
pub enum Progress<'a> {
    Started { trajectories: usize, targets: usize, conditions: usize },
    /// A condition (or its rollouts) saved earlier with the same settings is reused.
    Reused { what: &'a str, path: &'a Path },
    /// Work on `what` begins: `total` predictions.
    Begin { what: &'a str, total: usize },
    Trajectory(&'a str),
    /// `n` more predictions are done.
    Predictions(usize),
    End,
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
pub enum Group {
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
const NOISE_SEED: u64 = 0x5eed0f0d0;

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
        Change::Far { far } => t.intrinsics = traj.intrinsics.with_range(traj.intrinsics.near, *far).map_err(|e| setting("far", e.to_string()))?,
        Change::Noise { noise } => t.poses = crate::noise::apply(&traj.poses, *noise, NOISE_SEED ^ (index as u64).wrapping_mul(0x9e37_79b9)),
        Change::Poses { file } => t.poses = traj.believed_poses(suite, file)?,
    }
    Ok(t)
}

pub fn study(o: &Settings, progress: &dyn Fn(Progress)) -> Result<Summary> {
    if o.probe.stride == 0 || o.probe.batch == 0 {
        return Err(setting("--stride", "--stride and --batch must be at least 1"));
    }
    let trajectories = crate::suite::load(&o.probe.suite, o.probe.limit)?;
    if let Some(file) = &o.vo {
        // Fail before hours of work, naming the first trajectory without the file.
        for t in &trajectories {
            t.believed_poses(&o.probe.suite, file).map_err(|e| setting("--vo", format!("{file}: {e}")))?;
        }
    }
    let mut models: Vec<(String, Model)> = Vec::new();
    for name in VARIANTS {
        let dir = o.probe.models.join(name);
        if !dir.join("manifest.json").exists() {
            return Err(setting("--models", format!("{} has no {name}/ model folder; the study runs every trained variant", o.probe.models.display())));
        }
        models.push((name.to_string(), load(&dir, o.probe.runtime)?));
    }
    for (name, dir) in &o.probe.extra {
        models.push((name.clone(), load(dir, o.probe.runtime)?));
    }
    let one_thread = RuntimeOptions { threads: 1, ..o.probe.runtime };
    let timing: Vec<(String, Model)> = models.iter().map(|(n, m)| Ok((n.clone(), load(m.dir(), one_thread)?))).collect::<Result<_>>()?;
    let model_index = |name: &str| models.iter().position(|m| m.0 == name).expect("loaded above");
    let variant = |name: &str, group| RowSpec {
        name: name.into(),
        group,
        what: What::Model { model: model_index(name), policy: variant_policy(name).expect("a variant"), steps: o.probe.steps },
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
        what: What::Model { model: model_index("memory_retrieval"), policy: Policy::preset(PolicyKind::WorldMemGreedy), steps: o.probe.steps },
    });
    // The noise-free condition carries every speed/accuracy point.
    let mut clean = variants.clone();
    // Step counts for the paper's WorldPack and for the variant that keeps the newest frame.
    for name in ["worldpack", "worldpack_keep_last"] {
        for &s in o.probe.sweep_steps.iter().filter(|&&s| s != o.probe.steps) {
            let what = What::Model { model: model_index(name), policy: variant_policy(name).expect("a variant"), steps: s };
            clean.push(RowSpec { name: format!("{name}, {s} steps"), group: Group::Steps, what });
        }
    }
    for samples in [1000, 10_000] {
        let policy = Policy { estimator: Estimator::MonteCarlo(MonteCarlo { samples, seed: 0 }), ..wp_policy.clone() };
        clean.push(RowSpec { name: format!("worldpack, Monte Carlo {samples}"), group: Group::Estimator, what: What::Model { model: wp, policy, steps: o.probe.steps } });
    }
    // Extra models (other sizes, other training) run in every condition, pose noise included.
    let extras: Vec<RowSpec> = o
        .probe
        .extra
        .iter()
        .map(|(name, _)| {
            let model = model_index(name);
            RowSpec { name: name.clone(), group: Group::Size, what: What::Model { model, policy: models[model].1.trained_policy(), steps: o.probe.steps } }
        })
        .collect();
    clean.extend(extras.clone());
    clean.extend(references.clone());

    let mut conditions = vec![Condition { name: "clean".into(), change: Change::Clean, rows: clean, timed: true }];
    if !o.quick {
        for far in [15.0, 60.0] {
            let row = RowSpec { name: format!("worldpack, far {far}"), group: Group::Far, what: What::Model { model: wp, policy: wp_policy.clone(), steps: o.probe.steps } };
            conditions.push(Condition { name: format!("far {far}"), change: Change::Far { far }, rows: vec![row], timed: true });
        }
    }
    for (name, change) in noise_conditions(o.quick, &o.vo) {
        let mut rows = variants.clone();
        rows.extend(extras.clone());
        rows.extend(references.clone());
        conditions.push(Condition { name, change, rows, timed: false });
    }

    for (a, b) in &o.probe.contrasts {
        for name in [a, b] {
            if !conditions[0].rows.iter().any(|r| &r.name == name) {
                let names: Vec<&str> = conditions[0].rows.iter().map(|r| r.name.as_str()).collect();
                return Err(setting("--contrast", format!("no row called {name:?}; the rows are {}", names.join(", "))));
            }
        }
    }

    let model_keys: Vec<String> = models.iter().map(|(_, m)| model_key(m.dir()).map_err(io(m.dir()))).collect::<Result<_>>()?;
    let dir = o.out.join("conditions");
    std::fs::create_dir_all(&dir).map_err(io(&o.out))?;
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.probe.stride).len()).sum();
    progress(Progress::Started { trajectories: trajectories.len(), targets, conditions: conditions.len() });

    let mut latents: HashMap<(usize, usize), SharedLatents> = HashMap::new();
    let mut results: Vec<(Condition, Saved)> = Vec::new();
    for (ci, c) in conditions.into_iter().enumerate() {
        let key = Key {
            condition: c.name.clone(),
            change: c.change.clone(),
            suite: o.probe.suite.display().to_string(),
            trajectories: trajectories.iter().map(|t| t.entry.dir.clone()).collect(),
            rows: c.rows.iter().map(|r| r.name.clone()).collect(),
            models: c.rows.iter().map(|r| if let What::Model { model, .. } = r.what { Some(model_keys[model].clone()) } else { None }).collect(),
            stride: o.probe.stride,
            steps: c.rows.iter().map(|r| if let What::Model { steps, .. } = r.what { Some(steps) } else { None }).collect(),
            method: o.probe.method.name().into(),
            batch: o.probe.batch,
            latency_calls: c.timed.then_some(o.probe.latency_calls),
            latency_threads: c.timed.then_some(1),
            poses_digest: match &c.change {
                Change::Poses { file } => Some(poses_digest(&trajectories, &o.probe.suite, file)?),
                _ => None,
            },
        };
        let path = dir.join(format!("{ci:02}.json"));
        if let Some(saved) = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<Saved>(&t).ok()).filter(|s| s.key == key) {
            progress(Progress::Reused { what: &c.name, path: &path });
            results.push((c, saved));
            continue;
        }
        let saved = run_condition(o, &c, key, &trajectories, &models, &timing, &mut latents, progress)?;
        write_atomically(&path, &serde_json::to_string(&saved)?)?;
        results.push((c, saved));
    }

    let rollouts = if o.rollout_frames > 0 { noisy_rollouts(o, &results, &trajectories, &models, &mut latents, progress)? } else { Vec::new() };

    let strata: Vec<Vec<TargetFeatures>> = trajectories.iter().map(|t| features(t, &t.return_frames(o.probe.stride))).collect::<Result<_, _>>()?;
    let parameters: Vec<Option<u64>> = models.iter().map(|(_, m)| m.manifest().denoiser.parameters).collect();
    let summary = summarise(&results, &strata, &parameters, summarise_rollouts(&rollouts), &o.probe.contrasts);
    let path = o.out.join("study.json");
    let json = serde_json::json!({
        "format": "worldpack-study/1",
        "suite": o.probe.suite,
        "models": o.probe.models,
        "trajectories": trajectories.len(),
        "targets": targets,
        "stride": o.probe.stride,
        "sampler": { "method": o.probe.method.name(), "steps": o.probe.steps },
        "bootstrap": { "reps": BOOTSTRAP_REPS, "resampled": "trajectories", "level": 0.95 },
        "tradeoff": summary.tradeoff,
        "noise": summary.noise,
        "contrasts": summary.contrasts,
        "strata": summary.strata,
        "rollouts": summary.rollouts,
        "recommended": summary.recommended,
        "labels": summary.tradeoff.iter().map(|p| (p.name.clone(), memory::short_label(&p.name))).collect::<std::collections::BTreeMap<_, _>>(),
        "rollout_frames": o.rollout_frames,
        "wall_s": results.iter().map(|(c, s)| (c.name.clone(), s.wall_s)).collect::<Vec<_>>(),
    });
    write_atomically(&path, &serde_json::to_string_pretty(&json)?)?;
    Ok(summary)
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
                    let sampler = Sampler::new(&m.manifest().diffusion, *steps, method, 0.0).map_err(|e| setting("--steps", e.to_string()))?;
                    Predictor::Model { model: m, policy: policy.clone(), sampler }
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
    cache: &mut HashMap<(usize, usize), SharedLatents>,
    ti: usize,
    traj: &Trajectory,
    models: &[(String, Model)],
    mi: usize,
) -> Result<SharedLatents, ProbeError> {
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
    o: &Settings,
    c: &Condition,
    key: Key,
    trajectories: &[Trajectory],
    models: &[(String, Model)],
    timing: &[(String, Model)],
    latents: &mut HashMap<(usize, usize), SharedLatents>,
    progress: &dyn Fn(Progress),
) -> Result<Saved> {
    let start = Instant::now();
    let rows = build_rows(c, models, o.probe.method)?;
    let model_of = |m: &Model| models.iter().position(|(_, x)| std::ptr::eq(x, m)).expect("a loaded model");
    let mut latents_of = |ti: usize, traj: &Trajectory, m: &Model| cached_latents(latents, ti, traj, models, model_of(m));

    let mut latency = vec![None; rows.len()];
    if c.timed {
        let first = transform(&trajectories[0], &c.change, &o.probe.suite, 0)?;
        for (i, (row, spec)) in build_rows(c, timing, o.probe.method)?.iter().zip(&c.rows).enumerate() {
            let l = match &spec.what {
                What::Model { model, .. } => latents_of(0, &first, &models[*model].1)?,
                _ => Rc::default(),
            };
            latency[i] = Some(latency_ms(&first, row, &l, o.probe.latency_calls)?);
        }
    }

    let settings = ProbeSettings { stride: o.probe.stride, batch: o.probe.batch, seed: crate::probe::SEED };
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.probe.stride).len()).sum();
    progress(Progress::Begin { what: &c.name, total: targets * rows.len() });
    let policies = selection_policies();
    let mut scores = Vec::new();
    let mut agreement: Vec<(String, Vec<Vec<Agreement>>)> = policies.iter().map(|(n, _)| (n.clone(), Vec::new())).collect();
    let (mut err_d, mut err_r, mut frames) = (0.0, 0.0, 0usize);
    for (ti, traj) in trajectories.iter().enumerate() {
        progress(Progress::Trajectory(&traj.entry.dir));
        let seen = transform(traj, &c.change, &o.probe.suite, ti)?;
        scores.push(probe_trajectory(&seen, &rows, &settings, &mut |m| latents_of(ti, traj, m), &|n| progress(Progress::Predictions(n)))?);
        if matches!(c.change, Change::Noise { .. } | Change::Poses { .. }) {
            let (truth, believed) = (traj.frusta()?, seen.frusta()?);
            let at = traj.return_frames(o.probe.stride);
            for ((_, policy), (_, out)) in policies.iter().zip(agreement.iter_mut()) {
                out.push(selection_agreement(policy, &truth, &believed, &at));
            }
            let (d, r) = pose_error(&traj.poses, &seen.poses);
            err_d += d * traj.len() as f64;
            err_r += r * traj.len() as f64;
            frames += traj.len();
        }
    }
    progress(Progress::End);
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
    o: &Settings,
    results: &[(Condition, Saved)],
    trajectories: &[Trajectory],
    models: &[(String, Model)],
    latents: &mut HashMap<(usize, usize), SharedLatents>,
    progress: &dyn Fn(Progress),
) -> Result<Vec<(String, SavedRollout)>> {
    let dir = o.out.join("rollouts");
    std::fs::create_dir_all(&dir).map_err(io(&o.out))?;
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
            progress(Progress::Reused { what: &format!("rollouts under {}", c.name), path: &path });
            out.push((c.name.clone(), s));
            continue;
        }
        let start = Instant::now();
        let seen: Vec<Trajectory> = trajectories.iter().enumerate().map(|(i, t)| transform(t, &c.change, &o.probe.suite, i)).collect::<Result<_>>()?;
        let sub = Condition { name: c.name.clone(), change: c.change.clone(), rows: specs.iter().map(|r| (*r).clone()).collect(), timed: false };
        let rows = build_rows(&sub, models, o.probe.method)?;
        let frames: usize = seen.iter().map(|t| crate::rollout::rollout_frames(t, Some(o.rollout_frames)).len()).sum();
        progress(Progress::Begin { what: &format!("rollouts: {}", c.name), total: frames * rows.len() });
        let scorer = crate::rollout::Scorer::default();
        let mut scores = Vec::new();
        for (row, spec) in rows.iter().zip(&sub.rows) {
            let observed: Vec<Vec<Vec<f32>>> = match &spec.what {
                What::Model { model, .. } => (0..seen.len())
                    .map(|ti| Ok(cached_latents(latents, ti, &trajectories[ti], models, *model)?.as_ref().clone()))
                    .collect::<Result<_, ProbeError>>()?,
                _ => vec![Vec::new(); seen.len()],
            };
            let r = crate::rollout::rollout(&seen, row, &observed, Some(o.rollout_frames), o.probe.batch, crate::probe::SEED, &scorer, &|n| progress(Progress::Predictions(n)))?;
            scores.push(r.scores);
        }
        progress(Progress::End);
        let s = SavedRollout { key, scores, wall_s: start.elapsed().as_secs_f64() };
        write_atomically(&path, &serde_json::to_string(&s)?)?;
        out.push((c.name.clone(), s));
    }
    Ok(out)
}

#[derive(Serialize)]
pub struct RolloutRow {
    pub row: String,
    pub psnr: f64,
    /// Against the same row's noise-free rollout, frame by frame.
    pub psnr_vs_clean: Option<Interval>,
}

#[derive(Serialize)]
pub struct RolloutCondition {
    pub condition: String,
    pub frames: usize,
    pub wall_s: f64,
    pub rows: Vec<RolloutRow>,
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
pub struct TradeoffPoint {
    pub name: String,
    pub group: Group,
    pub condition: String,
    pub latency_ms: f64,
    pub psnr: f64,
    pub ssim: f64,
    pub psnr_vs_baseline: Interval,
    pub parameters: Option<u64>,
    pub steps: Option<usize>,
    /// No other point is both at least as fast and at least as accurate (and better in one).
    pub pareto: bool,
    /// The same among the learned points only (the references left out).
    pub pareto_learned: bool,
}

/// The configuration the study recommends serving.
#[derive(Serialize)]
pub struct Recommendation {
    /// The trade-off point's name.
    pub name: String,
    /// The most accurate learned point, which it could not be told from.
    pub best: String,
    /// Whether it is that point itself.
    pub is_best: bool,
}

#[derive(Serialize)]
pub struct NoiseRow {
    pub row: String,
    pub psnr: f64,
    /// Against the same row without noise, frame by frame.
    pub psnr_vs_clean: Interval,
}

#[derive(Serialize)]
pub struct NoiseSelection {
    pub policy: String,
    pub jaccard: f64,
    pub rank: f64,
}

#[derive(Serialize)]
pub struct NoiseCondition {
    pub condition: String,
    pub change: Change,
    pub pose_error_blocks: f64,
    pub pose_error_deg: f64,
    pub rows: Vec<NoiseRow>,
    pub selection: Vec<NoiseSelection>,
}

#[derive(Serialize)]
pub struct StratumRow {
    pub row: String,
    pub psnr: f64,
    pub psnr_vs_baseline: Option<Interval>,
    /// Against Nearest Frame Packing: the same 22-frame packing chosen by
    /// recency, so what geometric selection adds (the paper's TP-only control).
    pub psnr_vs_recency: Option<Interval>,
}

#[derive(Serialize)]
pub struct StratumSummary {
    pub stratum: &'static str,
    pub description: &'static str,
    pub targets: usize,
    pub trajectories: usize,
    pub rows: Vec<StratumRow>,
}

/// Row `a` minus row `b` in one condition, paired frame by frame (`--contrast A:B`).
#[derive(Serialize)]
pub struct ConditionContrast {
    pub condition: String,
    pub a: String,
    pub b: String,
    pub psnr: Interval,
}

/// What a study measured (also written to `study.json`).
pub struct Summary {
    pub tradeoff: Vec<TradeoffPoint>,
    pub noise: Vec<NoiseCondition>,
    /// The `--contrast` pairs in the clean condition and under each pose noise.
    pub contrasts: Vec<ConditionContrast>,
    pub strata: Vec<StratumSummary>,
    pub rollouts: Vec<RolloutCondition>,
    pub recommended: Option<Recommendation>,
}

/// Whether each (latency, PSNR) point is on the Pareto front: no other point
/// is at least as fast and at least as accurate, and better in one. A point
/// without a latency (NaN) is never on the front and never beats one.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    let dominated = |p: &(f64, f64), q: &(f64, f64)| q.0 <= p.0 && q.1 >= p.1 && (q.0 < p.0 || q.1 > p.1);
    points.iter().map(|p| p.0.is_finite() && !points.iter().any(|q| dominated(p, q))).collect()
}

/// Marks both fronts: of all points, and of the learned ones.
pub fn mark_pareto_front(points: &mut [TradeoffPoint]) {
    let all: Vec<(f64, f64)> = points.iter().map(|p| (p.latency_ms, p.psnr)).collect();
    let learned: Vec<(f64, f64)> = points.iter().map(|p| if p.group == Group::Reference { (f64::NAN, f64::NAN) } else { (p.latency_ms, p.psnr) }).collect();
    for ((p, a), l) in points.iter_mut().zip(pareto_front(&all)).zip(pareto_front(&learned)) {
        p.pareto = a;
        p.pareto_learned = l && p.group != Group::Reference;
    }
}

/// The least model and fewest steps the measurements cannot tell from the
/// best: the fastest point of the learned front whose interval against the
/// baseline reaches the most accurate learned point's interval; that point
/// itself when none does. `None` without learned points. Expects the fronts marked.
pub fn recommend(points: &[TradeoffPoint]) -> Option<Recommendation> {
    let learned = || points.iter().filter(|p| p.group != Group::Reference && p.latency_ms.is_finite());
    let best = learned().max_by(|a, b| a.psnr.total_cmp(&b.psnr))?;
    let mut front: Vec<&TradeoffPoint> = learned().filter(|p| p.pareto_learned).collect();
    front.sort_by(|a, b| a.latency_ms.total_cmp(&b.latency_ms));
    let pick = front.into_iter().find(|p| p.psnr_vs_baseline.hi >= best.psnr_vs_baseline.lo).unwrap_or(best);
    Some(Recommendation { name: pick.name.clone(), best: best.name.clone(), is_best: std::ptr::eq(pick, best) })
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

/// `parameters[m]`: model m's parameter count, when its manifest says.
fn summarise(
    results: &[(Condition, Saved)],
    strata: &[Vec<TargetFeatures>],
    parameters: &[Option<u64>],
    rollouts: Vec<RolloutCondition>,
    pairs: &[(String, String)],
) -> Summary {
    let all = |_: usize, _: &FrameScore| true;
    let (clean_c, clean) = &results[0];
    let row_index = |c: &Condition, name: &str| c.rows.iter().position(|r| r.name == name);
    let base = row_index(clean_c, "baseline").expect("the clean condition runs the baseline");
    let recency = row_index(clean_c, "nearest_frame_packing").expect("the clean condition runs nearest frame packing");

    let mut tradeoff: Vec<TradeoffPoint> = Vec::new();
    for (c, s) in results.iter().filter(|(c, _)| c.timed) {
        for (i, r) in c.rows.iter().enumerate() {
            let (parameters, steps) = match &r.what {
                What::Model { model, steps, .. } => (parameters[*model], Some(*steps)),
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
                pareto_learned: false,
            });
        }
    }
    mark_pareto_front(&mut tradeoff);

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
    let mut contrasts = Vec::new();
    for (c, s) in results.iter().filter(|(c, _)| matches!(c.change, Change::Clean | Change::Noise { .. } | Change::Poses { .. })) {
        for (a, b) in pairs {
            if let (Some(i), Some(j)) = (row_index(c, a), row_index(c, b)) {
                let psnr = cluster_bootstrap(&paired(&s.scores, i, &s.scores, j, &all), BOOTSTRAP_REPS, 11);
                contrasts.push(ConditionContrast { condition: c.name.clone(), a: a.clone(), b: b.clone(), psnr });
            }
        }
    }
    let recommended = recommend(&tradeoff);
    Summary { tradeoff, noise, contrasts, strata, rollouts, recommended }
}

fn load(dir: &Path, runtime: RuntimeOptions) -> Result<Model> {
    load_model(dir, runtime, || format!("loading the model in {}", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(name: &str, latency_ms: f64, psnr: f64) -> TradeoffPoint {
        let zero = Interval { mean: 0.0, lo: 0.0, hi: 0.0, clusters: 0, values: 0 };
        TradeoffPoint {
            name: name.into(),
            group: Group::Policy,
            condition: "clean".into(),
            latency_ms,
            psnr,
            ssim: 0.0,
            psnr_vs_baseline: zero,
            parameters: None,
            steps: None,
            pareto: false,
            pareto_learned: false,
        }
    }

    #[test]
    fn the_front_keeps_only_points_nothing_beats() {
        let mut points = vec![
            point("a", 10.0, 12.0),
            point("b", 20.0, 13.0),
            point("slower and worse than a", 15.0, 11.0),
            point("as slow as b, worse", 20.0, 12.5),
            point("fastest", 5.0, 9.0),
            point("a twin of a", 10.0, 12.0),
            point("untimed", f64::NAN, 20.0),
        ];
        mark_pareto_front(&mut points);
        let front: Vec<&str> = points.iter().filter(|p| p.pareto).map(|p| p.name.as_str()).collect();
        assert_eq!(front, ["a", "b", "fastest", "a twin of a"]);
    }

    #[test]
    fn the_recommendation_is_the_fastest_learned_point_the_best_cannot_be_told_from() {
        let with = |mut p: TradeoffPoint, group: Group, lo: f64, hi: f64| {
            p.group = group;
            p.psnr_vs_baseline = Interval { mean: (lo + hi) / 2.0, lo, hi, clusters: 10, values: 100 };
            p
        };
        let mut points = vec![
            with(point("reference", 1.0, 20.0), Group::Reference, 5.0, 6.0),
            with(point("best", 30.0, 13.0), Group::Policy, 0.8, 1.2),
            with(point("close and faster", 10.0, 12.9), Group::Steps, 0.6, 0.9),
            with(point("fastest, clearly worse", 2.0, 10.0), Group::Steps, -2.0, -1.0),
        ];
        mark_pareto_front(&mut points);
        assert!(!points[1].pareto && points[1].pareto_learned, "the reference beats every model; among models it is on the front");
        assert!(!points[0].pareto_learned);
        let r = recommend(&points).unwrap();
        assert_eq!((r.name.as_str(), r.best.as_str(), r.is_best), ("close and faster", "best", false));
        // Once nothing faster overlaps, the best itself.
        points[2].psnr_vs_baseline.hi = 0.7;
        let r = recommend(&points).unwrap();
        assert_eq!((r.name.as_str(), r.is_best), ("best", true));
    }

    fn spec(name: &str, group: Group) -> RowSpec {
        RowSpec { name: name.into(), group, what: What::Copy }
    }

    fn scores(rows: &[f64]) -> Vec<TrajectoryScores> {
        // Two trajectories, targets 10 and 20; each row's PSNR is its value plus the trajectory index.
        (0..2)
            .map(|i| TrajectoryScores {
                dir: format!("t{i}"),
                task: "aba".into(),
                range: 5,
                warped_depth: Default::default(),
                rows: rows
                    .iter()
                    .map(|&p| [10, 20].iter().map(|&t| FrameScore { t, psnr: p + i as f64, ssim: 0.5, lpips: None, dreamsim: None, sharpness: None, psnr_in_warp: None, psnr_out_warp: None, sharpness_out_warp: None }).collect())
                    .collect(),
            })
            .collect()
    }

    fn saved(condition: &str, latency: Option<[f64; 4]>, rows: &[f64]) -> Saved {
        let key = Key {
            condition: condition.into(),
            change: Change::Clean,
            suite: "s".into(),
            trajectories: vec![],
            rows: vec![],
            models: vec![],
            stride: 1,
            steps: vec![],
            method: "ddim".into(),
            batch: 1,
            latency_calls: None,
            latency_threads: None,
            poses_digest: None,
        };
        Saved {
            key,
            latency_ms: latency.map_or(vec![None; 4], |l| l.map(Some).to_vec()),
            scores: scores(rows),
            agreement: vec![("worldpack".into(), vec![vec![Agreement { t: 10, jaccard: 0.5, rank: Some(1.0) }], vec![Agreement { t: 20, jaccard: 1.0, rank: None }]])],
            pose_error: (0.25, 0.0),
            wall_s: 0.0,
        }
    }

    #[test]
    fn conditions_pair_with_the_clean_one_and_strata_keep_their_targets() {
        let rows = vec![
            spec("baseline", Group::Policy),
            spec("nearest_frame_packing", Group::Policy),
            spec("worldpack", Group::Policy),
            spec("copy", Group::Reference),
        ];
        let clean = Condition { name: "clean".into(), change: Change::Clean, rows: rows.clone(), timed: true };
        let noisy = Condition {
            name: "translation σ 0.25".into(),
            change: Change::Noise { noise: PoseNoise::Independent { translation: 0.25, rotation_deg: 0.0 } },
            rows,
            timed: false,
        };
        let results = vec![
            (clean, saved("clean", Some([1.0, 2.0, 3.0, 0.5]), &[10.0, 10.5, 12.0, 11.0])),
            (noisy, saved("noisy", None, &[10.0, 10.5, 11.0, 9.0])),
        ];
        // Target 20 of trajectory 0 needs memory; nothing else does.
        let feature = |t: usize, memory_only: f64| TargetFeatures {
            t,
            recent_visible: 1.0 - memory_only,
            memory_only,
            memory_age: Some(30),
            occluded: None,
            revisit_angle_deg: None,
            explored: 0.0,
        };
        let strata = vec![vec![feature(10, 0.0), feature(20, 0.5)], vec![feature(10, 0.0), feature(20, 0.0)]];
        let s = summarise(&results, &strata, &[], Vec::new(), &[]);

        // Only the timed (clean) condition's rows are speed/accuracy points.
        assert_eq!(s.tradeoff.len(), 4);
        let wp = &s.tradeoff[2];
        assert_eq!((wp.latency_ms, wp.psnr), (3.0, 12.5));
        assert_eq!(wp.psnr_vs_baseline.mean, 2.0);
        let front: Vec<&str> = s.tradeoff.iter().filter(|p| p.pareto).map(|p| p.name.as_str()).collect();
        assert_eq!(front, ["worldpack", "copy"]);
        let learned: Vec<&str> = s.tradeoff.iter().filter(|p| p.pareto_learned).map(|p| p.name.as_str()).collect();
        assert_eq!(learned, ["baseline", "nearest_frame_packing", "worldpack"]);
        assert_eq!(s.recommended.as_ref().unwrap().best, "worldpack");

        // The noise condition pairs every row with the same row without noise.
        assert_eq!(s.noise.len(), 1);
        let by_row: Vec<(&str, f64)> = s.noise[0].rows.iter().map(|r| (r.row.as_str(), r.psnr_vs_clean.mean)).collect();
        assert_eq!(by_row, [("baseline", 0.0), ("nearest_frame_packing", 0.0), ("worldpack", -1.0), ("copy", -2.0)]);
        assert_eq!(s.noise[0].pose_error_blocks, 0.25);
        assert_eq!((s.noise[0].selection[0].jaccard, s.noise[0].selection[0].rank), (0.75, 1.0));

        // Strata: all four targets, one memory-dependent (trajectory 0's target 20).
        let stratum = |name: &str| s.strata.iter().find(|x| x.stratum == name).unwrap();
        assert_eq!((stratum("all").targets, stratum("all").trajectories), (4, 2));
        let memory = stratum("memory_dependent");
        assert_eq!((memory.targets, memory.trajectories), (1, 1));
        let wp = memory.rows.iter().find(|r| r.row == "worldpack").unwrap();
        assert_eq!(wp.psnr, 12.0);
        assert_eq!(wp.psnr_vs_recency.unwrap().mean, 1.5, "worldpack − nearest frame packing on that target");
        assert!(memory.rows.iter().find(|r| r.row == "copy").unwrap().psnr_vs_recency.is_none(), "copy is no selection policy");
        assert_eq!(stratum("revisit").targets, 0);
    }
}
