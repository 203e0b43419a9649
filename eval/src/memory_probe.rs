//! The memory probe of docs/probe.md (`worldpack probe`): teacher-forced
//! next-frame prediction on a suite's return legs for every trained variant,
//! the WorldPack weights on recency contexts, other model sizes and sampler
//! step counts, and the copy and reproject references; paired bootstrap
//! intervals against the baseline and the contrasts that answer the probe's
//! questions.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::rc::Rc;

use memory::{Policy, PolicyKind};
use model::{Method, Model, RuntimeOptions, Sampler};
use serde::Serialize;

use crate::metrics::DepthTally;
use crate::probe::{FrameScore, Predictor, ProbeError, Row, Settings as ProbeSettings, SharedLatents, TrajectoryScores, encode_all, latency_ms, probe_trajectory};
use crate::program::{ProgramError, load_model, setting, write_atomically};
use crate::stats::{Interval, cluster_bootstrap, mean_std};
use crate::suite::Trajectory;

/// The trained variants, each run with its own context policy: the paper's
/// four in its order, then WorldPack fine-tuned with the newest frame kept.
pub const VARIANTS: [&str; 5] = ["baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldpack_keep_last"];

/// The context policy of a named variant (memory::variants).
pub fn variant_policy(name: &str) -> Option<Policy> {
    memory::variant(name).ok().map(|v| v.policy())
}

pub const SELECTION_CONTROL: &str = "worldpack weights, recency contexts";
pub const KEEP_LAST: &str = "worldpack weights, newest frame kept";
pub const COPY: &str = "copy best-overlap frame";
pub const REPROJECT: &str = "reproject best-overlap frame";
pub const REPROJECT_FUSED: &str = "reproject 3 best frames, fused";
pub const COMPOSITE: &str = "fused warp, baseline in its holes";

/// What one probe run does; `worldpack probe`'s flags, one field each.
#[derive(Clone, Debug)]
pub struct Settings {
    pub suite: PathBuf,
    /// A folder of variant model folders: baseline/ (required) and any of the others.
    pub models: PathBuf,
    /// More models (name, folder), each with the policy it was trained with.
    pub extra: Vec<(String, PathBuf)>,
    pub steps: usize,
    /// Also run the WorldPack variant at these step counts.
    pub sweep_steps: Vec<usize>,
    pub method: Method,
    /// Score every n-th return-leg frame.
    pub stride: usize,
    /// Frames predicted per denoiser call.
    pub batch: usize,
    /// Batch-1 predictions timed per row.
    pub latency_calls: usize,
    pub limit: Option<usize>,
    pub runtime: RuntimeOptions,
    /// Write the report and every frame's scores here (JSON).
    pub out: Option<PathBuf>,
    /// More paired contrasts (row a minus row b, by name) beyond the standard ones.
    pub contrasts: Vec<(String, String)>,
    /// Model rows whose predictions fill the fused warp's holes in a
    /// composite row each, beyond the baseline's (the composite reference).
    pub composites: Vec<String>,
}

/// What the run is doing, for a progress display.
pub enum Progress<'a> {
    Started { trajectories: usize, targets: usize, rows: usize },
    Trajectory(&'a str),
    /// `n` more (target, row) predictions are done.
    Predictions(usize),
    Done,
}

#[derive(Serialize)]
pub struct RowSummary {
    pub name: String,
    pub model: Option<String>,
    pub parameters: Option<u64>,
    pub sampler_steps: Option<usize>,
    pub frames: usize,
    pub psnr: f64,
    pub psnr_std: f64,
    pub ssim: f64,
    pub ssim_std: f64,
    pub latency_ms: f64,
    pub psnr_vs_baseline: Option<Interval>,
    pub ssim_vs_baseline: Option<Interval>,
    /// Mean PSNR inside and outside the validity mask (the pixels the fused
    /// warp of the best observed frames covers), over the frames whose side
    /// holds enough pixels.
    pub psnr_in_warp: Option<f64>,
    pub psnr_out_warp: Option<f64>,
}

#[derive(Serialize)]
pub struct Cell {
    pub task: String,
    pub range: i32,
    pub trajectories: usize,
    pub frames: usize,
    pub psnr: BTreeMap<String, f64>,
    pub ssim: BTreeMap<String, f64>,
    pub psnr_vs_baseline: BTreeMap<String, Interval>,
}

