//! `worldpack eval`: LoopNav-style autoregressive rollouts of the return
//! legs for every policy with its own weights, plus the non-learned
//! references; per-(task, range, policy) means and per-frame curves, written
//! as JSON that `scripts/report.py` turns into docs/results.md. Each row is
//! saved as it finishes, so an interrupted run resumes where it stopped.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use eval::features::{Embedding, Lpips, VideoFeatures};
use eval::probe::{FrameScore, Predictor, Row, encode_all};
use eval::rollout::{FvdEstimate, Scorer, clip_fvd, rollout, rollout_frames};
use eval::stats::{Interval, PooledRow};
use eval::summary::{Summary, cells_of, summarise};
use eval::suite::Trajectory;
use memory::{Policy, PolicyKind};
use model::{Model, Sampler};
use serde::{Deserialize, Serialize};

use crate::digest::model_key;
use crate::cli::{Runtime, count, parse_method, parse_named_path};
use crate::sim::bar;

#[derive(clap::Args)]
pub struct Options {
    /// A suite from `worldpack sim loopnav` (test seeds).
    #[arg(long)]
    pub suite: PathBuf,
    /// A folder of variant model folders (baseline/, nearest_frame_packing/, memory_retrieval/, worldpack/).
    #[arg(long, default_value = "fixtures/variants")]
    pub models: PathBuf,
    /// Comma-separated policies; worldmem_greedy runs with the memory_retrieval weights.
    #[arg(long, value_delimiter = ',', value_parser = crate::plan::parse_policy,
          default_value = "baseline,nearest_frame_packing,memory_retrieval,worldpack,worldmem_greedy")]
    pub policies: Vec<memory::PolicyKind>,
    /// Leave out the copy and reproject references.
    #[arg(long)]
    pub no_references: bool,
    /// Sampler steps per generated frame.
    #[arg(long, default_value_t = 10, value_parser = count(1, 1000))]
    pub steps: usize,
    #[arg(long, default_value = "ddim", value_parser = parse_method)]
    pub method: model::Method,
    /// Generate at most this many frames of each return leg.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Only the first n trajectories of the suite.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Trajectories generated together per denoiser call.
    #[arg(long, default_value_t = 32, value_parser = count(1, 1024))]
    pub batch: usize,
    #[command(flatten)]
    pub runtime: Runtime,
    /// Results folder: rows/<row>.json as each row finishes (reused when the settings match), then results.json.
    #[arg(long, default_value = "runs/eval")]
    pub out: PathBuf,
    /// An LPIPS feature network in ONNX (contract in docs/metrics.md): adds per-frame LPIPS.
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// A DreamSim-style embedding network in ONNX: adds per-frame 1 − cosine distance.
    #[arg(long)]
    pub dreamsim: Option<PathBuf>,
    /// A video feature network in ONNX (e.g. I3D): adds FVD per (task, range) with a bootstrap interval.
    #[arg(long)]
    pub fvd: Option<PathBuf>,
    /// The context noise level that marks generated frames, instead of the manifest's (models with that input only).
    #[arg(long)]
    pub generated_level: Option<f32>,
    /// More model rows, as NAME=DIR, each run with the policy its manifest says it was trained on.
    #[arg(long = "extra", value_parser = parse_named_path)]
    pub extra: Vec<(String, PathBuf)>,
    /// The row the paired differences are taken against (default: the first row).
    #[arg(long)]
    pub against: Option<String>,
}

/// Bootstrap resamples of clips for an FVD interval.
const FVD_REPS: usize = 100;

/// Which trained weights a policy runs with (memory::variants).
pub fn weights_for(kind: PolicyKind) -> &'static str {
    memory::variant(kind.name()).map_or(kind.name(), |v| v.weights)
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
    /// How noise is seeded (rows saved before per-item seeds have none, and are recomputed).
    #[serde(default)]
    noise_seeding: String,
    feature_networks: [Option<String>; 3],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct FvdCell {
    task: String,
    range: i32,
    #[serde(flatten)]
    estimate: FvdEstimate,
}

#[derive(Serialize, Deserialize)]
struct SavedRow {
    key: RowKey,
    /// Per trajectory (suite order), per generated frame.
    frames: Vec<Vec<FrameScore>>,
    fvd: Vec<FvdCell>,
    wall_s: f64,
}

