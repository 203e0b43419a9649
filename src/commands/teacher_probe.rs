//! `worldpack probe`: the flags, a progress bar and the printed tables of
//! `eval::memory_probe` (the memory probe of docs/probe.md).

use std::cell::RefCell;
use std::path::PathBuf;

use anyhow::Result;
use eval::memory_probe::{COMPOSITE, COPY, KEEP_LAST, Progress, REPROJECT, REPROJECT_FUSED, Report, SELECTION_CONTROL, Settings, probe};
use eval::stats::Interval;
use indicatif::ProgressBar;

use crate::cli::{Runtime, count, parse_method, parse_named_path};

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
    /// Another paired contrast, as A:B (row names; A minus B), beyond the standard ones.
    #[arg(long = "contrast", value_parser = parse_contrast)]
    pub contrasts: Vec<(String, String)>,
    /// A model (variant or --extra name) whose predictions fill the fused warp's holes in a
    /// composite row "NAME, warp overlaid" (repeatable; the baseline's is always there).
    #[arg(long = "composite")]
    pub composites: Vec<String>,
}

pub fn parse_contrast(s: &str) -> Result<(String, String), String> {
    match s.split_once(':') {
        Some((a, b)) if !a.is_empty() && !b.is_empty() => Ok((a.to_string(), b.to_string())),
        _ => Err(format!("expected A:B (two row names), got {s:?}")),
    }
}

impl Options {
    fn settings(&self) -> Settings {
        Settings {
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
            out: self.out.clone(),
            contrasts: self.contrasts.clone(),
            composites: self.composites.clone(),
        }
    }
}

pub fn run(o: &Options) -> Result<()> {
    let bar = RefCell::new(None::<ProgressBar>);
    let progress = |p: Progress| match p {
        Progress::Started { trajectories, targets, rows } => {
            eprintln!("probe: {trajectories} trajectories, {targets} return-leg targets, {rows} rows, {} sampler steps ({:?})", o.steps, o.method);
            *bar.borrow_mut() = Some(crate::cli::bar(targets * rows, "probe"));
        }
        Progress::Trajectory(dir) => bar.borrow().iter().for_each(|b| b.set_message(dir.to_string())),
        Progress::Predictions(n) => bar.borrow().iter().for_each(|b| b.inc(n as u64)),
        Progress::Done => bar.borrow_mut().take().iter().for_each(|b| b.finish()),
    };
    let report = probe(&o.settings(), &progress)?;
    print(&report, o);
    if let Some(path) = &o.out {
        println!("wrote {}", path.display());
    }
    Ok(())
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
            println!(
                "  {} − {}: {}  {:+.3} [{:+.3}, {:+.3}]; inside the warp {}, outside {}",
                c.a,
                c.b,
                interval(&Some(c.psnr)),
                c.ssim.mean,
                c.ssim.lo,
                c.ssim.hi,
                interval(&c.psnr_in_warp),
                interval(&c.psnr_out_warp)
            );
        }
    }
    println!("\nPSNR inside / outside the validity mask (the pixels the fused warp of the 3 best observed frames covers):");
    for s in &r.rows {
        let f = |v: Option<f64>| v.map_or("—".into(), |v| format!("{v:.2}"));
        println!("  {:<38} {:>7} / {:>7}", s.name, f(s.psnr_in_warp), f(s.psnr_out_warp));
    }
    let d = &r.warped_depth;
    println!(
        "\nDepth for unseen views: the fused warp of the 3 best observed frames against the true depth: AbsRel {:.3}, δ<1.25 {:.3}, on {:.1}% of the surface pixels",
        d.abs_rel(),
        d.delta_1_25(),
        100.0 * d.coverage()
    );
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
        COPY => "copy".into(),
        REPROJECT => "reproject".into(),
        REPROJECT_FUSED => "reproject x3".into(),
        COMPOSITE => "composite".into(),
        n => n.chars().take(14).collect(),
    }
}
