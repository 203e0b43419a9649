//! The evaluation program behind `worldpack eval`: LoopNav-style
//! autoregressive rollouts of the return legs for every policy with its own
//! weights, extra models, and the non-learned references; per-cell means,
//! per-frame curves, pooled figures with paired intervals, the revisit
//! stratum and the sharpness ratio, written to `results.json`. Each row is
//! saved as it finishes (keyed by a digest of the model files and every
//! setting that fixes its numbers), so an interrupted run resumes where it
//! stopped and a rerun with the same settings recomputes nothing.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use memory::{Policy, PolicyKind};
use model::{Method, Model, RuntimeOptions, Sampler};
use serde::{Deserialize, Serialize};

use crate::digest::model_key;
use crate::features::{Embedding, Lpips, VideoFeatures};
use crate::probe::{FrameScore, Predictor, Row, encode_all};
use crate::program::{ProgramError, io, load_model, setting, write_atomically};
use crate::rollout::{FvdEstimate, Scorer, clip_fvd, rollout, rollout_frames};
use crate::stats::{PooledRow, pooled};
use crate::strata::{EXPLORED_STRIDE, Stratum, explored_share};
use crate::suite::Trajectory;
use crate::summary::{Summary, cells_of, summarise};

/// What one evaluation run does; `worldpack eval`'s flags, one field each.
#[derive(Clone, Debug)]
pub struct Settings {
    /// A suite from `worldpack sim loopnav`.
    pub suite: PathBuf,
    /// A folder of variant model folders, one per policy's weights.
    pub models: PathBuf,
    pub policies: Vec<PolicyKind>,
    /// Also the copy and reproject references.
    pub references: bool,
    pub steps: usize,
    pub method: Method,
    /// Generate at most this many frames of each return leg.
    pub max_frames: Option<usize>,
    /// Only the first n trajectories.
    pub limit: Option<usize>,
    /// Trajectories generated together per denoiser call.
    pub batch: usize,
    pub runtime: RuntimeOptions,
    /// `rows/<row>.json` as each row finishes, then `results.json`.
    pub out: PathBuf,
    pub lpips: Option<PathBuf>,
    pub dreamsim: Option<PathBuf>,
    pub fvd: Option<PathBuf>,
    /// The context-noise level that marks generated frames, instead of each manifest's.
    pub generated_level: Option<f32>,
    /// More model rows (name, folder), each with the policy it was trained with.
    pub extra: Vec<(String, PathBuf)>,
    /// The row paired differences are taken against (default: the first).
    pub against: Option<String>,
    /// Rows to show in `strip.png` under the truth (none: no picture); the
    /// trajectory is the median one for the first row against `against`.
    pub strip: Vec<String>,
    /// Frames per row of the picture, evenly spaced over the return leg.
    pub strip_frames: usize,
    /// Model rows whose policy runs again with occlusion-aware selection of
    /// its plans and warp sources (memory::covisibility), as a row "NAME_covisible" each.
    pub covisible: Vec<String>,
    /// Geometry-model rows to run again warping only the observed frames their
    /// own plan selected, as a row "NAME_plan_warps" each (the ablation of
    /// retrieval for a policy that has none, such as nearest frame packing).
    pub plan_warps: Vec<String>,
    /// `extra` rows whose fusion-head model keeps each generated frame's sampled
    /// latent in memory instead of re-encoding the blended frame (`Model::keep_sampled_latents`).
    pub sampled_latents: Vec<String>,
    /// Model rows to run, by name (empty: all); e.g. only the `_covisible`
    /// rows, when the plain rows of the same models are not wanted.
    pub only: Vec<String>,
    /// Model rows whose predictions fill the fused warp's holes in a
    /// composite row each (with the references; empty: the baseline).
    pub composites: Vec<String>,
    /// Model rows run again with their frames brought to the suite's size
    /// bicubically and nothing else, as a row "NAME_upsampled_W" each (W the
    /// model's frame width): the floor under a full-size frame, on a suite
    /// larger than the model's frames.
    pub upsampled: Vec<String>,
    /// On a suite larger than the model's frames, each model row shows its frames by its
    /// manifest's full-size rule; these replace its agreement (luma levels) and frame count.
    pub full_size: (Option<f64>, Option<usize>),
    /// Model rows whose autoencoder's reconstruction of the true frames,
    /// decode(encode(truth)), is scored as a row "NAME_autoencoder" each.
    pub reconstruct: Vec<String>,
    /// The best-overlap observed frames the probe fuses: the `reproject_fused`
    /// row and the holes mask every row is scored over (`probe::FUSED_FRAMES`
    /// unless set; a geometry model's `warp.frames` compares it with the warp it is given).
    pub probe_frames: usize,
}