pub fn run(o: &Options) -> Result<()> {
    if o.policies.is_empty() && o.no_references {
        bail!("--policies: nothing to evaluate (name a policy or keep the references)");
    }
    let trajs = eval::suite::load(&o.suite, o.limit)?;
    let rows_dir = o.out.join("rows");
    std::fs::create_dir_all(&rows_dir).with_context(|| format!("--out {}", o.out.display()))?;

    let mut models: BTreeMap<&str, Model> = BTreeMap::new();
    for &kind in &o.policies {
        let name = weights_for(kind);
        if !models.contains_key(name) {
            let dir = o.models.join(name);
            let m = Model::load(&dir, o.runtime.options()).with_context(|| format!("--models: the {} policy runs with {}", kind.name(), dir.display()))?;
            models.insert(name, m);
        }
    }
    let lpips = o.lpips.as_deref().map(|p| Lpips::open(p, o.runtime.options()).context("--lpips")).transpose()?;
    let dreamsim = o.dreamsim.as_deref().map(|p| Embedding::open(p, o.runtime.options()).context("--dreamsim")).transpose()?;
    let fvd_net = o.fvd.as_deref().map(|p| VideoFeatures::open(p, o.runtime.options()).context("--fvd")).transpose()?;
    let scorer = Scorer { lpips: lpips.as_ref(), dreamsim: dreamsim.as_ref(), keep_frames: fvd_net.is_some() };
    let networks = [&o.lpips, &o.dreamsim, &o.fvd].map(|p| p.as_ref().map(|p| p.display().to_string()));
    let mut extras = Vec::with_capacity(o.extra.len());
    for (name, dir) in &o.extra {
        extras.push((name.clone(), Model::load(dir, o.runtime.options()).with_context(|| format!("--extra {name}={}", dir.display()))?));
    }
    if let Some(level) = o.generated_level {
        // Only models with a context-noise input take a level; at least one must.
        let takers: Vec<&mut Model> = models.values_mut().chain(extras.iter_mut().map(|(_, m)| m)).filter(|m| m.manifest().denoiser.context_noise.is_some()).collect();
        if takers.is_empty() {
            bail!("--generated-level: none of these models takes context noise levels");
        }
        for m in takers {
            m.set_generated_level(level).context("--generated-level")?;
        }
    }
    let mut rows: Vec<(Row, Option<&Model>)> = Vec::new();
    for &kind in &o.policies {
        let m = &models[weights_for(kind)];
        let sampler = Sampler::new(&m.manifest().diffusion, o.steps, o.method, 0.0)?;
        rows.push((Row { name: kind.name().to_string(), predictor: Predictor::Model { model: m, policy: Policy::preset(kind), sampler } }, Some(m)));
    }
    // WorldPack fine-tuned with the newest frame kept, when that variant is there.
    let keep_last_dir = o.models.join("worldpack_keep_last");
    let keep_last = if o.policies.contains(&PolicyKind::WorldPack) && keep_last_dir.join("manifest.json").exists() {
        Some(Model::load(&keep_last_dir, o.runtime.options()).with_context(|| format!("loading {}", keep_last_dir.display()))?)
    } else {
        None
    };
    if let Some(m) = &keep_last {
        let policy = crate::probe::trained_policy(m);
        let sampler = Sampler::new(&m.manifest().diffusion, o.steps, o.method, 0.0)?;
        rows.push((Row { name: "worldpack_keep_last".into(), predictor: Predictor::Model { model: m, policy, sampler } }, Some(m)));
    }
    for (name, m) in &extras {
        let sampler = Sampler::new(&m.manifest().diffusion, o.steps, o.method, 0.0)?;
        rows.push((Row { name: name.clone(), predictor: Predictor::Model { model: m, policy: crate::probe::trained_policy(m), sampler } }, Some(m)));
    }
    if let Some(dup) = rows.iter().enumerate().find(|(i, (r, _))| rows[..*i].iter().any(|(q, _)| q.name == r.name)) {
        bail!("--extra: two rows are called {:?}", dup.1.0.name);
    }
    if !o.no_references {
        rows.push((Row { name: "copy".into(), predictor: Predictor::Copy }, None));
        rows.push((Row { name: "reproject".into(), predictor: Predictor::Reproject }, None));
    }

    let per_row: usize = trajs.iter().map(|t| rollout_frames(t, o.max_frames).len()).sum();
    eprintln!("eval: {} trajectories, {} generated frames per row, {} rows, {} {:?} steps", trajs.len(), per_row, rows.len(), o.steps, o.method);
    // Each trajectory's (task, range) cell, for the FVD cells and the summaries.
    let cells: Vec<(String, i32)> = trajs.iter().map(|t| (t.entry.task.clone(), t.entry.range)).collect();
    let mut results: Vec<(String, SavedRow)> = Vec::new();
    for (row, m) in &rows {
        let key = RowKey {
            row: row.name.clone(),
            model: m.map(|m| model_key(m.dir())).transpose()?,
            suite: o.suite.display().to_string(),
            trajectories: trajs.iter().map(|t| t.entry.dir.clone()).collect(),
            steps: o.steps,
            method: format!("{:?}", o.method).to_lowercase(),
            max_frames: o.max_frames,
            batch: o.batch,
            generated_level: o.generated_level,
            noise_seeding: "per frame".into(),
            feature_networks: networks.clone(),
        };
        let path = rows_dir.join(format!("{}.json", row.name));
        if let Some(saved) = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<SavedRow>(&t).ok()).filter(|s| s.key == key) {
            eprintln!("eval: reusing {} from {}", row.name, path.display());
            results.push((row.name.clone(), saved));
            continue;
        }
        let started = std::time::Instant::now();
        let observed: Vec<Vec<Vec<f32>>> = match m {
            Some(m) => trajs.iter().map(|t| encode_all(m, t)).collect::<Result<_, _>>()?,
            None => trajs.iter().map(|_| Vec::new()).collect(),
        };
        let progress = bar(per_row, &row.name);
        let output = rollout(&trajs, row, &observed, o.max_frames, o.batch, 20261121, &scorer, &|n| progress.inc(n as u64))?;
        progress.finish();
        let mut fvd = Vec::new();
        if let Some(net) = &fvd_net {
            for (task, range) in cells_of(&cells) {
                let idx: Vec<usize> = (0..trajs.len()).filter(|&i| trajs[i].entry.task == task && trajs[i].entry.range == range).collect();
                let t: Vec<&Trajectory> = idx.iter().map(|&i| &trajs[i]).collect();
                let s: Vec<_> = idx.iter().map(|&i| &output.scores[i]).collect();
                let f: Vec<_> = idx.iter().map(|&i| &output.frames[i]).collect();
                if let Some(estimate) = clip_fvd(net, &t, &s, &f, FVD_REPS, 5)? {
                    fvd.push(FvdCell { task, range, estimate });
                }
            }
        }
        let saved = SavedRow { key, frames: output.scores, fvd, wall_s: started.elapsed().as_secs_f64() };
        let tmp = path.with_extension("json.tmp");
        std::fs::write(&tmp, serde_json::to_string(&saved)?)?;
        std::fs::rename(&tmp, &path)?;
        results.push((row.name.clone(), saved));
    }
    let scores: Vec<(&str, &[Vec<FrameScore>])> = results.iter().map(|(n, r)| (n.as_str(), r.frames.as_slice())).collect();
    let summary = summarise(&cells, &scores);
    print(&summary);
    let against = o.against.clone().unwrap_or_else(|| results[0].0.clone());
    if !results.iter().any(|(n, _)| *n == against) {
        bail!("--against: no row called {against:?}");
    }
    let pooled = eval::stats::pooled(&scores, &against, POOLED_REPS).expect("the row was checked above");
    print_pooled(&pooled, &against);
    let json = serde_json::json!({
        "format": "worldpack-eval/1",
        "suite": o.suite,
        "models": o.models,
        "sampler": { "method": format!("{:?}", o.method).to_lowercase(), "steps": o.steps },
        "max_frames": o.max_frames,
        "weights": o.policies.iter().map(|&k| (k.name(), weights_for(k))).collect::<BTreeMap<_, _>>(),
        "trajectories": trajs.iter().map(|t| serde_json::json!({"dir": t.entry.dir, "task": t.entry.task, "range": t.entry.range,
            "returning_point": t.entry.returning_point, "frames": t.len()})).collect::<Vec<_>>(),
        "rows": results.iter().map(|(n, r)| serde_json::json!({"name": n, "wall_s": r.wall_s, "model": r.key.model})).collect::<Vec<_>>(),
        "cells": summary.cells,
        "pooled": pooled,
        "paired_against": against,
        "labels": results.iter().map(|(n, _)| (n.clone(), row_label(n))).collect::<BTreeMap<_, _>>(),
        "fvd": results.iter().map(|(n, r)| (n.clone(), &r.fvd)).collect::<BTreeMap<_, _>>(),
        "feature_networks": { "lpips": networks[0], "dreamsim": networks[1], "fvd": networks[2] },
        "curves": summary.curves,
        "per_frame": results.iter().map(|(n, r)| (n.clone(), &r.frames)).collect::<BTreeMap<_, _>>(),
    });
    let path = o.out.join("results.json");
    std::fs::write(&path, serde_json::to_string(&json)?)?;
    println!("wrote {}", path.display());
    Ok(())
}