#[derive(Serialize)]
pub struct Contrast {
    pub a: String,
    pub b: String,
    pub psnr: Interval,
    pub ssim: Interval,
    /// The same difference inside and outside the validity mask (frames where both rows have that side).
    pub psnr_in_warp: Option<Interval>,
    pub psnr_out_warp: Option<Interval>,
}

const BOOTSTRAP_REPS: usize = 4000;

pub struct Report {
    pub rows: Vec<RowSummary>,
    pub contrasts: Vec<Contrast>,
    pub cells: Vec<Cell>,
    /// The depth the fused warp of the 3 best observed frames gives each target, against its true depth.
    pub warped_depth: DepthTally,
}

pub fn probe(o: &Settings, progress: &dyn Fn(Progress)) -> Result<Report, ProgramError> {
    if o.stride == 0 || o.batch == 0 {
        return Err(setting("--stride", "--stride and --batch must be at least 1"));
    }
    let trajectories = crate::suite::load(&o.suite, o.limit)?;
    let load = |dir: &std::path::Path| load_model(dir, o.runtime, || format!("loading the model in {}", dir.display()));

    // Models, loaded once each.
    let mut models: Vec<(String, Policy, Model)> = Vec::new();
    for name in VARIANTS {
        let dir = o.models.join(name);
        if dir.join("manifest.json").exists() {
            let policy = variant_policy(name).expect("every variant has a policy");
            models.push((name.to_string(), policy, load(&dir)?));
        }
    }
    if !models.iter().any(|m| m.0 == "baseline") {
        return Err(setting("--models", format!("{} has no baseline/ model folder; the probe compares every row with it", o.models.display())));
    }
    for (name, dir) in &o.extra {
        let model = load(dir)?;
        models.push((name.clone(), model.trained_policy(), model));
    }
    let sampler_for = |m: &Model, steps: usize| Sampler::new(&m.manifest().diffusion, steps, o.method, 0.0).map_err(|e| setting("--steps", e.to_string()));
    let mut rows: Vec<Row> = Vec::new();
    let mut row_models: Vec<Option<(&Model, usize)>> = Vec::new();
    for (name, policy, m) in &models {
        rows.push(Row { name: name.clone(), predictor: Predictor::Model { model: m, policy: policy.clone(), sampler: sampler_for(m, o.steps)? } });
        row_models.push(Some((m, o.steps)));
    }
    if let Some((_, _, wp)) = models.iter().find(|m| m.0 == "worldpack") {
        if wp.manifest().layout_for_packing(&Policy::preset(PolicyKind::Baseline).packing).is_some() {
            rows.push(Row {
                name: SELECTION_CONTROL.into(),
                predictor: Predictor::Model { model: wp, policy: Policy::preset(PolicyKind::Baseline), sampler: sampler_for(wp, o.steps)? },
            });
            row_models.push(Some((wp, o.steps)));
        }
        // The setting DESIGN §3 leaves open, at inference only: the newest frame pinned to the first full-rate slot.
        let keep_last = variant_policy("worldpack_keep_last").expect("a variant");
        rows.push(Row { name: KEEP_LAST.into(), predictor: Predictor::Model { model: wp, policy: keep_last, sampler: sampler_for(wp, o.steps)? } });
        row_models.push(Some((wp, o.steps)));
        for &s in o.sweep_steps.iter().filter(|&&s| s != o.steps) {
            rows.push(Row {
                name: format!("worldpack, {s} steps"),
                predictor: Predictor::Model { model: wp, policy: Policy::preset(PolicyKind::WorldPack), sampler: sampler_for(wp, s)? },
            });
            row_models.push(Some((wp, s)));
        }
    }
    rows.push(Row { name: COPY.into(), predictor: Predictor::Copy });
    rows.push(Row { name: REPROJECT.into(), predictor: Predictor::Reproject });
    rows.push(Row { name: REPROJECT_FUSED.into(), predictor: Predictor::ReprojectFused { frames: crate::probe::FUSED_FRAMES } });
    row_models.extend([None, None, None]);
    for name in std::iter::once("baseline").chain(o.composites.iter().map(String::as_str)) {
        let Some((_, policy, m)) = models.iter().find(|m| m.0 == name) else {
            return Err(setting("--composite", format!("no model called {name:?} (the variants and the --extra names)")));
        };
        let label = if name == "baseline" { COMPOSITE.to_string() } else { format!("{name}, warp overlaid") };
        rows.push(Row { name: label, predictor: Predictor::Composite { model: m, policy: policy.clone(), sampler: sampler_for(m, o.steps)? } });
        row_models.push(Some((m, o.steps)));
    }
    for (a, b) in &o.contrasts {
        for name in [a, b] {
            if !rows.iter().any(|r| &r.name == name) {
                let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
                return Err(setting("--contrast", format!("no row called {name:?}; the rows are {}", names.join(", "))));
            }
        }
    }

    let settings = ProbeSettings { stride: o.stride, batch: o.batch, seed: crate::probe::SEED };
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.stride).len()).sum();
    progress(Progress::Started { trajectories: trajectories.len(), targets, rows: rows.len() });

    // Latency first, on the first trajectory, while nothing else runs.
    let mut latencies = Vec::new();
    let mut first_latents = latent_cache(&trajectories[0]);
    for row in &rows {
        let latents = match &row.predictor {
            Predictor::Model { model, .. }
            | Predictor::Composite { model, .. }
            | Predictor::PlanWarps { model, .. } => first_latents(model)?,
            _ => Rc::default(),
        };
        latencies.push(latency_ms(&trajectories[0], row, &latents, o.latency_calls)?);
    }

    let mut all: Vec<TrajectoryScores> = Vec::new();
    for traj in &trajectories {
        progress(Progress::Trajectory(&traj.entry.dir));
        let mut latents_for = latent_cache(traj);
        all.push(probe_trajectory(traj, &rows, &settings, &mut latents_for, &|n| progress(Progress::Predictions(n)))?);
    }
    progress(Progress::Done);

    let report = summarise(&rows, &row_models, &latencies, &all, &o.contrasts);
    if let Some(path) = &o.out {
        let json = serde_json::json!({
            "format": "worldpack-probe/1",
            "suite": o.suite,
            "models": o.models,
            "sampler": { "method": o.method.name(), "steps": o.steps },
            "stride": o.stride,
            "bootstrap": { "reps": BOOTSTRAP_REPS, "resampled": "trajectories", "level": 0.95 },
            "rows": report.rows,
            "contrasts": report.contrasts,
            "cells": report.cells,
            "warped_depth": { "abs_rel": report.warped_depth.abs_rel(), "delta_1_25": report.warped_depth.delta_1_25(),
                              "coverage": report.warped_depth.coverage(), "tally": report.warped_depth },
            "trajectories": all,
        });
        write_atomically(path, &serde_json::to_string(&json)?)?;
    }
    Ok(report)
}

