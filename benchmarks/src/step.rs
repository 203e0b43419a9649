//! `worldpack bench step`: what one model step costs. Per denoiser call, the
//! 4-frame baseline context against the packed 22-frame WorldPack context
//! (latency in this process, memory in a fresh child process per layout so
//! the peaks do not mix), and whole next-frame latency at several sampler
//! step counts.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use model::generate::{Conditioning, gaussian};
use model::manifest::LayoutSpec;
use model::{Graph, Manifest, Method, Model, RuntimeOptions, Sampler, Tensor};
use serde::{Deserialize, Serialize};

use eval::stats::percentile;

/// Every slot present, random latents and poses: a full context of `layout`, batch 1.
fn full_context(m: &Manifest, layout: &LayoutSpec) -> Context3 {
    batched_context(m, layout, 1)
}

/// [`full_context`] repeated `batch` times along the batch axis.
fn batched_context(m: &Manifest, layout: &LayoutSpec, batch: usize) -> Context3 {
    let repeat = |t: Tensor| {
        let mut shape = t.shape.clone();
        shape[0] *= batch;
        Tensor::new(shape, t.data.repeat(batch))
    };
    let (context, action, rel_time) = one_context(m, layout);
    (context.into_iter().map(|(k, t)| (k, repeat(t))).collect(), repeat(action), repeat(rel_time))
}

fn one_context(m: &Manifest, layout: &LayoutSpec) -> Context3 {
    let l = &m.autoencoder.latent;
    let mut seed = 0;
    let mut next = |n: usize| {
        seed += 1;
        gaussian(seed, n)
    };
    let mut context = Vec::new();
    for s in &layout.slots {
        let k = s.count;
        context.push((format!("context_r{}", s.rate), Tensor::new(vec![1, k, l.channels, l.height, l.width], next(k * l.len()))));
        context.push((format!("context_time_r{}", s.rate), Tensor::new(vec![1, k], (0..k).map(|i| -1.0 - i as f32 * 7.0).collect())));
        context.push((format!("context_pose_r{}", s.rate), Tensor::new(vec![1, k, 12], next(k * 12))));
        context.push((format!("context_mask_r{}", s.rate), Tensor::new(vec![1, k], vec![1.0; k])));
    }
    let action = Tensor::new(vec![1, m.action.dim], vec![0.0; m.action.dim]);
    (context, action, Tensor::new(vec![1], vec![1.0]))
}

/// Context tensors, action, relative time.
type Context3 = (Vec<(String, Tensor)>, Tensor, Tensor);

/// One denoiser call at the context's batch.
fn call(graph: &Graph, m: &Manifest, ctx: &Context3) -> Result<()> {
    let l = &m.autoencoder.latent;
    let batch = ctx.2.shape[0];
    let x = Tensor::new(vec![batch, l.channels, l.height, l.width], gaussian(99, batch * l.len()));
    let t = Tensor::new(vec![batch], vec![500.0; batch]);
    let mut inputs: Vec<(&str, &Tensor)> = ctx.0.iter().map(|(k, v)| (k.as_str(), v)).collect();
    inputs.extend([("x_t", &x), ("timestep", &t), ("action", &ctx.1), ("rel_time", &ctx.2)]);
    graph.run(&inputs)?;
    Ok(())
}

fn stats(mut ms: Vec<f64>) -> (f64, f64) {
    ms.sort_by(f64::total_cmp);
    (percentile(&ms, 0.5), percentile(&ms, 0.95))
}

/// Peak memory of one layout, measured by the hidden `bench step-probe`.
#[derive(Serialize, Deserialize)]
pub struct Probe {
    pub layout: String,
    /// Resident memory after loading the graph, before any call (KiB).
    pub loaded_kib: u64,
    /// Peak resident memory over the calls (VmHWM, KiB).
    pub peak_kib: u64,
    /// Whether the high-water mark was reset after loading. If not, the peak
    /// may be the load's, and the calls' own memory is not reported.
    pub hwm_reset: bool,
}

pub(crate) fn status_kib(key: &str) -> Result<u64> {
    let status = std::fs::read_to_string("/proc/self/status").context("reading /proc/self/status (Linux only)")?;
    let line = status.lines().find(|l| l.starts_with(key)).with_context(|| format!("no {key} in /proc/self/status"))?;
    Ok(line.split_whitespace().nth(1).unwrap_or("0").parse()?)
}