/// How tables and charts name a row: the registry's label for a policy, a
/// sentence for a reference, the name itself for an extra model.
pub fn row_label(name: &str) -> String {
    match name {
        "copy" => "copy best-overlap observed frame".into(),
        "reproject" => "reproject it with depth".into(),
        _ => memory::variant(name).map_or_else(|_| name.to_string(), |v| v.label.to_string()),
    }
}

/// Bootstrap resamples of trajectories for the pooled intervals.
const POOLED_REPS: usize = 4000;

fn print_pooled(rows: &[PooledRow], against: &str) {
    println!("\nPooled over every generated frame (95% bootstrap over trajectories); differences paired against {against}");
    println!("{:<28} {:>24} {:>22} {:>26} {:>26}", "row", "PSNR", "SSIM", "PSNR diff", "SSIM diff");
    let iv = |i: &Interval, d: usize| format!("{:.d$} [{:.d$}, {:.d$}]", i.mean, i.lo, i.hi);
    for r in rows {
        let diff = |i: &Option<Interval>, d: usize| i.as_ref().map_or("—".into(), |i| iv(i, d));
        println!("{:<28} {:>24} {:>22} {:>26} {:>26}", r.row, iv(&r.psnr, 2), iv(&r.ssim, 3), diff(&r.psnr_diff, 2), diff(&r.ssim_diff, 3));
    }
}

