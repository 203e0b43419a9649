//! `worldpack bench imagine`: imagined frames per second, and where the
//! speed comes from. A synthetic session explores as `bench walk`'s do; then
//! K candidates of H steps are made three ways from its present:
//! - batched: one `Engine::imagine` of all K (one model call per step);
//! - alone: K `Engine::imagine` calls of one candidate each (no batching);
//! - stepped: K forks, each stepped H times through `Engine::step` (what a
//!   client without imagine does: a durable commit, PNG encoding and, in a
//!   synthetic session, the world's true frame scored, every step).
//!
//! batched against alone is what batching buys, with what sharing buys when
//! candidates begin alike (`--drawn`: frames made is then below K × H);
//! alone against stepped what skipping the step's other work buys (split by
//! the step's own timings). Every frame is decoded in all three (the model
//! decodes in `predict`) except the last step of "last latent".

use std::path::Path;
use std::time::Instant;

use anyhow::{Result, anyhow};
use api::EngineError;
use api::engine::{Engine, StepOptions};
use api::imagine::{Candidate, Last};
use api::store::Store;
use model::{Method, RuntimeOptions, Sampler};
use motion::Action;
use serde::Serialize;
use serde_json::json;

use crate::walk::{Walk, action};

pub struct Options {
    pub steps: usize,
    pub method: Method,
    pub covisible: bool,
    pub explore: usize,
    pub horizon: usize,
    pub rounds: usize,
    /// Candidates drawn as the example planner draws them (some share first actions).
    pub drawn: bool,
}

#[derive(Serialize)]
pub struct Row {
    pub candidates: usize,
    pub horizon: usize,
    /// Frames the batched imagine made (K × H less those candidates with the same prefix shared).
    pub made: usize,
    /// Imagined frames per second, median over the rounds.
    pub batched_fps: f64,
    /// Batched, with the last step left as a latent (scored in latent space: not decoded).
    pub latent_last_fps: f64,
    pub alone_fps: f64,
    pub stepped_fps: f64,
    /// Per frame in the batched runs (ms): poses, plans and warp sources; the warp; sampling; decoding.
    pub batched_ms: [f64; 4],
    /// Per frame in the stepped runs (ms): the step's stages (select, warp, sample, decode with PNG
    /// encoding, full size (0: the sessions are at the model's size), the world's true frame rendered
    /// and scored, store commit) and the rest (the fork).
    pub stepped_ms: [f64; 8],
}

fn fail(e: EngineError) -> anyhow::Error {
    anyhow!("{}: {}", e.field, e.message)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Candidate k turns by its own angle every step and walks forward every other one.
fn candidates(k: usize, horizon: usize) -> Vec<Candidate> {
    (0..k)
        .map(|c| {
            let yaw_deg = (c as f64 - k as f64 / 2.0) * 6.0;
            Candidate { actions: (0..horizon).map(|h| Action { forward: h % 2 == 0, yaw_deg, ..Action::default() }).collect(), poses: None }
        })
        .collect()
}

/// K candidates as the example planner's first round draws them: each step one of its six
/// actions (a key or a turn of 15° either way), uniformly, from a fixed seed.
fn drawn(k: usize, horizon: usize, seed: u64) -> Vec<Candidate> {
    let choices = [
        Action { forward: true, ..Action::default() },
        Action { back: true, ..Action::default() },
        Action { left: true, ..Action::default() },
        Action { right: true, ..Action::default() },
        Action { yaw_deg: 15.0, ..Action::default() },
        Action { yaw_deg: -15.0, ..Action::default() },
    ];
    let mut rng = memory::rng::SplitMix64::new(seed);
    (0..k)
        .map(|_| Candidate { actions: (0..horizon).map(|_| choices[(rng.next_u64() % choices.len() as u64) as usize]).collect(), poses: None })
        .collect()
}

fn row(engine: &Engine, s: &mut api::session::Session, sampler: &Sampler, k: usize, o: &Options) -> Result<Row, EngineError> {
    let cands = if o.drawn { drawn(k, o.horizon, 7) } else { candidates(k, o.horizon) };
    let frames = (k * o.horizon) as f64;
    let mut made = 0;
    let (mut batched, mut latent_last, mut alone, mut stepped) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut batched_ms, mut stepped_ms) = ([0.0; 4], [0.0; 8]);
    for round in 0..o.rounds {
        let seed = Some(round as u64);
        let t = Instant::now();
        let all = engine.imagine(s, &cands, sampler, seed, Last::Frame)?;
        batched.push(frames / t.elapsed().as_secs_f64());
        made = all.made;
        for (acc, v) in batched_ms.iter_mut().zip([all.select_ms, all.warp_ms, all.sample_ms, all.decode_ms]) {
            *acc += v / frames / o.rounds as f64;
        }
        let t = Instant::now();
        engine.imagine(s, &cands, sampler, seed, Last::Latent)?;
        latent_last.push(frames / t.elapsed().as_secs_f64());
        let t = Instant::now();
        for c in &cands {
            engine.imagine(s, std::slice::from_ref(c), sampler, seed, Last::Frame)?;
        }
        alone.push(frames / t.elapsed().as_secs_f64());
        let mut took = 0.0;
        for c in &cands {
            let t = Instant::now();
            let mut fork = engine.fork(s)?;
            let mut stages = 0.0;
            for (h, a) in c.actions.iter().enumerate() {
                let out = engine.step(&mut fork, a, sampler, &StepOptions { seed: seed.map(|x| x + h as u64), ..StepOptions::default() })?;
                for (acc, v) in stepped_ms.iter_mut().zip(out.timings_ms) {
                    *acc += v / frames / o.rounds as f64;
                    stages += v;
                }
            }
            let elapsed = t.elapsed().as_secs_f64();
            took += elapsed;
            stepped_ms[7] += (elapsed * 1e3 - stages) / frames / o.rounds as f64;
            engine.store.delete_session(fork.id)?; // not timed: forks are dropped between rounds
        }
        stepped.push(frames / took);
    }
    Ok(Row { candidates: k, horizon: o.horizon, made, batched_fps: median(batched), latent_last_fps: median(latent_last), alone_fps: median(alone), stepped_fps: median(stepped), batched_ms, stepped_ms })
}