/// The latents of `traj` under a model, encoded once per model (rows share models).
pub fn latent_cache(traj: &Trajectory) -> impl FnMut(&Model) -> Result<SharedLatents, ProbeError> + '_ {
    let mut cache: Vec<(*const Model, SharedLatents)> = Vec::new();
    move |m| {
        if let Some((_, l)) = cache.iter().find(|(p, _)| std::ptr::eq(*p, m)) {
            return Ok(l.clone());
        }
        let l = Rc::new(encode_all(m, traj)?);
        cache.push((m as *const Model, l.clone()));
        Ok(l)
    }
}

/// Per-trajectory paired differences `a − b` of one metric.
fn diffs(all: &[&TrajectoryScores], a: usize, b: usize, metric: fn(&FrameScore) -> f64) -> Vec<Vec<f64>> {
    all.iter().map(|t| t.rows[a].iter().zip(&t.rows[b]).map(|(x, y)| metric(x) - metric(y)).collect()).collect()
}

/// Row `i`'s mean PSNR on one side of the validity mask, over the frames that have that side.
fn masked_mean(all: &[&TrajectoryScores], i: usize, side: fn(&FrameScore) -> Option<f64>) -> Option<f64> {
    let v: Vec<f64> = all.iter().flat_map(|t| t.rows[i].iter().filter_map(side)).collect();
    (!v.is_empty()).then(|| mean_std(&v).0)
}