/// What the run is doing, for a progress display.
pub enum Progress<'a> {
    Started { trajectories: usize, frames_per_row: usize, rows: usize },
    /// A row saved earlier with the same settings is reused.
    Reused { row: &'a str, path: &'a Path },
    RowStarted { row: &'a str, frames: usize },
    /// `n` more frames of the current row are done.
    Frames(usize),
    RowDone,
}

/// Bootstrap resamples of clips for an FVD interval.
const FVD_REPS: usize = 100;
/// Bootstrap resamples of trajectories for the pooled intervals.
const POOLED_REPS: usize = 4000;

/// Which trained weights a policy runs with (memory::variants).
pub fn weights_for(kind: PolicyKind) -> &'static str {
    memory::variant(kind.name()).map_or(kind.name(), |v| v.weights)
}

/// How tables and charts name a row: the registry's label for a policy, a
/// sentence for a reference, the name itself for an extra model.
pub fn row_label(name: &str, probe_frames: usize) -> String {
    match name {
        "copy" => "copy best-overlap observed frame".into(),
        "reproject" => "reproject it with depth".into(),
        "reproject_fused" => format!("reproject the {probe_frames} best frames, fused"),
        "composite" => "fused warp, baseline in its holes".into(),
        _ => memory::variant(name).map_or_else(|_| name.to_string(), |v| v.label.to_string()),
    }
}

/// What fixes a row's numbers; a saved row is reused only when it matches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RowKey {
    row: String,
    model: Option<String>,
    suite: String,
    trajectories: Vec<String>,
    steps: usize,
    method: String,
    max_frames: Option<usize>,
    /// The noise of a frame depends on which frames share its denoiser call.
    batch: usize,
    #[serde(default)]
    generated_level: Option<f32>,
    /// Whether the row's model kept sampled latents (rows saved before the option did not).
    #[serde(default)]
    sampled_latents: bool,
    /// How noise is seeded (rows saved before per-item seeds have none, and are recomputed).
    #[serde(default)]
    noise_seeding: String,
    /// The per-frame scores a row carries (rows saved before the sharpness ratio lack it, and are recomputed).
    #[serde(default)]
    scores: String,
    /// How a non-learned row makes its frames (`probe::reference_rules`; rows saved under an older rule are recomputed).
    #[serde(default)]
    reference: Option<String>,
    /// The frames whose fused warp makes the holes mask (rows saved before the setting used 3).
    #[serde(default = "default_probe_frames")]
    probe_frames: usize,
    /// How a model row's frames reach a suite larger than the model's frames (`model::full_size`); none at the model's size.
    #[serde(default)]
    full_size: Option<String>,
    feature_networks: [Option<String>; 3],
}

fn default_probe_frames() -> usize {
    crate::probe::FUSED_FRAMES
}

// "holes": the PSNR and sharpness in the warp's holes (rows saved before them are recomputed).
const SCORES: &str = "psnr ssim sharpness holes";

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FvdCell {
    pub task: String,
    pub range: i32,
    #[serde(flatten)]
    pub estimate: FvdEstimate,
}