/// Child process: open one layout's graph only, call it, print a `Probe` as JSON.
pub fn probe(dir: &Path, layout: &str, options: RuntimeOptions, calls: usize) -> Result<()> {
    let manifest = Manifest::load(dir)?;
    let spec = manifest.layout(layout).with_context(|| format!("--layout: no layout {layout:?}"))?.clone();
    let graph = Graph::open(dir, &spec.graph(), options)?;
    let ctx = full_context(&manifest, &spec);
    let loaded_kib = status_kib("VmRSS:")?;
    // Reset the high-water mark so the peak is the calls' own, not the load's
    // (Linux >= 4.0), and check that it took: a reset mark sits at the
    // current resident size, give or take what the read itself allocated.
    let written = std::fs::write("/proc/self/clear_refs", "5").is_ok();
    let hwm_reset = written && status_kib("VmHWM:")? <= status_kib("VmRSS:")? + 1024;
    for _ in 0..calls {
        call(&graph, &manifest, &ctx)?;
    }
    let peak_kib = status_kib("VmHWM:")?;
    println!("{}", serde_json::to_string(&Probe { layout: layout.into(), loaded_kib, peak_kib, hwm_reset })?);
    Ok(())
}

#[derive(Serialize)]
struct Report {
    model: String,
    provider: String,
    threads: usize,
    calls: usize,
    baseline: LayoutRow,
    worldpack: LayoutRow,
    time_ratio: f64,
    peak_ratio: f64,
    /// None when a high-water-mark reset failed (the peak may then be the load's).
    call_memory_ratio: Option<f64>,
    next_frame: Vec<StepRow>,
    /// Per-item cost of one denoiser call at each batch size (median over the calls).
    batching: Vec<BatchRow>,
}

#[derive(Serialize)]
struct BatchRow {
    batch: usize,
    baseline_ms_per_item: f64,
    worldpack_ms_per_item: f64,
}

#[derive(Serialize)]
struct LayoutRow {
    frames: usize,
    context_tokens: u64,
    median_ms: f64,
    p95_ms: f64,
    peak_mib: f64,
    /// Peak over the calls minus the resident size after loading; None when
    /// the high-water mark could not be reset.
    call_memory_mib: Option<f64>,
    /// Whether the child process's high-water mark was reset after loading.
    hwm_reset: bool,
}

#[derive(Serialize)]
struct StepRow {
    steps: usize,
    baseline_ms: f64,
    worldpack_ms: f64,
}

