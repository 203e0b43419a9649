//! `worldpack`: the product's command line.

mod cli;
mod demo;
mod eval;
mod fusion;
mod geometry;
mod plan;
mod probe;
mod sim;
mod study;

use std::io::Read;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use cli::{parse_method, parse_provider};

#[derive(Parser)]
#[command(name = "worldpack", version, about = "Geometry-first memory for long-context video world models")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run every context policy over a built-in ABA loop and compare what they retrieve.
    Demo {
        /// Distance from A to B in blocks.
        #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(1..=500))]
        range: u32,
    },
    /// Serve the REST API (sessions, step, observe, select) over the committed model and a local store.
    Serve {
        /// Model folder (ONNX graphs + manifest.json).
        #[arg(long, default_value = "fixtures/small")]
        model: PathBuf,
        /// Run without a model: observe and select work, step answers 409.
        #[arg(long, conflicts_with = "model")]
        memory_only: bool,
        /// Where the model's graphs run: in this process (default), or `triton://HOST:PORT`, a Triton
        /// Inference Server's HTTP port serving the model's graphs (serving/triton/host.py;
        /// docs/deployment.md). The manifest is still read from --model.
        #[arg(long, conflicts_with = "memory_only")]
        model_backend: Option<String>,
        /// The store: a redb file (created when missing), or a PostgreSQL database as
        /// postgres://USER[:PASSWORD]@HOST:PORT/DB (its schema is made and migrated on start).
        /// Either way the sessions in it are restored.
        #[arg(long, default_value = "data/worldpack.redb")]
        store: PathBuf,
        #[arg(long, default_value = "127.0.0.1:8080")]
        addr: std::net::SocketAddr,
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        /// Intra-op threads per model session.
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Sampler steps per generated frame (a step request may override).
        #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u64).range(1..=1000))]
        steps: u64,
        /// Sampler: ancestral, ddim or dpm2m (DPM-Solver++(2M): the 10-step DDIM's frames in about 8 calls).
        #[arg(long, default_value = "ancestral", value_parser = parse_method)]
        method: model::Method,
        /// Policy of sessions that do not name one, by name (memory::variants): a preset, or an option such as worldpack_target or worldpack_keep_last.
        #[arg(long, default_value = "worldpack", value_parser = plan::parse_variant)]
        policy: &'static memory::Variant,
        /// Requests queued on one session before the next is refused with 429.
        #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=100_000))]
        max_queue: u64,
        /// Model calls in flight across sessions before the next is refused with 503.
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=100_000))]
        max_inflight: u64,
        /// Geometry models only: each generated frame keeps the warp of its sources wherever it
        /// lands, and the model fills only the holes (the composite; docs/geometry.md).
        #[arg(long)]
        overlay_warp: bool,
        /// Choose each step's plan and a geometry model's warp sources by co-visibility from the
        /// observed frames' depth instead of frustum overlap (docs/geometry.md).
        #[arg(long)]
        covisible: bool,
        /// Batching across sessions: gather concurrent steps' model calls for up to this many
        /// milliseconds into one call (0: off, each step calls alone).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=1000))]
        batch_window_ms: u64,
        /// The most steps one batched call serves.
        #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u64).range(1..=1024))]
        batch_max: u64,
        /// Retention: delete sessions that no frame was written to for this many seconds
        /// (swept every quarter of it, at most every minute; 0: keep them until deleted).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=10 * 365 * 86_400))]
        retain_idle_secs: u64,
        /// API tokens: a file of lines `TENANT sha256:HEX [sessions=N] [rate=R]` (the SHA-256 of each
        /// token, never the token). Tokens may also come from the environment, WORLDPACK_TOKENS=TENANT:TOKEN,...;
        /// with either, every /v1 route needs `Authorization: Bearer <token>` (docs/api.md).
        #[arg(long)]
        tokens_file: Option<PathBuf>,
        /// Live sessions a tenant may own at once, unless its line in the tokens file says otherwise.
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
        max_sessions_per_tenant: u64,
        /// Requests a second a tenant may make (bursts of twice that), unless its line says otherwise.
        #[arg(long, default_value_t = 50.0)]
        rate_per_tenant: f64,
        /// Serve a non-loopback --addr without tokens: anyone who reaches it may use every session.
        #[arg(long)]
        allow_unauthenticated: bool,
        /// Serve HTTPS: the certificate chain, a PEM file (with --tls-key; default: plain HTTP).
        #[arg(long, requires = "tls_key")]
        tls_cert: Option<PathBuf>,
        /// The certificate's private key, a PEM file (PKCS#8, PKCS#1 or SEC1).
        #[arg(long, requires = "tls_cert")]
        tls_key: Option<PathBuf>,
        /// A fusion-head model's memory keeps each frame's sampled latent instead of re-encoding the blended frame shown (one encoder call less a step).
        #[arg(long)]
        sampled_latents: bool,
    },
    /// Benchmarks (tables on stdout; --json for machines).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
    /// The synthetic LoopNav-style voxel world: suites, training data, single frames.
    Sim {
        #[command(subcommand)]
        what: SimCommand,
    },
    /// The memory probe: teacher-forced next-frame prediction on a suite's return legs, for each trained
    /// variant, the WorldPack weights on recency contexts, and the copy and reproject references.
    Probe(probe::Options),
    /// Speed against accuracy, stability under pose noise and where methods
    /// fail (docs/results.md): the probe under many conditions, paired frame by frame.
    Study(study::Options),
    /// LoopNav-style evaluation: observe each trajectory's exploration, roll out its return leg
    /// autoregressively under each policy with its own weights, and score PSNR and SSIM per frame.
    Eval(Box<eval::Options>),
    /// Training examples for a geometry model's fusion head: its own predictions, the fused
    /// reference of its warp sources, where the warp landed and the truth, on a suite's return legs.
    FusionData(fusion::Options),
    /// PSNR and SSIM of two PNG images, as JSON (the metrics `eval` uses).
    Compare { a: PathBuf, b: PathBuf },
    /// Write each trajectory's context plans (plan-<policy>.npy) beside a suite or dataset, for training.
    Plan {
        /// A folder written by `worldpack sim dataset` or `sim loopnav`.
        #[arg(long)]
        data: PathBuf,
        /// Comma-separated policies by name (memory::variants): the presets baseline, nearest_frame_packing, memory_retrieval, worldpack, worldmem_greedy, and the options memory_retrieval_target, worldpack_target, worldpack_keep_last.
        #[arg(long, value_delimiter = ',', default_value = "baseline,nearest_frame_packing,memory_retrieval,worldpack",
              value_parser = plan::parse_variant)]
        policies: Vec<&'static memory::Variant>,
        /// Also write memory-need.npy per trajectory: the share of each frame's view that only frames older than the 4 newest show (for `train --memory-focus`).
        #[arg(long)]
        memory_need: bool,
    },
    /// Check a suite folder against the dataset format (docs/dataset.md): every file and field
    /// that training, `plan` and `eval` read. Names the file and field of the first fault.
    Check {
        /// A suite folder (index.json and one folder per trajectory).
        #[arg(long)]
        data: PathBuf,
    },
    /// Answer geometry requests: JSON on stdin (one object or an array), JSON on stdout.
    ///
    /// Ops: convert, project, resize, frustum, overlap, select. See docs/cli.md.
    Geometry {
        /// Read the request from this file instead of stdin.
        #[arg(long)]
        input: Option<std::path::PathBuf>,
    },
}