#[derive(Serialize, Deserialize)]
struct SavedRow {
    key: RowKey,
    /// Per trajectory (suite order), per generated frame.
    frames: Vec<Vec<FrameScore>>,
    fvd: Vec<FvdCell>,
    wall_s: f64,
}

/// One stratum of the return-leg frames, pooled like the whole suite.
#[derive(Serialize)]
pub struct StratumPooled {
    pub name: &'static str,
    pub describe: &'static str,
    pub frames: usize,
    pub trajectories: usize,
    pub pooled: Vec<PooledRow>,
}

/// The picture of one return leg (`strip.png`).
#[derive(Serialize)]
pub struct Strip {
    pub path: PathBuf,
    pub trajectory: String,
    pub rule: String,
    /// Top to bottom; the first is the truth.
    pub rows: Vec<String>,
    /// The frame index of each column.
    pub frames: Vec<usize>,
}

/// What a run measured (also written to `results.json`).
pub struct Evaluation {
    pub summary: Summary,
    pub pooled: Vec<PooledRow>,
    pub against: String,
    /// The revisit and new-ground strata.
    pub strata: Vec<StratumPooled>,
    pub strip: Option<Strip>,
    pub results: PathBuf,
}

pub fn evaluate(s: &Settings, progress: &dyn Fn(Progress)) -> Result<Evaluation, ProgramError> {
    if s.policies.is_empty() && !s.references && s.extra.is_empty() {
        return Err(setting("--policies", "nothing to evaluate (name a policy, an extra model or keep the references)"));
    }
    let trajs = crate::suite::load(&s.suite, s.limit)?;
    let rows_dir = s.out.join("rows");
    std::fs::create_dir_all(&rows_dir).map_err(io(&s.out))?;

    let load = |dir: &Path, what: String| load_model(dir, s.runtime, || what);
    let mut models: BTreeMap<&str, Model> = BTreeMap::new();
    for &kind in &s.policies {
        let name = weights_for(kind);
        if !models.contains_key(name) {
            let dir = s.models.join(name);
            let m = load(&dir, format!("--models: the {} policy runs with {}", kind.name(), dir.display()))?;
            models.insert(name, m);
        }
    }
    let feature = |what: &'static str| move |source| ProgramError::Feature { what, source };
    let lpips = s.lpips.as_deref().map(|p| Lpips::open(p, s.runtime).map_err(feature("--lpips"))).transpose()?;
    let dreamsim = s.dreamsim.as_deref().map(|p| Embedding::open(p, s.runtime).map_err(feature("--dreamsim"))).transpose()?;
    let fvd_net = s.fvd.as_deref().map(|p| VideoFeatures::open(p, s.runtime).map_err(feature("--fvd"))).transpose()?;
    let scorer = Scorer { lpips: lpips.as_ref(), dreamsim: dreamsim.as_ref(), keep_frames: fvd_net.is_some(), probe_frames: s.probe_frames, full_size: s.full_size, ..Scorer::default() };
    let networks = [&s.lpips, &s.dreamsim, &s.fvd].map(|p| p.as_ref().map(|p| p.display().to_string()));
    let mut extras = Vec::with_capacity(s.extra.len());
    for (name, dir) in &s.extra {
        extras.push((name.clone(), load(dir, format!("--extra {name}={}", dir.display()))?));
    }
    for name in &s.sampled_latents {
        let Some((_, m)) = extras.iter_mut().find(|(n, _)| n == name) else {
            return Err(setting("--sampled-latents", format!("no --extra row called {name:?}")));
        };
        m.keep_sampled_latents(true);
    }
    if let Some(level) = s.generated_level {
        // Only models with a context-noise input take a level; at least one must.
        let takers: Vec<&mut Model> =
            models.values_mut().chain(extras.iter_mut().map(|(_, m)| m)).filter(|m| m.manifest().denoiser.context_noise.is_some()).collect();
        if takers.is_empty() {
            return Err(setting("--generated-level", "none of these models takes context noise levels"));
        }
        for m in takers {
            m.set_generated_level(level).map_err(|e| setting("--generated-level", e.to_string()))?;
        }
    }
    let sampler = |m: &Model| Sampler::new(&m.manifest().diffusion, s.steps, s.method, 0.0).map_err(|e| setting("--steps", e.to_string()));
    let mut rows: Vec<(Row, Option<&Model>)> = Vec::new();
    for &kind in &s.policies {
        let m = &models[weights_for(kind)];
        rows.push((Row { name: kind.name().to_string(), predictor: Predictor::Model { model: m, policy: Policy::preset(kind), sampler: sampler(m)? } }, Some(m)));
    }
    for (name, m) in &extras {
        rows.push((Row { name: name.clone(), predictor: Predictor::Model { model: m, policy: m.trained_policy(), sampler: sampler(m)? } }, Some(m)));
    }
    for name in &s.covisible {
        let Some((Predictor::Model { model, policy, .. }, m)) = rows.iter().find(|(r, _)| &r.name == name).map(|(r, m)| (&r.predictor, *m)) else {
            return Err(setting("--covisible", format!("no model row called {name:?}")));
        };
        let predictor = Predictor::Model { model, policy: policy.clone().covisible(), sampler: sampler(model)? };
        rows.push((Row { name: format!("{name}_covisible"), predictor }, m));
    }
    for name in &s.plan_warps {
        let Some((Predictor::Model { model, policy, .. }, m)) = rows.iter().find(|(r, _)| &r.name == name).map(|(r, m)| (&r.predictor, *m)) else {
            return Err(setting("--plan-warps", format!("no model row called {name:?}")));
        };
        if model.manifest().denoiser.warp.is_none() {
            return Err(setting("--plan-warps", format!("{name}: its model has no warp input")));
        }
        let predictor = Predictor::PlanWarps { model, policy: policy.clone(), sampler: sampler(model)? };
        rows.push((Row { name: format!("{name}_plan_warps"), predictor }, m));
    }
    for name in &s.upsampled {
        let Some((Predictor::Model { model, policy, .. }, m)) = rows.iter().find(|(r, _)| &r.name == name).map(|(r, m)| (&r.predictor, *m)) else {
            return Err(setting("--upsampled", format!("no model row called {name:?}")));
        };
        let predictor = Predictor::Upsampled { model, policy: policy.clone(), sampler: sampler(model)? };
        rows.push((Row { name: format!("{name}_upsampled_{}", model.manifest().image.width), predictor }, m));
    }
    for name in &s.reconstruct {
        let Some((model, m)) = rows.iter().find(|(r, _)| &r.name == name).and_then(|(r, m)| Some((r.predictor.model()?, *m))) else {
            return Err(setting("--reconstruct", format!("no model row called {name:?}")));
        };
        rows.push((Row { name: format!("{name}_autoencoder"), predictor: Predictor::Reconstruct { model } }, m));
    }
    if let Some(dup) = rows.iter().enumerate().find(|(i, (r, _))| rows[..*i].iter().any(|(q, _)| q.name == r.name)) {
        return Err(setting("--extra", format!("two rows are called {:?}", dup.1.0.name)));
    }
    if let Some(unknown) = s.only.iter().find(|n| !rows.iter().any(|(r, _)| &r.name == *n)) {
        let names: Vec<&str> = rows.iter().map(|(r, _)| r.name.as_str()).collect();
        return Err(setting("--only", format!("no model row called {unknown:?}; the rows are {names:?}")));
    }
    if !s.only.is_empty() {
        rows.retain(|(r, _)| s.only.contains(&r.name));
    }
    if s.references {
        rows.push((Row { name: "copy".into(), predictor: Predictor::Copy }, None));
        rows.push((Row { name: "reproject".into(), predictor: Predictor::Reproject }, None));
        rows.push((Row { name: "reproject_fused".into(), predictor: Predictor::ReprojectFused { frames: s.probe_frames } }, None));
        // Composite rows: the fused warp where it lands, a model row's prediction in its holes
        // (the composite reference uses the 4-frame baseline's).
        let wanted: Vec<String> = if s.composites.is_empty() { vec!["baseline".into()] } else { s.composites.clone() };
        for name in wanted {
            let Some((Predictor::Model { model, policy, .. }, m)) = rows.iter().find(|(r, _)| r.name == name).map(|(r, m)| (&r.predictor, *m)) else {
                if s.composites.is_empty() {
                    continue; // no baseline row: no default composite
                }
                return Err(setting("--composite", format!("no model row called {name:?}")));
            };
            let predictor = Predictor::Composite { model, policy: policy.clone(), sampler: sampler(model)? };
            let label = if name == "baseline" { "composite".to_string() } else { format!("composite_{name}") };
            rows.push((Row { name: label, predictor }, m));
        }
    }
    let against = s.against.clone().unwrap_or_else(|| rows[0].0.name.clone());
    for (field, name) in std::iter::once(("--against", &against)).chain(s.strip.iter().map(|n| ("--strip", n))) {
        if !rows.iter().any(|(r, _)| &r.name == name) {
            let names: Vec<&str> = rows.iter().map(|(r, _)| r.name.as_str()).collect();
            return Err(setting(field, format!("no row called {name:?}; the rows are {}", names.join(", "))));
        }
    }

    let frames_per_row: usize = trajs.iter().map(|t| rollout_frames(t, s.max_frames).len()).sum();
    progress(Progress::Started { trajectories: trajs.len(), frames_per_row, rows: rows.len() });
    // Each trajectory's (task, range) cell, for the FVD cells and the summaries.
    let cells: Vec<(String, i32)> = trajs.iter().map(|t| (t.entry.task.clone(), t.entry.range)).collect();
    let mut results: Vec<(String, SavedRow)> = Vec::new();
    for (row, m) in &rows {
        let key = RowKey {
            row: row.name.clone(),
            model: m.map(|m| model_key(m.dir()).map_err(io(m.dir()))).transpose()?,
            suite: s.suite.display().to_string(),
            trajectories: trajs.iter().map(|t| t.entry.dir.clone()).collect(),
            steps: s.steps,
            method: s.method.name().into(),
            max_frames: s.max_frames,
            batch: s.batch,
            generated_level: s.generated_level,
            sampled_latents: m.is_some_and(|m| m.keeps_sampled_latents()),
            noise_seeding: "per frame".into(),
            scores: SCORES.into(),
            reference: (!matches!(row.predictor, Predictor::Model { .. })).then(|| crate::probe::reference_rules(s.probe_frames)),
            probe_frames: s.probe_frames,
            full_size: m.filter(|m| larger_than(&trajs, m)).map(|m| format!("{:?}", model::full_size::FullSize::of(m.manifest().serving.as_ref()).with(s.full_size.0, s.full_size.1))),
            feature_networks: networks.clone(),
        };
        let path = rows_dir.join(format!("{}.json", row.name));
        if let Some(saved) = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<SavedRow>(&t).ok()).filter(|r| r.key == key) {
            progress(Progress::Reused { row: &row.name, path: &path });
            results.push((row.name.clone(), saved));
            continue;
        }
        let started = std::time::Instant::now();
        let observed: Vec<Vec<Vec<f32>>> = match m {
            Some(m) => trajs.iter().map(|t| encode_all(m, t)).collect::<Result<_, _>>()?,
            None => trajs.iter().map(|_| Vec::new()).collect(),
        };
        progress(Progress::RowStarted { row: &row.name, frames: frames_per_row });
        let output = rollout(&trajs, row, &observed, s.max_frames, s.batch, crate::probe::SEED, &scorer, &|n| progress(Progress::Frames(n)))?;
        progress(Progress::RowDone);
        let mut fvd = Vec::new();
        if let Some(net) = &fvd_net {
            for (task, range) in cells_of(&cells) {
                let idx: Vec<usize> = (0..trajs.len()).filter(|&i| trajs[i].entry.task == task && trajs[i].entry.range == range).collect();
                let t: Vec<&Trajectory> = idx.iter().map(|&i| &trajs[i]).collect();
                let sc: Vec<_> = idx.iter().map(|&i| &output.scores[i]).collect();
                let f: Vec<_> = idx.iter().map(|&i| &output.frames[i]).collect();
                if let Some(estimate) = clip_fvd(net, &t, &sc, &f, FVD_REPS, 5)? {
                    fvd.push(FvdCell { task, range, estimate });
                }
            }
        }
        let saved = SavedRow { key, frames: output.scores, fvd, wall_s: started.elapsed().as_secs_f64() };
        write_atomically(&path, &serde_json::to_string(&saved)?)?;
        results.push((row.name.clone(), saved));
    }
    let scores: Vec<(&str, &[Vec<FrameScore>])> = results.iter().map(|(n, r)| (n.as_str(), r.frames.as_slice())).collect();
    let summary = summarise(&cells, &scores);
    let pooled_rows = pooled(&scores, &against, POOLED_REPS).expect("the row was checked above");
    let strata = explored_strata(&trajs, &scores, &against)?;
    let strip = if s.strip.is_empty() { None } else { strip(s, &trajs, &rows, &scores, &against)? };
    let json = serde_json::json!({
        "format": "worldpack-eval/1",
        "suite": s.suite,
        "models": s.models,
        "sampler": { "method": s.method.name(), "steps": s.steps },
        "max_frames": s.max_frames,
        "weights": s.policies.iter().map(|&k| (k.name(), weights_for(k))).collect::<BTreeMap<_, _>>(),
        "trajectories": trajs.iter().map(|t| serde_json::json!({"dir": t.entry.dir, "task": t.entry.task, "range": t.entry.range,
            "returning_point": t.entry.returning_point, "frames": t.len()})).collect::<Vec<_>>(),
        "rows": results.iter().map(|(n, r)| serde_json::json!({"name": n, "wall_s": r.wall_s, "model": r.key.model})).collect::<Vec<_>>(),
        "cells": summary.cells,
        "tasks": summary.tasks,
        "pooled": pooled_rows,
        "paired_against": against,
        "strata": &strata,
        "strip": strip,
        "labels": results.iter().map(|(n, _)| (n.clone(), row_label(n, s.probe_frames))).collect::<BTreeMap<_, _>>(),
        "fvd": results.iter().map(|(n, r)| (n.clone(), &r.fvd)).collect::<BTreeMap<_, _>>(),
        "feature_networks": { "lpips": networks[0], "dreamsim": networks[1], "fvd": networks[2] },
        "curves": summary.curves,
        "per_frame": results.iter().map(|(n, r)| (n.clone(), &r.frames)).collect::<BTreeMap<_, _>>(),
    });
    let path = s.out.join("results.json");
    write_atomically(&path, &serde_json::to_string(&json)?)?;
    Ok(Evaluation { summary, pooled: pooled_rows, against, strata, strip, results: path })
}