pub fn run(model_dir: &Path, runtime: RuntimeOptions, o: &Options, ks: &[usize], json_out: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-imagine-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let model = api::load_model(model_dir, None, runtime).map_err(anyhow::Error::msg)?;
    let sampler = Sampler::new(&model.manifest().diffusion, o.steps, o.method, 0.0)?;
    let engine = Engine::new(Store::open(&dir.join("store.redb"))?, Some(model));
    let policy = json!({ "kind": "worldpack", "covisibility": o.covisible.then(memory::CoVisibility::default) });
    let rows = (|| -> Result<Vec<Row>, EngineError> {
        let mut s = engine.create_synthetic(policy, 7, None, None, None)?;
        let walk = Walk { explore: o.explore, back: 0, size: None, truth: true };
        for i in 0..o.explore {
            engine.step_observed(&mut s, &action(&walk, i))?;
        }
        ks.iter().map(|&k| row(&engine, &mut s, &sampler, k, o)).collect()
    })()
    .map_err(fail);
    drop(engine);
    let _ = std::fs::remove_dir_all(&dir);
    let rows = rows?;
    if json_out {
        let report = json!({ "model": model_dir, "steps": sampler.len(), "method": sampler.method.name(), "covisible": o.covisible,
                             "threads": runtime.threads, "explore": o.explore, "rounds": o.rounds, "drawn": o.drawn, "rows": rows });
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "model {}, {} {} steps, covisible {}, {} intra-op thread(s); {} observed steps, then K candidates of {} steps, median of {} rounds\n",
        model_dir.display(), sampler.len(), sampler.method.name(), o.covisible, runtime.threads, o.explore, o.horizon, o.rounds
    );
    println!("{:>3} {:>6} {:>12} {:>12} {:>12} {:>10} {:>10} {:>10} {:>14} {:>10}", "K", "made", "batched f/s", "alone f/s", "stepped f/s", "batching", "skipping", "in all",
        "last latent f/s", "in all");
    for r in &rows {
        println!("{:>3} {:>6} {:>12.2} {:>12.2} {:>12.2} {:>9.2}× {:>9.2}× {:>9.2}× {:>14.2} {:>9.2}×", r.candidates, r.made, r.batched_fps, r.alone_fps, r.stepped_fps,
            r.batched_fps / r.alone_fps, r.alone_fps / r.stepped_fps, r.batched_fps / r.stepped_fps, r.latent_last_fps, r.latent_last_fps / r.stepped_fps);
    }
    println!("\nms per frame    batched: select / warp / sample / decode        stepped: select / warp / sample / decode+png / store / rest");
    for r in &rows {
        let b = r.batched_ms;
        let st = r.stepped_ms;
        println!("K = {:<3} {:>14.2} / {:.2} / {:.2} / {:.2} {:>22.2} / {:.2} / {:.2} / {:.2} / {:.2} / {:.2}", r.candidates, b[0], b[1], b[2], b[3], st[0], st[1], st[2], st[3], st[6], st[5] + st[7]);
    }
    println!("\n(made: frames the batched imagine made of K × H, the rest shared by candidates that begin alike;");
    println!(" batching: batched over alone, sharing included; skipping: alone over stepped, the step's commit, PNG and truth scoring; rest: the true frame and the fork;");
    println!(" last latent: batched, the last step not decoded, as when candidates are scored in latent space)");
    Ok(())
}