fn print(s: &Summary) {
    println!("\nReturn-leg rollouts: PSNR / SSIM, mean over trajectories (± std)");
    println!("{:<10} {:>5} {:<24} {:>16} {:>16} {:>9} {:>9}", "task", "range", "row", "PSNR", "SSIM", "LPIPS", "DreamSim");
    let opt = |v: Option<(f64, f64)>| v.map_or("—".to_string(), |(m, _)| format!("{m:.4}"));
    for c in &s.cells {
        println!("{:<10} {:>5} {:<24} {:>9.2} ± {:<5.2} {:>9.3} ± {:<5.3} {:>9} {:>9}", c.task, c.range, c.row, c.psnr.0, c.psnr.1, c.ssim.0, c.ssim.1, opt(c.lpips), opt(c.dreamsim));
    }
}

/// `worldpack compare A.png B.png`: the metrics of two images, as JSON.
pub fn compare(a: &Path, b: &Path) -> Result<()> {
    let (wa, ha, pa) = read_rgb(a)?;
    let (wb, hb, pb) = read_rgb(b)?;
    if (wa, ha) != (wb, hb) {
        bail!("the images differ in size: {}x{} and {}x{}", wa, ha, wb, hb);
    }
    let out = serde_json::json!({
        "psnr": eval::metrics::psnr(&pa, &pb),
        "ssim": eval::metrics::ssim(&pa, &pb, wa, ha),
        "width": wa, "height": ha,
    });
    println!("{out}");
    Ok(())
}

fn read_rgb(path: &Path) -> Result<(usize, usize, Vec<u8>)> {
    let file = std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().with_context(|| format!("{}: not a PNG", path.display()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).with_context(|| format!("{}: not a PNG", path.display()))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let rgb = match info.color_type {
        png::ColorType::Rgb => buf[..w * h * 3].to_vec(),
        png::ColorType::Rgba => buf[..w * h * 4].chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => buf[..w * h].iter().flat_map(|&g| [g, g, g]).collect(),
        png::ColorType::GrayscaleAlpha => buf[..w * h * 2].chunks_exact(2).flat_map(|p| [p[0], p[0], p[0]]).collect(),
        other => bail!("{}: unsupported PNG colour type {other:?}", path.display()),
    };
    Ok((w, h, rgb))
}
