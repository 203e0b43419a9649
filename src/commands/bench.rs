//! `worldpack bench`: the benchmarks (`benchmarks` crate), tables on stdout
//! or JSON with `--json`.

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::Subcommand;

use crate::cli::parse_provider;

#[derive(Subcommand)]
pub enum Bench {
    /// Selection latency against stored frames: indexed exact, brute-force exact, brute-force Monte Carlo.
    Select {
        /// Comma-separated history sizes.
        #[arg(long, value_delimiter = ',', default_value = "50,100,400,1600,10000,100000")]
        candidates: Vec<usize>,
        #[arg(long, value_enum, default_value = "walk")]
        workload: benchmarks::select::Workload,
        /// Target poses per size (each timed once for the indexed path).
        #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        queries: u64,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Model step cost: denoiser call latency and memory for the 4-frame baseline and the packed
    /// 22-frame WorldPack context, and next-frame latency at several sampler step counts.
    Step {
        /// A model folder (ONNX graphs + manifest.json).
        #[arg(long, default_value = "fixtures/small")]
        model: PathBuf,
        /// Execution provider: cpu, cuda (fails when absent) or auto.
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        /// Intra-op threads per session (0: ONNX Runtime's choice).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Comma-separated sampler step counts for the next-frame timing.
        #[arg(long, value_delimiter = ',', default_value = "1,4,16,50")]
        steps: Vec<usize>,
        /// Timed denoiser calls per layout.
        #[arg(long, default_value_t = 50, value_parser = clap::value_parser!(u64).range(1..=100_000))]
        calls: u64,
        /// Comma-separated batch sizes at which to time one denoiser call (per-item cost; what batching across sessions could save).
        #[arg(long, value_delimiter = ',', default_value = "1,4,16", value_parser = clap::value_parser!(u64).range(1..=1024))]
        batches: Vec<u64>,
        #[arg(long)]
        json: bool,
    },
    /// The server: HTTP step latency against the same step as a library call, and
    /// throughput and p99 with 1, 2, 4 and 16 sessions stepping at once.
    Serve {
        #[arg(long, default_value = "fixtures/small")]
        model: PathBuf,
        /// Sampler steps per generated frame.
        #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u64).range(1..=1000))]
        steps: u64,
        /// Interleaved library/HTTP steps timed.
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        calls: u64,
        /// Comma-separated numbers of concurrent sessions.
        #[arg(long, value_delimiter = ',', default_value = "1,2,4,16")]
        sessions: Vec<usize>,
        /// Steps per session in the concurrency runs.
        #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        per_session: u64,
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Also run the concurrent rows against a server that batches across sessions with this window (ms; 0: only without).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=1000))]
        batch_window_ms: u64,
        /// Run the graphs on a Triton server (`triton://HOST:PORT`, as `serve --model-backend`).
        #[arg(long)]
        model_backend: Option<String>,
        #[arg(long)]
        json: bool,
    },
    /// The main job's step as a user drives it: sessions observe an exploration, turn round and
    /// generate their way back; p50 and p99 of each stage the step answer reports, per number
    /// of sessions walking at once. The defaults are `./scripts/serve.sh`'s.
    Walk {
        #[arg(long, default_value = "fixtures/variants/worldpack_geometry_fused_1step")]
        model: PathBuf,
        /// Sampler steps per generated frame (a distilled model: its own count).
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
        steps: u64,
        /// Sampler: ancestral, ddim or dpm2m (DPM-Solver++(2M): the 10-step DDIM's frames in about 8 calls).
        #[arg(long, default_value = "ddim")]
        method: model::Method,
        /// Choose plans and warp sources by co-visibility (as `serve --covisible`).
        #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
        covisible: bool,
        /// As `serve --sampled-latents`.
        #[arg(long)]
        sampled_latents: bool,
        /// Comma-separated numbers of sessions walking at once.
        #[arg(long, value_delimiter = ',', default_value = "1,4,16")]
        sessions: Vec<usize>,
        /// Generated steps timed per row, split over its sessions (at least 25 each).
        #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..=100_000))]
        walk_steps: u64,
        /// Observed steps each session takes before it turns (not timed).
        #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        explore: u64,
        /// The sessions' frame width in pixels (default: the model's): the world is rendered and
        /// each step answered at this size (the full-size stage, `full_size`).
        #[arg(long, value_parser = clap::value_parser!(u32).range(8..=4096))]
        size: Option<u32>,
        /// Do not score steps against the world's true frame (`"truth": false` in a step request;
        /// a session of real frames has none): at 224×224 rendering it costs as much as the model's step.
        #[arg(long)]
        no_truth: bool,
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        /// Intra-op threads per model call (pin the process to one core with `taskset -c 0` for a one-core figure).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        #[arg(long)]
        json: bool,
    },
    /// The same walk through the CPU provider and another (cuda): each frame's latent and picture compared, frame by frame.
    Parity {
        #[arg(long, default_value = "fixtures/variants/worldpack_geometry_fused_1step")]
        model: PathBuf,
        /// The provider set against the CPU's.
        #[arg(long, value_parser = parse_provider)]
        provider: model::Provider,
        /// Sampler steps per generated frame (a distilled model: its own count).
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
        steps: u64,
        /// Observed steps before the turn.
        #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        explore: u64,
        /// Generated steps after the turn (the turn's own are generated too).
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        back: u64,
        #[arg(long, default_value_t = 1)]
        threads: usize,
        #[arg(long)]
        json: bool,
    },
    /// The durable store: redb (what the server uses) against SQLite (WAL, full sync), one commit per frame.
    Store {
        #[arg(long, default_value_t = 500, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
        frames: u64,
        #[arg(long)]
        json: bool,
    },
    /// Forking a long session: the fork's cost (store and memory) against re-indexing its frames, and selection over the runs forks leave.
    Fork {
        #[arg(long, default_value_t = 10_000, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
        frames: u64,
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        forks: u64,
        #[arg(long)]
        json: bool,
    },
    /// Imagined frames per second at K candidates: batched, each alone, and as forks stepped, with the cost by stage.
    Imagine {
        #[arg(long, default_value = "fixtures/variants/worldpack_geometry_fused_1step")]
        model: PathBuf,
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
        steps: u64,
        #[arg(long, default_value = "ddim")]
        method: model::Method,
        #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
        covisible: bool,
        /// Comma-separated numbers of candidates.
        #[arg(long, value_delimiter = ',', default_value = "1,4,16", value_parser = clap::value_parser!(u64).range(1..=64))]
        candidates: Vec<u64>,
        /// Steps per candidate.
        #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=64))]
        horizon: u64,
        #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=10_000))]
        explore: u64,
        #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..=100))]
        rounds: u64,
        /// Candidates drawn as the example planner's first round draws them (each step one of its
        /// six actions, uniformly, seeded), so some share their first actions; without it each
        /// candidate turns by its own angle and none shares a frame.
        #[arg(long)]
        drawn: bool,
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        /// Intra-op threads per model call (pin the process to one core with `taskset -c 0` for a one-core figure).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        #[arg(long)]
        json: bool,
    },
    /// (internal) One layout's peak memory, in a process of its own.
    #[command(hide = true)]
    StepProbe {
        #[arg(long)]
        model: PathBuf,
        #[arg(long)]
        layout: String,
        #[arg(long, value_parser = parse_provider)]
        provider: model::Provider,
        #[arg(long)]
        threads: usize,
        #[arg(long)]
        calls: usize,
    },
    /// Renderer frames per second on one core at 64x64, 128x128, 224x224 and 640x360.
    Render {
        #[arg(long, default_value_t = 60, value_parser = clap::value_parser!(u64).range(1..=100_000))]
        frames: u64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
}