pub fn run(dir: &Path, options: RuntimeOptions, steps: &[usize], calls: usize, batches: &[usize], json: bool) -> Result<()> {
    let m = Model::load(dir, options)?;
    let (Some(base), Some(packed)) = (m.manifest().layout("baseline").cloned(), m.manifest().layout("worldpack").cloned()) else {
        bail!("--model: {} needs both a \"baseline\" and a \"worldpack\" layout to compare", dir.display());
    };
    let graphs = m.local()?;
    let (gb, gp) = (graphs.denoiser("baseline")?, graphs.denoiser("worldpack")?);
    let (cb, cp) = (full_context(m.manifest(), &base), full_context(m.manifest(), &packed));
    for _ in 0..3 {
        call(gb, m.manifest(), &cb)?;
        call(gp, m.manifest(), &cp)?;
    }
    // Interleaved, so drift in machine load hits both layouts alike.
    let (mut tb, mut tp) = (Vec::new(), Vec::new());
    for _ in 0..calls {
        let s = Instant::now();
        call(gb, m.manifest(), &cb)?;
        tb.push(s.elapsed().as_secs_f64() * 1e3);
        let s = Instant::now();
        call(gp, m.manifest(), &cp)?;
        tp.push(s.elapsed().as_secs_f64() * 1e3);
    }
    let ((mb, pb), (mp, pp)) = (stats(tb), stats(tp));

    let probe_of = |layout: &str| -> Result<Probe> {
        let exe = std::env::current_exe()?;
        let out = Command::new(exe)
            .args(["bench", "step-probe", "--model", &dir.to_string_lossy(), "--layout", layout, "--calls", "5"])
            .args(["--provider", options_provider(options), "--threads", &options.threads.to_string()])
            .output()?;
        if !out.status.success() {
            bail!("memory probe for {layout} failed: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(serde_json::from_slice(&out.stdout)?)
    };
    let (qb, qp) = (probe_of("baseline")?, probe_of("worldpack")?);

    let mut next_frame = Vec::new();
    for &n in steps {
        let sampler = Sampler::new(&m.manifest().diffusion, n, Method::Ancestral, 0.0)?;
        let time_one = |layout: &str, ctx: &Context3| -> Result<f64> {
            let cond = Conditioning { context: &ctx.0, action: &ctx.1, rel_time: &ctx.2 };
            let mut ms = Vec::new();
            for rep in 0..3 {
                let s = Instant::now();
                let latent = m.sample(layout, &cond, &sampler, &[rep])?;
                m.decode(&latent)?;
                ms.push(s.elapsed().as_secs_f64() * 1e3);
            }
            Ok(stats(ms).0)
        };
        next_frame.push(StepRow { steps: n, baseline_ms: time_one("baseline", &cb)?, worldpack_ms: time_one("worldpack", &cp)? });
    }

    // Per item at each batch size, the layouts interleaved as above.
    let mut batching = Vec::new();
    for &b in batches {
        let (cb, cp) = (batched_context(m.manifest(), &base, b), batched_context(m.manifest(), &packed, b));
        call(gb, m.manifest(), &cb)?;
        call(gp, m.manifest(), &cp)?;
        let (mut tb, mut tp) = (Vec::new(), Vec::new());
        for _ in 0..calls.div_ceil(b).max(3) {
            let s = Instant::now();
            call(gb, m.manifest(), &cb)?;
            tb.push(s.elapsed().as_secs_f64() * 1e3 / b as f64);
            let s = Instant::now();
            call(gp, m.manifest(), &cp)?;
            tp.push(s.elapsed().as_secs_f64() * 1e3 / b as f64);
        }
        batching.push(BatchRow { batch: b, baseline_ms_per_item: stats(tb).0, worldpack_ms_per_item: stats(tp).0 });
    }

    let mib = |k: u64| k as f64 / 1024.0;
    let row = |l: &LayoutSpec, median_ms, p95_ms, q: &Probe| LayoutRow {
        frames: l.frames,
        context_tokens: l.context_tokens,
        median_ms,
        p95_ms,
        peak_mib: mib(q.peak_kib),
        call_memory_mib: q.hwm_reset.then(|| mib(q.peak_kib.saturating_sub(q.loaded_kib))),
        hwm_reset: q.hwm_reset,
    };
    let report = Report {
        model: dir.display().to_string(),
        provider: m.provider().into(),
        threads: options.threads,
        calls,
        time_ratio: mp / mb,
        peak_ratio: qp.peak_kib as f64 / qb.peak_kib as f64,
        call_memory_ratio: (qb.hwm_reset && qp.hwm_reset)
            .then(|| qp.peak_kib.saturating_sub(qp.loaded_kib) as f64 / qb.peak_kib.saturating_sub(qb.loaded_kib).max(1) as f64),
        baseline: row(&base, mb, pb, &qb),
        worldpack: row(&packed, mp, pp, &qp),
        next_frame,
        batching,
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print(&report);
    }
    Ok(())
}

fn options_provider(o: RuntimeOptions) -> &'static str {
    match o.provider {
        model::Provider::Cpu => "cpu",
        model::Provider::Cuda => "cuda",
        model::Provider::Auto => "auto",
    }
}

fn print(r: &Report) {
    println!("model {} on {} ({} intra-op threads; 0 = ONNX Runtime's choice), {} calls per layout\n", r.model, r.provider, r.threads, r.calls);
    println!("{:<11} {:>7} {:>8} {:>12} {:>10} {:>11} {:>15}", "context", "frames", "tokens", "median (ms)", "p95 (ms)", "peak (MiB)", "per call (MiB)");
    let or_na = |v: Option<f64>, digits: usize| v.map_or("n/a".to_string(), |v| format!("{v:.digits$}"));
    for (name, l) in [("baseline", &r.baseline), ("worldpack", &r.worldpack)] {
        println!("{:<11} {:>7} {:>8} {:>12.3} {:>10.3} {:>11.1} {:>15}", name, l.frames, l.context_tokens, l.median_ms, l.p95_ms, l.peak_mib, or_na(l.call_memory_mib, 2));
    }
    println!(
        "\nworldpack / baseline: time {:.3}x, peak memory {:.3}x, per-call memory {}x  (paper: 1.16x time, 1.12x memory)",
        r.time_ratio, r.peak_ratio, or_na(r.call_memory_ratio, 3)
    );
    if r.call_memory_ratio.is_none() {
        println!("per-call memory n/a: the high-water mark could not be reset after loading (/proc/self/clear_refs), so a peak may be the load's");
    }
    if !r.batching.is_empty() {
        println!("\none denoiser call per item, by batch size (median):");
        println!("{:>6} {:>20} {:>21}", "batch", "baseline (ms/item)", "worldpack (ms/item)");
        for b in &r.batching {
            println!("{:>6} {:>20.3} {:>21.3}", b.batch, b.baseline_ms_per_item, b.worldpack_ms_per_item);
        }
    }
    println!("\nnext frame (sampler + decode), median of 3:");
    println!("{:>6} {:>14} {:>15}", "steps", "baseline (ms)", "worldpack (ms)");
    for s in &r.next_frame {
        println!("{:>6} {:>14.1} {:>15.1}", s.steps, s.baseline_ms, s.worldpack_ms);
    }
}