/// Row `a` minus row `b` on one side of the validity mask, per trajectory,
/// over the frames where both have that side; `None` when no frame has.
fn masked_contrast(all: &[&TrajectoryScores], a: usize, b: usize, side: fn(&FrameScore) -> Option<f64>) -> Option<Interval> {
    let d: Vec<Vec<f64>> = all
        .iter()
        .map(|t| t.rows[a].iter().zip(&t.rows[b]).filter_map(|(x, y)| Some(side(x)? - side(y)?)).collect::<Vec<f64>>())
        .filter(|t| !t.is_empty())
        .collect();
    (!d.is_empty()).then(|| cluster_bootstrap(&d, BOOTSTRAP_REPS, 17))
}

fn summarise(rows: &[Row], row_models: &[Option<(&Model, usize)>], latencies: &[f64], all: &[TrajectoryScores], extra: &[(String, String)]) -> Report {
    let in_warp = |f: &FrameScore| f.psnr_in_warp;
    let out_warp = |f: &FrameScore| f.psnr_out_warp;
    let psnr = |f: &FrameScore| f.psnr;
    let ssim = |f: &FrameScore| f.ssim;
    let everything: Vec<&TrajectoryScores> = all.iter().collect();
    let base = 0; // the baseline variant is always the first row
    let column = |i: usize, m: fn(&FrameScore) -> f64, of: &[&TrajectoryScores]| -> Vec<f64> {
        of.iter().flat_map(|t| t.rows[i].iter().map(m)).collect()
    };
    let summaries = rows
        .iter()
        .enumerate()
        .map(|(i, row)| {
            let (p, ps) = mean_std(&column(i, psnr, &everything));
            let (s, ss) = mean_std(&column(i, ssim, &everything));
            let vs = |m| (i != base).then(|| cluster_bootstrap(&diffs(&everything, i, base, m), BOOTSTRAP_REPS, 7));
            RowSummary {
                name: row.name.clone(),
                model: row_models[i].map(|(m, _)| m.dir().display().to_string()),
                parameters: row_models[i].and_then(|(m, _)| m.manifest().denoiser.parameters),
                sampler_steps: row_models[i].map(|(_, s)| s),
                frames: column(i, psnr, &everything).len(),
                psnr: p,
                psnr_std: ps,
                ssim: s,
                ssim_std: ss,
                latency_ms: latencies[i],
                psnr_vs_baseline: vs(psnr),
                ssim_vs_baseline: vs(ssim),
                psnr_in_warp: masked_mean(&everything, i, in_warp),
                psnr_out_warp: masked_mean(&everything, i, out_warp),
            }
        })
        .collect();

    let index = |name: &str| rows.iter().position(|r| r.name == name);
    // Pairs that answer the probe's questions: what selection buys with the same
    // weights, what pinning the newest frame buys, and the non-learned references.
    const PAIRS: [(&str, &str); 6] = [
        ("worldpack", SELECTION_CONTROL),
        ("worldpack_keep_last", "worldpack"),
        ("worldpack", COPY),
        ("worldpack", REPROJECT),
        ("worldpack_keep_last", "nearest_frame_packing"),
        ("worldpack_keep_last", REPROJECT),
    ];
    let contrasts = PAIRS
        .iter()
        .map(|&(a, b)| (a, b))
        .chain(extra.iter().map(|(a, b)| (a.as_str(), b.as_str())))
        .filter_map(|(a, b)| Some((a, b, index(a)?, index(b)?)))
        .map(|(a, b, i, j)| Contrast {
            a: a.into(),
            b: b.into(),
            psnr: cluster_bootstrap(&diffs(&everything, i, j, psnr), BOOTSTRAP_REPS, 11),
            ssim: cluster_bootstrap(&diffs(&everything, i, j, ssim), BOOTSTRAP_REPS, 11),
            psnr_in_warp: masked_contrast(&everything, i, j, in_warp),
            psnr_out_warp: masked_contrast(&everything, i, j, out_warp),
        })
        .collect();

    let mut keys: Vec<(String, i32)> = all.iter().map(|t| (t.task.clone(), t.range)).collect();
    keys.sort();
    keys.dedup();
    let cells = keys
        .into_iter()
        .map(|(task, range)| {
            let of: Vec<&TrajectoryScores> = all.iter().filter(|t| t.task == task && t.range == range).collect();
            let mean = |i, m| mean_std(&column(i, m, &of)).0;
            Cell {
                trajectories: of.len(),
                frames: column(base, psnr, &of).len(),
                psnr: rows.iter().enumerate().map(|(i, r)| (r.name.clone(), mean(i, psnr))).collect(),
                ssim: rows.iter().enumerate().map(|(i, r)| (r.name.clone(), mean(i, ssim))).collect(),
                psnr_vs_baseline: rows
                    .iter()
                    .enumerate()
                    .filter(|&(i, _)| i != base)
                    .map(|(i, r)| (r.name.clone(), cluster_bootstrap(&diffs(&of, i, base, psnr), BOOTSTRAP_REPS, 13)))
                    .collect(),
                task,
                range,
            }
        })
        .collect();
    let mut warped_depth = DepthTally::default();
    all.iter().for_each(|t| warped_depth.add(&t.warped_depth));
    Report { rows: summaries, contrasts, cells, warped_depth }
}