#[derive(Subcommand)]
enum SimCommand {
    /// Write the LoopNav evaluation suite: ABA and ABCA at ranges 5, 15, 30, 50 (test world seeds).
    Loopnav {
        #[arg(long)]
        out: PathBuf,
        /// Trajectories per (task, range); LoopNav uses 18.
        #[arg(long, default_value_t = 18, value_parser = clap::value_parser!(u32).range(1..=1000))]
        per_cell: u32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Frame size WxH.
        #[arg(long, default_value = "64x64", value_parser = sim::parse_size)]
        size: (u32, u32),
        /// Comma-separated tasks.
        #[arg(long, value_delimiter = ',', default_value = "aba,abca", value_parser = sim::parse_task)]
        tasks: Vec<world::Task>,
        /// Comma-separated navigation ranges in blocks.
        #[arg(long, value_delimiter = ',', default_value = "5,15,30,50")]
        ranges: Vec<i32>,
    },
    /// Write the occluder suite: a wall beside the way back hides it from the frames that stand closest to it (test world seeds; docs/geometry.md).
    Occluders {
        #[arg(long)]
        out: PathBuf,
        /// Scenes (one trajectory each).
        #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(u32).range(1..=1000))]
        count: u32,
        /// Length of the wall and of the way back, in blocks.
        #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(i32).range(4..=40))]
        range: i32,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Frame size WxH.
        #[arg(long, default_value = "64x64", value_parser = sim::parse_size)]
        size: (u32, u32),
    },
    /// Write training data: loop-style trajectories and free exploration (training world seeds).
    Dataset {
        #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
        trajectories: u32,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value = "64x64", value_parser = sim::parse_size)]
        size: (u32, u32),
    },
    /// Render one frame: rgb.png, depth.png, depth.npy and render.json.
    Render {
        #[arg(long)]
        out: PathBuf,
        /// World seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Camera as x,y,z,pitch,yaw (Minecraft convention, degrees, eye position). Default: the spawn point facing +z.
        #[arg(long, value_parser = sim::parse_pose5, allow_hyphen_values = true)]
        pose: Option<memory::Pose5>,
        /// Spawn in this biome instead (plains, forest, desert, snowy, mountains, badlands).
        #[arg(long, value_parser = sim::parse_biome, conflicts_with = "pose")]
        biome: Option<world::Biome>,
        #[arg(long, default_value = "64x64", value_parser = sim::parse_size)]
        size: (u32, u32),
        /// Pixel u,v whose block face is reported in render.json (default: the centre).
        #[arg(long, value_parser = parse_pixel)]
        probe: Option<(u32, u32)>,
    },
}




