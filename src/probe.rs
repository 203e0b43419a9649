//! `worldpack probe`: the memory probe of docs/probe.md. Teacher-forced
//! next-frame prediction on a suite's return legs for every trained variant,
//! the WorldPack weights on recency contexts, other model sizes and sampler
//! step counts, and the copy and reproject references; paired bootstrap
//! intervals against the baseline.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use anyhow::{Context, Result, bail};
use eval::probe::{Predictor, ProbeError, Row, Settings, TrajectoryScores, encode_all, latency_ms, probe_trajectory};
use eval::stats::{Interval, cluster_bootstrap, mean_std};
use eval::suite::Trajectory;
use memory::{Policy, PolicyKind};
use model::{Model, RuntimeOptions, Sampler};
use serde::Serialize;

use crate::cli::{Runtime, count, parse_method, parse_named_path};
use crate::sim::bar;

/// The trained variants, each run with its own context policy: the paper's
/// four in its order, then WorldPack fine-tuned with the newest frame kept.
pub const VARIANTS: [&str; 5] = ["baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldpack_keep_last"];

/// The context policy of a named variant (memory::variants).
pub fn variant_policy(name: &str) -> Option<Policy> {
    memory::variant(name).ok().map(|v| v.policy())
}

/// The policy a model was trained with: its manifest's `training.policy`,
/// scoring against the view its plans were made with. Models exported
/// before plans recorded their query were all trained with the target-pose
/// query; a manifest that names no variant gets the paper's WorldPack.
pub fn trained_policy(model: &Model) -> Policy {
    let Some(training) = model.manifest().training.as_ref() else { return Policy::preset(PolicyKind::WorldPack) };
    let Some(mut policy) = variant_policy(&training.policy) else { return Policy::preset(PolicyKind::WorldPack) };
    policy.query = training.plans_query.unwrap_or(memory::Query::Target);
    policy
}

pub const SELECTION_CONTROL: &str = "worldpack weights, recency contexts";
pub const KEEP_LAST: &str = "worldpack weights, newest frame kept";