#[cfg(test)]
mod tests {
    use super::*;

    fn score(t: usize, psnr: f64) -> FrameScore {
        FrameScore { t, psnr, ssim: psnr / 100.0, lpips: None, dreamsim: None, sharpness: None, psnr_in_warp: None, psnr_out_warp: None, sharpness_out_warp: None }
    }

    /// Rows: baseline, worldpack (+1 dB on aba, +3 dB on abca), copy (−2 dB
    /// everywhere); two trajectories per task of two frames each.
    fn scores() -> Vec<TrajectoryScores> {
        (0..4)
            .map(|i| {
                let (task, gain) = if i < 2 { ("aba", 1.0) } else { ("abca", 3.0) };
                let base = [10.0 + i as f64, 12.0];
                TrajectoryScores {
                    dir: format!("t{i}"),
                    task: task.into(),
                    range: 5,
                    warped_depth: Default::default(),
                    rows: vec![
                        base.iter().enumerate().map(|(t, &p)| score(t, p)).collect(),
                        base.iter().enumerate().map(|(t, &p)| score(t, p + gain)).collect(),
                        base.iter().enumerate().map(|(t, &p)| score(t, p - 2.0)).collect(),
                    ],
                }
            })
            .collect()
    }

    #[test]
    fn rows_are_paired_against_the_baseline_and_contrasts_pick_their_rows() {
        let rows = [
            Row { name: "baseline".into(), predictor: Predictor::Copy },
            Row { name: "worldpack".into(), predictor: Predictor::Copy },
            Row { name: COPY.into(), predictor: Predictor::Copy },
        ];
        let r = summarise(&rows, &[None, None, None], &[1.0, 2.0, 0.5], &scores(), &[]);
        assert_eq!(r.rows.len(), 3);
        assert!(r.rows[0].psnr_vs_baseline.is_none(), "the baseline is not paired with itself");
        let wp = r.rows[1].psnr_vs_baseline.unwrap();
        assert!((wp.mean - 2.0).abs() < 1e-12, "half the frames gain 1 dB, half 3: {wp:?}");
        assert!(wp.lo >= 1.0 && wp.hi <= 3.0 && wp.above_zero(), "{wp:?}");
        let copy = r.rows[2].psnr_vs_baseline.unwrap();
        assert_eq!((copy.mean, copy.lo, copy.hi), (-2.0, -2.0, -2.0));
        assert_eq!(r.rows[1].latency_ms, 2.0);
        assert_eq!(r.rows[0].frames, 8);
        // Of the six contrasts only worldpack − copy has both rows here.
        assert_eq!(r.contrasts.len(), 1);
        assert_eq!((r.contrasts[0].a.as_str(), r.contrasts[0].b.as_str()), ("worldpack", COPY));
        assert!((r.contrasts[0].psnr.mean - 4.0).abs() < 1e-12);
        // One cell per (task, range), each paired within itself.
        assert_eq!(r.cells.len(), 2);
        assert_eq!(r.cells[0].psnr_vs_baseline["worldpack"].mean, 1.0);
        assert_eq!(r.cells[1].psnr_vs_baseline["worldpack"].mean, 3.0);
        assert_eq!(r.cells[1].psnr["baseline"], (12.0 + 13.0 + 12.0 + 12.0) / 4.0);
    }
}