/// Whether the suite's frames differ in size from `m`'s, so its rows show frames through `model::full_size`.
fn larger_than(trajs: &[Trajectory], m: &Model) -> bool {
    let image = &m.manifest().image;
    trajs.first().is_some_and(|t| (t.intrinsics.width as usize, t.intrinsics.height as usize) != (image.width, image.height))
}

/// Rolls the rule's trajectory out again for each strip row, with the noise
/// it had in the suite (so the frames are the ones scored, up to the batch
/// tolerance of `Model::predict`), and writes the truth and those rows as one
/// picture.
fn strip(
    s: &Settings,
    trajs: &[Trajectory],
    rows: &[(Row, Option<&Model>)],
    scores: &[(&str, &[Vec<FrameScore>])],
    against: &str,
) -> Result<Option<Strip>, ProgramError> {
    let of = |name: &str| scores.iter().find(|(n, _)| *n == name).map(|(_, r)| *r).expect("strip rows were checked");
    let Some(ti) = crate::strip::median_trajectory(of(&s.strip[0]), of(against)) else { return Ok(None) };
    let traj = &trajs[ti];
    let leg = rollout_frames(traj, s.max_frames);
    let columns = crate::strip::spread(leg.len(), s.strip_frames);
    let scorer = Scorer { keep_frames: true, probe_frames: s.probe_frames, full_size: s.full_size, ..Scorer::default() };
    let mut generated: Vec<Vec<Vec<u8>>> = Vec::new();
    for name in &s.strip {
        let (row, model) = rows.iter().find(|(r, _)| &r.name == name).expect("strip rows were checked");
        let observed = match model {
            Some(m) => vec![encode_all(m, traj)?],
            None => vec![Vec::new()],
        };
        let out = crate::rollout::rollout_as(std::slice::from_ref(traj), &[ti], row, &observed, s.max_frames, 1, crate::probe::SEED, &scorer, &|_| {})?;
        generated.push(out.frames.into_iter().next().unwrap_or_default());
    }
    let truth: Vec<&[u8]> = columns.iter().map(|&c| traj.frame(leg.start + c)).collect();
    let mut grid_rows = vec![truth];
    grid_rows.extend(generated.iter().map(|frames| columns.iter().map(|&c| frames[c].as_slice()).collect()));
    let (w, h) = (traj.intrinsics.width as usize, traj.intrinsics.height as usize);
    let (gw, gh, px) = crate::strip::grid(&grid_rows, w, h, 2);
    let path = s.out.join("strip.png");
    world::picture::write_png(&path, gw as u32, gh as u32, &px).map_err(io(&path))?;
    Ok(Some(Strip {
        path,
        trajectory: traj.entry.dir.clone(),
        rule: format!("the median trajectory of the mean paired PSNR difference {} − {against}", s.strip[0]),
        rows: std::iter::once("truth".to_string()).chain(s.strip.iter().cloned()).collect(),
        frames: columns.iter().map(|&c| leg.start + c).collect(),
    }))
}

