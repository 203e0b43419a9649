//! `worldpack study`: the flags, progress bars and printed tables of
//! `eval::study` (speed against accuracy, stability under pose noise, and
//! where methods fail; docs/cli.md).

use std::cell::RefCell;
use std::path::PathBuf;

use anyhow::Result;
use eval::stats::Interval;
use eval::memory_probe::Settings as ProbeRun;
use eval::study::{Progress, Settings, Summary, study};
use indicatif::ProgressBar;

use crate::cli::{Runtime, count, parse_method, parse_named_path};

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
    /// A paired contrast, as A:B (row names; A minus B), in the clean condition and under each pose noise.
    #[arg(long = "contrast", value_parser = crate::commands::teacher_probe::parse_contrast)]
    pub contrasts: Vec<(String, String)>,
}

impl Options {
    fn settings(&self) -> Settings {
        let probe = ProbeRun {
            suite: self.suite.clone(),
            models: self.models.clone(),
            extra: self.extra.clone(),
            steps: self.steps,
            sweep_steps: self.sweep_steps.clone(),
            method: self.method,
            stride: self.stride,
            batch: self.batch,
            latency_calls: self.latency_calls,
            limit: self.limit,
            runtime: self.runtime.options(),
            out: None,
            contrasts: self.contrasts.clone(),
            composites: Vec::new(),
        };
        Settings { probe, vo: self.vo.clone(), quick: self.quick, rollout_frames: self.rollout_frames, out: self.out.clone() }
    }
}

pub fn run(o: &Options) -> Result<()> {
    let bar = RefCell::new(None::<ProgressBar>);
    let progress = |p: Progress| match p {
        Progress::Started { trajectories, targets, conditions } => {
            eprintln!("study: {trajectories} trajectories, {targets} return-leg targets, {conditions} conditions, {} {:?} steps", o.steps, o.method)
        }
        Progress::Reused { what, path } => eprintln!("study: {what} reused from {}", path.display()),
        Progress::Begin { what, total } => *bar.borrow_mut() = Some(crate::cli::bar(total, &format!("study: {what}"))),
        Progress::Trajectory(dir) => bar.borrow().iter().for_each(|b| b.set_message(dir.to_string())),
        Progress::Predictions(n) => bar.borrow().iter().for_each(|b| b.inc(n as u64)),
        Progress::End => bar.borrow_mut().take().iter().for_each(|b| b.finish()),
    };
    let summary = study(&o.settings(), &progress)?;
    print(&summary);
    println!("wrote {}", o.out.join("study.json").display());
    Ok(())
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
    if !s.contrasts.is_empty() {
        println!("\nContrasts: A minus B, paired frame by frame in each condition (95% over trajectories)");
        for c in &s.contrasts {
            println!("  {:<24} {} − {}: {}", c.condition, c.a, c.b, interval(&c.psnr));
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

