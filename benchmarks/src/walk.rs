//! `worldpack bench walk`: what a step of the main job costs as a user
//! drives it. Each session observes an exploration of the synthetic world,
//! turns round and generates its way back through `Engine::step`, the call
//! the server's step handler makes (durable commit included). Only the
//! generated steps are timed, stage by stage.

use std::path::Path;
use std::sync::Barrier;
use std::time::Instant;

use anyhow::{Result, anyhow};
use api::EngineError;
use api::engine::{Engine, StepOptions};
use api::store::Store;
use model::{Method, RuntimeOptions, Sampler};
use motion::Action;
use serde::Serialize;
use serde_json::json;

/// The walk each session takes.
#[derive(Clone, Copy, Debug)]
pub struct Walk {
    /// Observed steps before the turn (frames from the world, not timed).
    pub explore: usize,
    /// Generated steps after the turn (the turn is generated and timed too).
    pub back: usize,
    /// The sessions' frame width (`None`: the model's).
    pub size: Option<u32>,
    /// Each step scored against the world's true frame, as the server's steps are unless told not to.
    pub truth: bool,
}

/// The stages a step's answer reports (`StepOutcome::timings_ms`), and the whole step.
pub const STAGES: [&str; 8] = ["select", "warp", "sample", "decode", "full_size", "truth", "store", "total"];

/// One row: `sessions` walking at once.
#[derive(Clone, Debug, Serialize)]
pub struct WalkRow {
    pub sessions: usize,
    pub steps: usize,
    pub steps_per_s: f64,
    /// Per stage (`STAGES`'s order): p50 and p99 in ms.
    pub p50_ms: Vec<f64>,
    pub p99_ms: Vec<f64>,
}

/// Generated steps that turn the walk round, 10 degrees each.
pub(crate) const TURN: usize = 18;

/// Exploration: forward, a slow left turn every 4th step; the turn: `TURN`
/// steps of 10 degrees; the way back mirrors the exploration's turns.
pub(crate) fn action(walk: &Walk, i: usize) -> Action {
    let yaw_deg = if i < walk.explore {
        if i.is_multiple_of(4) { 8.0 } else { 0.0 }
    } else if i < walk.explore + TURN {
        10.0
    } else if i.is_multiple_of(4) {
        -8.0
    } else {
        0.0
    };
    Action { forward: !(walk.explore..walk.explore + TURN).contains(&i), yaw_deg, ..Action::default() }
}

/// One session's walk: each generated step's stage timings and total, and
/// when its generated steps began and ended. `ready` holds every walk at
/// the turn until all have explored, so the timed phases overlap.
fn one_walk(engine: &Engine, policy: &serde_json::Value, sampler: &Sampler, seed: u64, walk: &Walk, ready: &Barrier) -> Result<Timed, EngineError> {
    let explored = (|| -> Result<api::session::Session, EngineError> {
        let mut s = engine.create_synthetic(policy.clone(), seed, None, walk.size, None)?;
        for i in 0..walk.explore {
            engine.step_observed(&mut s, &action(walk, i))?;
        }
        Ok(s)
    })();
    ready.wait(); // also on an error, so the other walks are not left waiting
    let mut s = explored?;
    let began = Instant::now();
    let mut times = Vec::with_capacity(TURN + walk.back);
    for i in walk.explore..walk.explore + TURN + walk.back {
        let t = Instant::now();
        let out = engine.step(&mut s, &action(walk, i), sampler, &StepOptions { truth: walk.truth, ..StepOptions::default() })?;
        let total = t.elapsed().as_secs_f64() * 1e3;
        let [a, b, c, d, e, f, g] = out.timings_ms;
        times.push([a, b, c, d, e, f, g, total]);
    }
    Ok(Timed { times, began, ended: Instant::now() })
}

struct Timed {
    times: Vec<[f64; 8]>,
    began: Instant,
    ended: Instant,
}

