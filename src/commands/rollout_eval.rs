//! `worldpack eval`: the flags, a progress bar and the printed tables of
//! `eval::evaluate` (LoopNav-style rollouts of the return legs, written as
//! JSON that `scripts/report.py` turns into docs/results.md).

use std::cell::RefCell;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use eval::evaluate::{Progress, Settings, StratumPooled, evaluate};
use eval::stats::{Interval, PooledRow};
use eval::summary::Summary;
use indicatif::ProgressBar;

use crate::cli::{Runtime, count, parse_method, parse_named_path};

#[derive(clap::Args)]
pub struct Options {
    /// A suite from `worldpack sim loopnav` (test seeds).
    #[arg(long)]
    pub suite: PathBuf,
    /// A folder of variant model folders (baseline/, nearest_frame_packing/, memory_retrieval/, worldpack/).
    #[arg(long, default_value = "fixtures/variants")]
    pub models: PathBuf,
    /// Comma-separated policies; worldmem_greedy runs with the memory_retrieval weights.
    #[arg(long, value_delimiter = ',', value_parser = crate::commands::plan::parse_policy,
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
    /// Comma-separated rows to draw in OUT/strip.png under the true frames, on the trajectory whose
    /// paired PSNR difference (first of these − the --against row) is the median.
    #[arg(long, value_delimiter = ',')]
    pub strip: Vec<String>,
    /// Frames per row of the strip, evenly spaced over the return leg.
    #[arg(long, default_value_t = 10, value_parser = count(1, 100))]
    pub strip_frames: usize,
    /// A model row whose predictions fill the fused warp's holes in a composite row
    /// (repeatable; default: the baseline, the composite reference).
    #[arg(long = "composite")]
    pub composites: Vec<String>,
    /// A model row to run again with occlusion-aware selection of its plans and warp sources, as a row "NAME_covisible" (repeatable).
    #[arg(long = "covisible")]
    pub covisible: Vec<String>,
    /// A geometry-model row to run again warping only observed frames its own plan selected (no retrieval beyond its context), as a row "NAME_plan_warps" (repeatable).
    #[arg(long = "plan-warps")]
    pub plan_warps: Vec<String>,
    /// A model row whose autoencoder's reconstruction of the true frames, decode(encode(truth)), is
    /// scored as a row "NAME_autoencoder" (repeatable): the ceiling under every frame the model makes.
    #[arg(long = "reconstruct")]
    pub reconstruct: Vec<String>,
    /// On a suite larger than the model's frames: a model row run again with its frames brought to
    /// the suite's size bicubically and nothing else, as a row "NAME_upsampled_W" (repeatable): the
    /// floor under the full-size frame the plain row shows (docs/fullsize.md).
    #[arg(long = "upsampled")]
    pub upsampled: Vec<String>,
    /// On a suite larger than the model's frames: the most stored frames the full-size frame shows
    /// (`model::full_size`; default: the model's manifest `serving.full_size`, else 8).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=1024))]
    pub full_size_frames: Option<u64>,
    /// On a suite larger than the model's frames: the largest luma difference (0-255) between the
    /// warp and the model's frame, over one model pixel, at which the warp is shown (default: the
    /// model's manifest `serving.full_size`, else 48).
    #[arg(long)]
    pub agree_luma: Option<f64>,
    /// Run only these model rows (repeatable; default: every row), e.g. only NAME_covisible.
    #[arg(long = "only")]
    pub only: Vec<String>,
    /// An --extra row whose fusion-head model keeps each generated frame's sampled latent instead of re-encoding the blend, as `serve --sampled-latents` (repeatable).
    #[arg(long = "sampled-latents")]
    pub sampled_latents: Vec<String>,
    /// The best-overlap observed frames the probe fuses: the reproject_fused row and the holes
    /// mask every row is scored over. A geometry model's warp.frames compares it with the warp it is given.
    #[arg(long, default_value_t = eval::probe::FUSED_FRAMES, value_parser = count(1, 64))]
    pub probe_frames: usize,
}

impl Options {
    fn settings(&self) -> Settings {
        Settings {
            suite: self.suite.clone(),
            models: self.models.clone(),
            policies: self.policies.clone(),
            references: !self.no_references,
            steps: self.steps,
            method: self.method,
            max_frames: self.max_frames,
            limit: self.limit,
            batch: self.batch,
            runtime: self.runtime.options(),
            out: self.out.clone(),
            lpips: self.lpips.clone(),
            dreamsim: self.dreamsim.clone(),
            fvd: self.fvd.clone(),
            generated_level: self.generated_level,
            extra: self.extra.clone(),
            against: self.against.clone(),
            strip: self.strip.clone(),
            strip_frames: self.strip_frames,
            composites: self.composites.clone(),
            reconstruct: self.reconstruct.clone(),
            upsampled: self.upsampled.clone(),
            full_size: (self.agree_luma, self.full_size_frames.map(|f| f as usize)),
            probe_frames: self.probe_frames,
            covisible: self.covisible.clone(),
            plan_warps: self.plan_warps.clone(),
            only: self.only.clone(),
            sampled_latents: self.sampled_latents.clone(),
        }
    }
}