/// The return-leg frames split by how much of their view the exploration
/// showed: revisits ([`Stratum::Revisit`], where memory can bring the scene
/// back) and new ground ([`Stratum::NewGround`], where the model has to
/// paint), every row pooled over just those frames.
fn explored_strata(trajs: &[Trajectory], scores: &[(&str, &[Vec<FrameScore>])], against: &str) -> Result<Vec<StratumPooled>, ProgramError> {
    // Each generated frame's explored share (every row scores the same frames).
    let mut explored: Vec<Vec<f64>> = Vec::with_capacity(trajs.len());
    for (i, traj) in trajs.iter().enumerate() {
        let frusta = traj.frusta()?;
        explored.push(scores[0].1[i].iter().map(|f| explored_share(traj, &frusta, f.t, EXPLORED_STRIDE)).collect());
    }
    let stratum = |stratum: Stratum| {
        let members: Vec<Vec<bool>> = explored.iter().map(|t| t.iter().map(|&e| stratum.contains_explored(e)).collect()).collect();
        let kept: Vec<Vec<Vec<FrameScore>>> = scores
            .iter()
            .map(|(_, r)| r.iter().zip(&members).map(|(t, keep)| t.iter().zip(keep).filter(|(_, k)| **k).map(|(f, _)| *f).collect()).collect())
            .collect();
        let rows: Vec<(&str, &[Vec<FrameScore>])> = scores.iter().zip(&kept).map(|((n, _), k)| (*n, k.as_slice())).collect();
        StratumPooled {
            name: stratum.name(),
            describe: stratum.describe(),
            frames: members.iter().flatten().filter(|&&k| k).count(),
            trajectories: members.iter().filter(|t| t.iter().any(|&k| k)).count(),
            pooled: pooled(&rows, against, POOLED_REPS).expect("the row is one of these"),
        }
    };
    Ok(vec![stratum(Stratum::Revisit), stratum(Stratum::NewGround)])
}