/// `sessions` walks at once on threads sharing `engine`; `o.walk_steps`
/// generated steps in all, split evenly (at least 25 each).
pub fn walk_row(engine: &Engine, policy: &serde_json::Value, sampler: &Sampler, sessions: usize, o: &Options) -> Result<WalkRow, EngineError> {
    let back = o.walk_steps.div_ceil(sessions).max(25);
    let walk = Walk { explore: o.explore, back, size: o.size, truth: o.truth };
    let ready = Barrier::new(sessions);
    let results: Vec<Result<Timed, EngineError>> = std::thread::scope(|scope| {
        let ready = &ready;
        let workers: Vec<_> = (0..sessions).map(|k| scope.spawn(move || one_walk(engine, policy, sampler, 7 + k as u64, &walk, ready))).collect();
        workers.into_iter().map(|w| w.join().expect("a walk thread panicked")).collect()
    });
    let timed = results.into_iter().collect::<Result<Vec<_>, _>>()?;
    // Generated steps per second while the walks generated.
    let began = timed.iter().map(|t| t.began).min().expect("at least one session");
    let ended = timed.iter().map(|t| t.ended).max().expect("at least one session");
    let all: Vec<[f64; 8]> = timed.into_iter().flat_map(|t| t.times).collect();
    let wall = ended.duration_since(began).as_secs_f64();
    let generated = all.len();
    let column = |k: usize| {
        let mut v: Vec<f64> = all.iter().map(|t| t[k]).collect();
        v.sort_by(f64::total_cmp);
        v
    };
    let (mut p50, mut p99) = (Vec::new(), Vec::new());
    for k in 0..STAGES.len() {
        let v = column(k);
        p50.push(eval::stats::percentile(&v, 0.5));
        p99.push(eval::stats::percentile(&v, 0.99));
    }
    Ok(WalkRow { sessions, steps: generated, steps_per_s: generated as f64 / wall, p50_ms: p50, p99_ms: p99 })
}

pub struct Options {
    pub steps: usize,
    pub method: Method,
    pub covisible: bool,
    pub sampled_latents: bool,
    pub walk_steps: usize,
    pub explore: usize,
    /// The sessions' frame width (`None`: the model's size).
    pub size: Option<u32>,
    /// Score each step against the world's true frame (a session of real frames has none).
    pub truth: bool,
}

pub fn run(model_dir: &Path, runtime: RuntimeOptions, o: &Options, sessions: &[usize], json_out: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-walk-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut model = api::load_model(model_dir, None, runtime).map_err(anyhow::Error::msg)?;
    model.keep_sampled_latents(o.sampled_latents);
    let sampler = Sampler::new(&model.manifest().diffusion, o.steps, o.method, 0.0)?;
    let mut engine = Engine::new(Store::open(&dir.join("store.redb"))?, Some(model));
    engine.max_frame_side = engine.max_frame_side.max(o.size.unwrap_or(0));
    // Co-visibility is the sessions' policy's choice, as a client would make it.
    let policy = json!({ "kind": "worldpack", "covisibility": o.covisible.then(memory::CoVisibility::default) });
    let rows = sessions
        .iter()
        .map(|&n| walk_row(&engine, &policy, &sampler, n, o).map_err(|e| anyhow!("{}: {}", e.field, e.message)))
        .collect::<Result<Vec<_>>>();
    drop(engine);
    let _ = std::fs::remove_dir_all(&dir);
    let rows = rows?;
    if json_out {
        // What the sampler runs: a distilled model's own grid, whatever was asked.
        let report = json!({ "model": model_dir, "steps": sampler.len(), "timesteps": sampler.timesteps, "method": sampler.method.name(), "covisible": o.covisible, "sampled_latents": o.sampled_latents,
                             "threads": runtime.threads, "explore": o.explore, "size": o.size, "truth": o.truth, "stages": STAGES, "rows": rows });
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "model {}, {} {} steps, covisible {}, sampled latents {}, {} intra-op thread(s), frames {}, truth scored {}; {} observed steps, then the way back generated\n",
        model_dir.display(), sampler.len(), sampler.method.name(), o.covisible, o.sampled_latents, runtime.threads,
        o.size.map_or_else(|| "at the model's size".to_string(), |s| format!("{s} wide")), o.truth, o.explore
    );
    print!("{:>8} {:>6} {:>8}", "sessions", "steps", "steps/s");
    for s in STAGES {
        print!(" {:>15}", format!("{s} p50/p99"));
    }
    println!();
    for r in &rows {
        print!("{:>8} {:>6} {:>8.2}", r.sessions, r.steps, r.steps_per_s);
        for k in 0..STAGES.len() {
            print!(" {:>15}", format!("{:.1}/{:.1}", r.p50_ms[k], r.p99_ms[k]));
        }
        println!();
    }
    println!("\n(ms; p50/p99 over the generated steps of every session in the row)");
    Ok(())
}