impl Bench {
    pub fn name(&self) -> &'static str {
        match self {
            Bench::Select { .. } => "bench select",
            Bench::Step { .. } => "bench step",
            Bench::Serve { .. } => "bench serve",
            Bench::Walk { .. } => "bench walk",
            Bench::Parity { .. } => "bench parity",
            Bench::Store { .. } => "bench store",
            Bench::Fork { .. } => "bench fork",
            Bench::Imagine { .. } => "bench imagine",
            Bench::StepProbe { .. } => "bench step-probe",
            Bench::Render { .. } => "bench render",
        }
    }

    pub fn run(&self) -> Result<()> {
        match self {
            Bench::Select { candidates, workload, queries, json } => {
                if let Some(bad) = candidates.iter().find(|&&n| n == 0 || n > 2_000_000) {
                    bail!("--candidates must lie in 1..=2000000, got {bad}");
                }
                let rows = benchmarks::select::run(*workload, candidates, *queries as usize, true);
                if *json {
                    let out = serde_json::json!({ "workload": format!("{workload:?}").to_lowercase(), "rows": rows,
                        "loglog_slope": (rows.len() >= 2).then(|| benchmarks::select::loglog_slope(&rows)) });
                    println!("{out}");
                } else {
                    benchmarks::select::print(*workload, &rows);
                }
                Ok(())
            }
            Bench::Step { model, provider, threads, steps, calls, batches, json } => {
                if let Some(bad) = steps.iter().find(|&&n| n == 0 || n > 1000) {
                    bail!("--steps must lie in 1..=1000, got {bad}");
                }
                let batches: Vec<usize> = batches.iter().map(|&b| b as usize).collect();
                let runtime = model::RuntimeOptions { provider: *provider, threads: *threads };
                benchmarks::step::run(model, runtime, steps, *calls as usize, &batches, *json)
            }
            Bench::Serve { model, steps, calls, sessions, per_session, provider, threads, batch_window_ms, model_backend, json } => {
                if let Some(bad) = sessions.iter().find(|&&n| n == 0 || n > 256) {
                    bail!("--sessions must lie in 1..=256, got {bad}");
                }
                let runtime = model::RuntimeOptions { provider: *provider, threads: *threads };
                benchmarks::serve::run(model, runtime, *steps as usize, *calls as usize, sessions, *per_session as usize, *batch_window_ms,
                    model_backend.as_deref(), *json)
            }
            Bench::Walk { model, steps, method, covisible, sampled_latents, sessions, walk_steps, explore, size, no_truth, provider, threads, json } => {
                if let Some(bad) = sessions.iter().find(|&&n| n == 0 || n > 256) {
                    bail!("--sessions must lie in 1..=256, got {bad}");
                }
                let runtime = model::RuntimeOptions { provider: *provider, threads: *threads };
                let o = benchmarks::walk::Options { steps: *steps as usize, method: *method, covisible: *covisible, sampled_latents: *sampled_latents,
                    walk_steps: *walk_steps as usize, explore: *explore as usize, size: *size, truth: !*no_truth };
                benchmarks::walk::run(model, runtime, &o, sessions, *json)
            }
            Bench::Parity { model, provider, steps, explore, back, threads, json } => {
                let runtime = model::RuntimeOptions { provider: *provider, threads: *threads };
                benchmarks::parity::run(model, runtime, *steps as usize, *explore as usize, *back as usize, *json)
            }
            Bench::Store { frames, json } => benchmarks::store::run(*frames as usize, *json),
            Bench::Fork { frames, forks, json } => benchmarks::fork::run(*frames as usize, *forks as usize, *json),
            Bench::Imagine { model, steps, method, covisible, candidates, horizon, explore, rounds, drawn, provider, threads, json } => {
                let runtime = model::RuntimeOptions { provider: *provider, threads: *threads };
                let o = benchmarks::imagine::Options { steps: *steps as usize, method: *method, covisible: *covisible, explore: *explore as usize,
                    horizon: *horizon as usize, rounds: *rounds as usize, drawn: *drawn };
                let ks: Vec<usize> = candidates.iter().map(|&k| k as usize).collect();
                benchmarks::imagine::run(model, runtime, &o, &ks, *json)
            }
            Bench::StepProbe { model, layout, provider, threads, calls } => {
                benchmarks::step::probe(model, layout, model::RuntimeOptions { provider: *provider, threads: *threads }, *calls)
            }
            Bench::Render { frames, seed } => benchmarks::render::run(*frames as usize, *seed),
        }
    }
}