pub fn run(o: &Options) -> Result<()> {
    let bar = RefCell::new(None::<ProgressBar>);
    let progress = |p: Progress| match p {
        Progress::Started { trajectories, frames_per_row, rows } => {
            eprintln!("eval: {trajectories} trajectories, {frames_per_row} generated frames per row, {rows} rows, {} {:?} steps", o.steps, o.method)
        }
        Progress::Reused { row, path } => eprintln!("eval: reusing {row} from {}", path.display()),
        Progress::RowStarted { row, frames } => *bar.borrow_mut() = Some(crate::cli::bar(frames, row)),
        Progress::Frames(n) => bar.borrow().iter().for_each(|b| b.inc(n as u64)),
        Progress::RowDone => bar.borrow_mut().take().iter().for_each(|b| b.finish()),
    };
    let e = evaluate(&o.settings(), &progress)?;
    print(&e.summary);
    print_pooled(&e.pooled, &e.against);
    for s in &e.strata {
        print_stratum(s, &e.against);
    }
    if let Some(strip) = &e.strip {
        println!("\nwrote {} (rows: {}; trajectory {}, {}; frames {:?})", strip.path.display(), strip.rows.join(", "), strip.trajectory, strip.rule, strip.frames);
    }
    println!("wrote {}", e.results.display());
    Ok(())
}

fn print_pooled(rows: &[PooledRow], against: &str) {
    println!("\nPooled over every generated frame (95% bootstrap over trajectories); differences paired against {against}");
    print_pooled_rows(rows);
}

fn print_stratum(s: &StratumPooled, against: &str) {
    println!("\nStratum {} ({}): {} frames of {} trajectories; differences paired against {against}", s.name, s.describe, s.frames, s.trajectories);
    if s.frames > 0 {
        print_pooled_rows(&s.pooled);
    }
}

fn print_pooled_rows(rows: &[PooledRow]) {
    println!(
        "{:<28} {:>24} {:>22} {:>26} {:>26} {:>22} {:>24} {:>26} {:>22}",
        "row", "PSNR", "SSIM", "PSNR diff", "SSIM diff", "sharpness", "holes PSNR", "holes PSNR diff", "holes sharpness"
    );
    let iv = |i: &Interval, d: usize| format!("{:.d$} [{:.d$}, {:.d$}]", i.mean, i.lo, i.hi);
    let opt = |i: &Option<Interval>, d: usize| i.as_ref().map_or("—".into(), |i| iv(i, d));
    for r in rows {
        println!(
            "{:<28} {:>24} {:>22} {:>26} {:>26} {:>22} {:>24} {:>26} {:>22}",
            r.row,
            iv(&r.psnr, 2),
            iv(&r.ssim, 3),
            opt(&r.psnr_diff, 2),
            opt(&r.ssim_diff, 3),
            opt(&r.sharpness, 2),
            opt(&r.holes_psnr, 2),
            opt(&r.holes_psnr_diff, 2),
            opt(&r.holes_sharpness, 2)
        );
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
#[derive(clap::Args)]
pub struct CompareArgs {
    a: PathBuf,
    b: PathBuf,
}

pub fn compare(args: &CompareArgs) -> Result<()> {
    let (a, b) = (&args.a, &args.b);
    let (wa, ha, pa) = read_rgb(a)?;
    let (wb, hb, pb) = read_rgb(b)?;
    if (wa, ha) != (wb, hb) {
        bail!("the images differ in size: {}x{} and {}x{}", wa, ha, wb, hb);
    }
    let out = serde_json::json!({
        "psnr": eval::metrics::psnr(&pa, &pb),
        "ssim": eval::metrics::ssim(&pa, &pb, wa, ha),
        // The first image's gradient energy over the second's (the truth's); null for a flat second image.
        "sharpness": eval::metrics::sharpness_ratio(&pa, &pb, wa, ha),
        "width": wa, "height": ha,
    });
    println!("{out}");
    Ok(())
}

fn read_rgb(path: &Path) -> Result<(usize, usize, Vec<u8>)> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot open {}", path.display()))?;
    let (rgb, w, h) = world::picture::decode_rgb(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok((w as usize, h as usize, rgb))
}
