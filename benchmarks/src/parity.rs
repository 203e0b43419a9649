//! `worldpack bench parity`: the same walk through two execution providers.
//! Two engines, one on the CPU provider and one on the provider asked for,
//! each observe the same exploration and generate the same way back with the
//! same noise; every frame's latent and picture are compared between them, so
//! a provider's numeric drift shows frame by frame as it compounds.

use std::path::Path;

use anyhow::{Result, anyhow};
use api::engine::{Engine, StepOptions};
use api::store::Store;
use model::{Method, Provider, RuntimeOptions, Sampler, Tensor};
use serde::Serialize;
use serde_json::json;

use crate::walk::{TURN, Walk, action};

/// One frame of the walk, the provider's against the CPU's.
#[derive(Clone, Debug, Serialize)]
pub struct FrameParity {
    /// 0-based index in the walk; observed frames come first.
    pub step: usize,
    pub generated: bool,
    /// Largest absolute difference of the frame's (scaled) latent.
    pub latent_max_abs: f32,
    /// Largest absolute difference of the frame's 8-bit picture (0 for observed frames, which are the world's).
    pub frame_max_abs: u8,
    /// PSNR of the provider's picture against the CPU's (dB, at most 100; generated frames).
    pub frame_psnr_db: Option<f64>,
    /// Each one's PSNR against the world's true frame at that pose (generated frames).
    pub truth_psnr_db_cpu: Option<f64>,
    pub truth_psnr_db_other: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub model: String,
    pub provider: String,
    pub steps: usize,
    /// The decoder alone, on the CPU run's first generated latent: largest absolute difference of its float output.
    pub decoder_max_abs: f32,
    pub frames: Vec<FrameParity>,
}

fn engine(model_dir: &Path, runtime: RuntimeOptions, dir: &Path) -> Result<Engine> {
    let model = api::load_model(model_dir, None, runtime).map_err(anyhow::Error::msg)?;
    Ok(Engine::new(Store::open(&dir.join("store.redb"))?, Some(model)))
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

fn rgb(png: &[u8]) -> Result<Vec<u8>> {
    Ok(world::picture::decode_rgb(png).map_err(|e| anyhow!("a step's picture: {e}"))?.0)
}

/// `explore` observed steps, the turn, then `back` generated steps on both providers.
pub fn run(model_dir: &Path, other: RuntimeOptions, steps: usize, explore: usize, back: usize, json_out: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-parity-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cpu_dir = dir.join("cpu");
    let other_dir = dir.join("other");
    std::fs::create_dir_all(&cpu_dir)?;
    std::fs::create_dir_all(&other_dir)?;
    let result = (|| -> Result<Report> {
        let cpu = engine(model_dir, RuntimeOptions { provider: Provider::Cpu, threads: other.threads }, &cpu_dir)?;
        let oth = engine(model_dir, other, &other_dir)?;
        let sampler = Sampler::new(&cpu.model()?.manifest().diffusion, steps, Method::Ddim, 0.0)?;
        let policy = json!({ "kind": "worldpack", "covisibility": memory::CoVisibility::default() });
        let fail = |e: api::EngineError| anyhow!("{}: {}", e.field, e.message);
        let mut a = cpu.create_synthetic(policy.clone(), 7, None, None, None).map_err(fail)?;
        let mut b = oth.create_synthetic(policy, 7, None, None, None).map_err(fail)?;
        let walk = Walk { explore, back, size: None, truth: true };
        let mut frames = Vec::new();
        let mut decoder_max_abs = None;
        for i in 0..explore + TURN + back {
            let act = action(&walk, i);
            let generated = i >= explore;
            let (mut frame_max_abs, mut frame_psnr_db, mut ta, mut tb) = (0u8, None, None, None);
            if generated {
                let oa = cpu.step(&mut a, &act, &sampler, &StepOptions::default()).map_err(fail)?;
                let ob = oth.step(&mut b, &act, &sampler, &StepOptions::default()).map_err(fail)?;
                let (pa, pb) = (rgb(&oa.png)?, rgb(&ob.png)?);
                frame_max_abs = pa.iter().zip(&pb).map(|(x, y)| x.abs_diff(*y)).max().unwrap_or(0);
                frame_psnr_db = Some(eval::metrics::psnr(&pa, &pb));
                ta = oa.truth.map(|t| t.psnr_db);
                tb = ob.truth.map(|t| t.psnr_db);
            } else {
                cpu.step_observed(&mut a, &act).map_err(fail)?;
                oth.step_observed(&mut b, &act).map_err(fail)?;
            }
            let (la, lb) =
                (&a.history().last().expect("a step pushes a frame").latent, &b.history().last().expect("a step pushes a frame").latent);
            if generated && decoder_max_abs.is_none() {
                let l = &cpu.model()?.manifest().autoencoder.latent;
                let latent = Tensor::new(vec![1, l.channels, l.height, l.width], la.clone());
                let (da, db) = (cpu.model()?.decode(&latent)?, oth.model()?.decode(&latent)?);
                decoder_max_abs = Some(max_abs(&da.data, &db.data));
            }
            frames.push(FrameParity {
                step: i,
                generated,
                latent_max_abs: max_abs(la, lb),
                frame_max_abs,
                frame_psnr_db,
                truth_psnr_db_cpu: ta,
                truth_psnr_db_other: tb,
            });
        }
        Ok(Report {
            model: model_dir.display().to_string(),
            provider: oth.model()?.provider().to_string(),
            steps: sampler.len(),
            decoder_max_abs: decoder_max_abs.unwrap_or(0.0),
            frames,
        })
    })();
    let _ = std::fs::remove_dir_all(&dir);
    let report = result?;
    if json_out {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "model {}, {} against the CPU provider, {} sampler step(s); decoder alone: max |diff| {:.2e}\n",
        report.model, report.provider, report.steps, report.decoder_max_abs
    );
    println!(
        "{:>5} {:>9} {:>11} {:>9} {:>10} {:>10} {:>10}",
        "step", "kind", "latent max", "frame max", "frame dB", "truth cpu", "truth oth"
    );
    for f in &report.frames {
        let db = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
        println!(
            "{:>5} {:>9} {:>11.2e} {:>9} {:>10} {:>10} {:>10}",
            f.step,
            if f.generated { "generated" } else { "observed" },
            f.latent_max_abs,
            f.frame_max_abs,
            db(f.frame_psnr_db),
            db(f.truth_psnr_db_cpu),
            db(f.truth_psnr_db_other)
        );
    }
    Ok(())
}