#[derive(clap::Args)]
pub struct Options {
    /// A suite from `worldpack sim loopnav` (test seeds).
    #[arg(long)]
    pub suite: PathBuf,
    /// A folder of variant model folders: baseline/ (required), nearest_frame_packing/, memory_retrieval/, worldpack/.
    #[arg(long, default_value = "fixtures/variants")]
    pub models: PathBuf,
    /// More models to compare, as NAME=DIR (e.g. other sizes), each with the policy its manifest says it was trained on (WorldPack when it does not say).
    #[arg(long = "extra", value_parser = parse_named_path)]
    pub extra: Vec<(String, PathBuf)>,
    /// Sampler steps per predicted frame.
    #[arg(long, default_value_t = 10, value_parser = count(1, 1000))]
    pub steps: usize,
    /// Also run the WorldPack variant at these step counts (comma-separated).
    #[arg(long, value_delimiter = ',', value_parser = count(1, 1000))]
    pub sweep_steps: Vec<usize>,
    /// Sampler: ddim (deterministic) or ancestral.
    #[arg(long, default_value = "ddim", value_parser = parse_method)]
    pub method: model::Method,
    /// Score every n-th return-leg frame.
    #[arg(long, default_value_t = 1, value_parser = count(1, 10_000))]
    pub stride: usize,
    /// Frames predicted per denoiser call.
    #[arg(long, default_value_t = 16, value_parser = count(1, 1024))]
    pub batch: usize,
    /// Batch-1 predictions timed per row for the latency column.
    #[arg(long, default_value_t = 20, value_parser = count(1, 10_000))]
    pub latency_calls: usize,
    /// Only the first n trajectories of the suite.
    #[arg(long)]
    pub limit: Option<usize>,
    #[command(flatten)]
    pub runtime: Runtime,
    /// Write the summary and every frame's scores here (JSON).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

#[derive(Serialize)]
struct RowSummary {
    name: String,
    model: Option<String>,
    parameters: Option<u64>,
    sampler_steps: Option<usize>,
    frames: usize,
    psnr: f64,
    psnr_std: f64,
    ssim: f64,
    ssim_std: f64,
    latency_ms: f64,
    psnr_vs_baseline: Option<Interval>,
    ssim_vs_baseline: Option<Interval>,
}

#[derive(Serialize)]
struct Cell {
    task: String,
    range: i32,
    trajectories: usize,
    frames: usize,
    psnr: BTreeMap<String, f64>,
    ssim: BTreeMap<String, f64>,
    psnr_vs_baseline: BTreeMap<String, Interval>,
}

#[derive(Serialize)]
struct Contrast {
    a: String,
    b: String,
    psnr: Interval,
    ssim: Interval,
}

const BOOTSTRAP_REPS: usize = 4000;

pub fn load(dir: &Path, runtime: RuntimeOptions) -> Result<Model> {
    Model::load(dir, runtime).with_context(|| format!("loading the model in {}", dir.display()))
}

pub fn run(o: &Options) -> Result<()> {
    if o.stride == 0 || o.batch == 0 {
        bail!("--stride and --batch must be at least 1");
    }
    let trajectories = eval::suite::load(&o.suite, o.limit)?;

    // Models, loaded once each.
    let mut models: Vec<(String, Policy, Model)> = Vec::new();
    for name in VARIANTS {
        let dir = o.models.join(name);
        if dir.join("manifest.json").exists() {
            let policy = variant_policy(name).expect("every variant has a policy");
            models.push((name.to_string(), policy, load(&dir, o.runtime.options())?));
        }
    }
    if !models.iter().any(|m| m.0 == "baseline") {
        bail!("--models: {} has no baseline/ model folder; the probe compares every row with it", o.models.display());
    }
    for (name, dir) in &o.extra {
        let model = load(dir, o.runtime.options())?;
        models.push((name.clone(), trained_policy(&model), model));
    }
    let sampler_for = |m: &Model, steps: usize| Sampler::new(&m.manifest().diffusion, steps, o.method, 0.0);
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
    rows.push(Row { name: "copy best-overlap frame".into(), predictor: Predictor::Copy });
    rows.push(Row { name: "reproject best-overlap frame".into(), predictor: Predictor::Reproject });
    row_models.extend([None, None]);

    let settings = Settings { stride: o.stride, batch: o.batch, seed: 20261121 };
    let targets: usize = trajectories.iter().map(|t| t.return_frames(o.stride).len()).sum();
    eprintln!("probe: {} trajectories, {} return-leg targets, {} rows, {} sampler steps ({:?})", trajectories.len(), targets, rows.len(), o.steps, o.method);

    // Latency first, on the first trajectory, while nothing else runs.
    let mut latencies = Vec::new();
    let mut first_latents = latent_cache(&trajectories[0]);
    for row in &rows {
        let latents = match &row.predictor {
            Predictor::Model { model, .. } => first_latents(model)?,
            _ => Rc::default(),
        };
        latencies.push(latency_ms(&trajectories[0], row, &latents, o.latency_calls)?);
    }

    let progress = bar(targets * rows.len(), "probe");
    let mut all: Vec<TrajectoryScores> = Vec::new();
    for traj in &trajectories {
        progress.set_message(traj.entry.dir.clone());
        let mut latents_for = latent_cache(traj);
        all.push(probe_trajectory(traj, &rows, &settings, &mut latents_for, &|n| progress.inc(n as u64))?);
    }
    progress.finish();

    let report = summarise(&rows, &row_models, &latencies, &all);
    print(&report, o);
    if let Some(path) = &o.out {
        let json = serde_json::json!({
            "format": "worldpack-probe/1",
            "suite": o.suite,
            "models": o.models,
            "sampler": { "method": format!("{:?}", o.method).to_lowercase(), "steps": o.steps },
            "stride": o.stride,
            "bootstrap": { "reps": BOOTSTRAP_REPS, "resampled": "trajectories", "level": 0.95 },
            "rows": report.rows,
            "contrasts": report.contrasts,
            "cells": report.cells,
            "trajectories": all,
        });
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(path, serde_json::to_string(&json)?).with_context(|| format!("--out {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// The latents of `traj` under a model, encoded once per model (rows share models).
pub fn latent_cache(traj: &Trajectory) -> impl FnMut(&Model) -> Result<Rc<Vec<Vec<f32>>>, ProbeError> + '_ {
    let mut cache: Vec<(*const Model, Rc<Vec<Vec<f32>>>)> = Vec::new();
    move |m| {
        if let Some((_, l)) = cache.iter().find(|(p, _)| std::ptr::eq(*p, m)) {
            return Ok(l.clone());
        }
        let l = Rc::new(encode_all(m, traj)?);
        cache.push((m as *const Model, l.clone()));
        Ok(l)
    }
}

struct Report {
    rows: Vec<RowSummary>,
    contrasts: Vec<Contrast>,
    cells: Vec<Cell>,
}

/// Per-trajectory paired differences `a − b` of one metric.
fn diffs(all: &[&TrajectoryScores], a: usize, b: usize, metric: fn(&eval::probe::FrameScore) -> f64) -> Vec<Vec<f64>> {
    all.iter().map(|t| t.rows[a].iter().zip(&t.rows[b]).map(|(x, y)| metric(x) - metric(y)).collect()).collect()
}

fn summarise(rows: &[Row], row_models: &[Option<(&Model, usize)>], latencies: &[f64], all: &[TrajectoryScores]) -> Report {
    let psnr = |f: &eval::probe::FrameScore| f.psnr;
    let ssim = |f: &eval::probe::FrameScore| f.ssim;
    let everything: Vec<&TrajectoryScores> = all.iter().collect();
    let base = 0; // the baseline variant is always the first row
    let column = |i: usize, m: fn(&eval::probe::FrameScore) -> f64, of: &[&TrajectoryScores]| -> Vec<f64> {
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
            }
        })
        .collect();

    let index = |name: &str| rows.iter().position(|r| r.name == name);
    // Pairs that answer the probe's questions: what selection buys with the same
    // weights, what pinning the newest frame buys, and the non-learned references.
    const PAIRS: [(&str, &str); 6] = [
        ("worldpack", SELECTION_CONTROL),
        ("worldpack_keep_last", "worldpack"),
        ("worldpack", "copy best-overlap frame"),
        ("worldpack", "reproject best-overlap frame"),
        ("worldpack_keep_last", "nearest_frame_packing"),
        ("worldpack_keep_last", "reproject best-overlap frame"),
    ];
    let contrasts = PAIRS
        .iter()
        .filter_map(|&(a, b)| Some((a, b, index(a)?, index(b)?)))
        .map(|(a, b, i, j)| Contrast {
            a: a.into(),
            b: b.into(),
            psnr: cluster_bootstrap(&diffs(&everything, i, j, psnr), BOOTSTRAP_REPS, 11),
            ssim: cluster_bootstrap(&diffs(&everything, i, j, ssim), BOOTSTRAP_REPS, 11),
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
    Report { rows: summaries, contrasts, cells }
}

fn interval(i: &Option<Interval>) -> String {
    match i {
        Some(i) => format!("{:+.2} [{:+.2}, {:+.2}]", i.mean, i.lo, i.hi),
        None => "—".into(),
    }
}

fn print(r: &Report, o: &Options) {
    println!("\nReturn-leg next-frame prediction, teacher-forced ({} sampler steps, {:?}; intervals: 95% bootstrap over trajectories)", o.steps, o.method);
    println!("{:<38} {:>6} {:>7} {:>7} {:>26} {:>22} {:>10}", "row", "frames", "PSNR", "SSIM", "ΔPSNR vs baseline", "ΔSSIM vs baseline", "ms/frame");
    for s in &r.rows {
        let ssim_vs = s.ssim_vs_baseline.map(|i| format!("{:+.3} [{:+.3}, {:+.3}]", i.mean, i.lo, i.hi)).unwrap_or("—".into());
        println!("{:<38} {:>6} {:>7.2} {:>7.3} {:>26} {:>22} {:>10.2}", s.name, s.frames, s.psnr, s.ssim, interval(&s.psnr_vs_baseline), ssim_vs, s.latency_ms);
    }
    if !r.contrasts.is_empty() {
        println!("\nContrasts (ΔPSNR dB, ΔSSIM):");
        for c in &r.contrasts {
            println!("  {} − {}: {}  {:+.3} [{:+.3}, {:+.3}]", c.a, c.b, interval(&Some(c.psnr)), c.ssim.mean, c.ssim.lo, c.ssim.hi);
        }
    }
    println!("\nPSNR by (task, range):");
    let names: Vec<&String> = r.rows.iter().map(|s| &s.name).collect();
    print!("{:<12} {:>5}", "cell", "n");
    for n in &names {
        print!(" {:>14}", short(n));
    }
    println!();
    for c in &r.cells {
        print!("{:<12} {:>5}", format!("{} r{}", c.task, c.range), c.frames);
        for n in &names {
            print!(" {:>14.2}", c.psnr[*n]);
        }
        println!();
    }
}

/// Column headers short enough for a terminal.
fn short(name: &str) -> String {
    match name {
        "nearest_frame_packing" => "nfp".into(),
        "memory_retrieval" => "mr".into(),
        "worldpack_keep_last" => "wp keep-last".into(),
        SELECTION_CONTROL => "wp w/ recency".into(),
        KEEP_LAST => "wp w/ keep-last".into(),
        "copy best-overlap frame" => "copy".into(),
        "reproject best-overlap frame" => "reproject".into(),
        n => n.chars().take(14).collect(),
    }
}