fn parse_pixel(s: &str) -> Result<(u32, u32), String> {
    let (u, v) = s.split_once(',').ok_or_else(|| format!("expected u,v, got {s:?}"))?;
    let n = |t: &str| t.trim().parse::<u32>().map_err(|_| format!("expected whole pixel coordinates u,v, got {s:?}"));
    Ok((n(u)?, n(v)?))
}

#[derive(Subcommand)]
enum BenchCommand {
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
        #[arg(long, default_value = "cpu", value_parser = parse_provider)]
        provider: model::Provider,
        /// Intra-op threads per model call (pin the process to one core with `taskset -c 0` for a one-core figure).
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

fn main() -> ExitCode {
    match Cli::parse().command {
        Command::Demo { range } => {
            let rows = demo::run(range);
            demo::print(range, &rows);
            ExitCode::SUCCESS
        }
        Command::Bench { what: BenchCommand::Select { candidates, workload, queries, json } } => {
            if let Some(bad) = candidates.iter().find(|&&n| n == 0 || n > 2_000_000) {
                eprintln!("worldpack bench select: --candidates must lie in 1..=2000000, got {bad}");
                return ExitCode::from(2);
            }
            let rows = benchmarks::select::run(workload, &candidates, queries as usize, true);
            if json {
                let out = serde_json::json!({ "workload": format!("{workload:?}").to_lowercase(), "rows": rows,
                    "loglog_slope": (rows.len() >= 2).then(|| benchmarks::select::loglog_slope(&rows)) });
                println!("{out}");
            } else {
                benchmarks::select::print(workload, &rows);
            }
            ExitCode::SUCCESS
        }
        Command::Bench { what: BenchCommand::Step { model, provider, threads, steps, calls, batches, json } } => {
            if let Some(bad) = steps.iter().find(|&&n| n == 0 || n > 1000) {
                eprintln!("worldpack bench step: --steps must lie in 1..=1000, got {bad}");
                return ExitCode::from(2);
            }
            let batches: Vec<usize> = batches.iter().map(|&b| b as usize).collect();
            report(benchmarks::step::run(&model, model::RuntimeOptions { provider, threads }, &steps, calls as usize, &batches, json), "bench step")
        }
        Command::Bench { what: BenchCommand::Serve { model, steps, calls, sessions, per_session, provider, threads, batch_window_ms, model_backend, json } } => {
            if let Some(bad) = sessions.iter().find(|&&n| n == 0 || n > 256) {
                eprintln!("worldpack bench serve: --sessions must lie in 1..=256, got {bad}");
                return ExitCode::from(2);
            }
            let runtime = model::RuntimeOptions { provider, threads };
            report(benchmarks::serve::run(&model, runtime, steps as usize, calls as usize, &sessions, per_session as usize, batch_window_ms, model_backend.as_deref(), json), "bench serve")
        }
        Command::Bench { what: BenchCommand::Walk { model, steps, method, covisible, sampled_latents, sessions, walk_steps, explore, provider, threads, json } } => {
            if let Some(bad) = sessions.iter().find(|&&n| n == 0 || n > 256) {
                eprintln!("worldpack bench walk: --sessions must lie in 1..=256, got {bad}");
                return ExitCode::from(2);
            }
            let runtime = model::RuntimeOptions { provider, threads };
            let o = benchmarks::walk::Options { steps: steps as usize, method, covisible, sampled_latents, walk_steps: walk_steps as usize, explore: explore as usize };
            report(benchmarks::walk::run(&model, runtime, &o, &sessions, json), "bench walk")
        }
        Command::Bench { what: BenchCommand::Store { frames, json } } => report(benchmarks::store::run(frames as usize, json), "bench store"),
        Command::Bench { what: BenchCommand::StepProbe { model, layout, provider, threads, calls } } => {
            report(benchmarks::step::probe(&model, &layout, model::RuntimeOptions { provider, threads }, calls), "bench step-probe")
        }
        Command::Bench { what: BenchCommand::Render { frames, seed } } => report(sim::bench_render(frames as usize, seed), "bench render"),
        Command::Sim { what } => match what {
            SimCommand::Loopnav { out, per_cell, seed, size, tasks, ranges } => {
                report(sim::loopnav(&out, per_cell as usize, seed, size, &tasks, &ranges), "sim loopnav")
            }
            SimCommand::Occluders { out, count, range, seed, size } => {
                report(sim::occluders(&out, count as usize, range, seed, size), "sim occluders")
            }
            SimCommand::Dataset { trajectories, out, seed, size } => {
                report(sim::dataset(&out, trajectories as usize, seed, size), "sim dataset")
            }
            SimCommand::Render { out, seed, pose, biome, size, probe } => {
                report(sim::render_one(&out, seed, pose, biome, size, probe), "sim render")
            }
        },
        Command::Serve { model, memory_only, model_backend, store, addr, provider, threads, steps, method, policy, max_queue, max_inflight, overlay_warp, covisible, batch_window_ms, batch_max, retain_idle_secs, tokens_file, max_sessions_per_tenant, rate_per_tenant, allow_unauthenticated, tls_cert, tls_key, sampled_latents } => {
            if !(rate_per_tenant.is_finite() && rate_per_tenant > 0.0) {
                eprintln!("worldpack serve: --rate-per-tenant: must be a positive number, got {rate_per_tenant}");
                return ExitCode::from(2);
            }
            let limits = api::auth::Limits { sessions: max_sessions_per_tenant as usize, rate: rate_per_tenant };
            let env = std::env::var(api::auth::TOKENS_ENV).ok();
            let tokens = match api::auth::Tokens::load(tokens_file.as_deref(), env.as_deref(), &limits) {
                Ok(t) => std::sync::Arc::new(t),
                Err(e) => {
                    eprintln!("worldpack serve: {e}");
                    return ExitCode::from(2);
                }
            };
            let config = api::Config {
                tokens,
                allow_unauthenticated,
                tls: tls_cert.zip(tls_key),
                sampled_latents,
                addr,
                store,
                model: (!memory_only).then_some(model),
                model_backend,
                runtime: model::RuntimeOptions { provider, threads },
                steps: steps as usize,
                method,
                policy: serde_json::json!({ "kind": policy.kind, "query": policy.query, "keep_last": policy.keep_last }),
                max_queue_per_session: max_queue as usize,
                max_inflight: max_inflight as usize,
                overlay_warp,
                covisible,
                batch_window: (batch_window_ms > 0).then(|| std::time::Duration::from_millis(batch_window_ms)),
                batch_max: batch_max as usize,
                retain_idle: (retain_idle_secs > 0).then(|| std::time::Duration::from_secs(retain_idle_secs)),
                ..api::Config::default()
            };
            report(serve(config), "serve")
        }
        Command::Probe(o) => report(probe::run(&o), "probe"),
        Command::FusionData(o) => report(fusion::run(&o), "fusion-data"),
        Command::Study(o) => report(study::run(&o), "study"),
        Command::Eval(o) => report(eval::run(&o), "eval"),
        Command::Compare { a, b } => report(eval::compare(&a, &b), "compare"),
        Command::Plan { data, policies, memory_need } => report(plan::run(&data, &policies, memory_need), "plan"),
        Command::Check { data } => report(check_suite(&data), "check"),
        Command::Geometry { input } => {
            let text = match input {
                Some(path) => std::fs::read_to_string(&path).map_err(|e| format!("cannot read {}: {e}", path.display())),
                None => {
                    let mut s = String::new();
                    std::io::stdin().read_to_string(&mut s).map(|_| s).map_err(|e| format!("cannot read stdin: {e}"))
                }
            };
            match text.and_then(|t| geometry::run(&t)) {
                Ok((out, all_ok)) => {
                    println!("{out}");
                    if all_ok { ExitCode::SUCCESS } else { ExitCode::from(2) }
                }
                Err(message) => {
                    eprintln!("worldpack geometry: {message}");
                    ExitCode::from(2)
                }
            }
        }
    }
}

fn serve(config: api::Config) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async {
        let server = api::Server::bind(config).await.map_err(anyhow::Error::msg)?;
        println!("worldpack serve: {}", server.description);
        use std::io::Write;
        std::io::stdout().flush()?;
        server.run().await.map_err(anyhow::Error::msg)
    })
}

/// Prints an error chain as one line naming the command; exit code 2.
fn check_suite(data: &std::path::Path) -> anyhow::Result<()> {
    let c = ::eval::suite::check(data)?;
    println!(
        "{}: {} trajectories, {} frames ({} on return legs), {}x{}, {}",
        data.display(),
        c.trajectories,
        c.frames,
        c.returning_frames,
        c.width,
        c.height,
        if c.without_depth == 0 { "depth in every trajectory".to_string() } else { format!("{} without depth", c.without_depth) }
    );
    Ok(())
}

fn report(result: anyhow::Result<()>, command: &str) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("worldpack {command}: {e:#}");
            ExitCode::from(2)
        }
    }
}
