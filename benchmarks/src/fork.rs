//! `worldpack bench fork`: what forking a long session costs. A session of
//! `frames` frames (server-sized latents, poses along a walk) is stored in a
//! redb file; then, `forks` times, one frame is added to it and it is forked
//! through `Engine::fork` (the store's record and link, then the shared
//! runs in memory), and once more in memory only (`Session::fork`). Against
//! it, what a fork that copied would pay at least: indexing every frame
//! again (`Session::restore`, no store writes). And what sharing costs
//! later: the plan of a step over the forked session's runs against the same
//! frames in one run.

use std::time::Instant;

use anyhow::{Result, anyhow};
use api::EngineError;
use api::engine::{Engine, meta};
use api::session::{GENERATED, Session};
use api::store::{FrameRecord, SessionRecord, Store};
use eval::stats::percentile;
use memory::workload::{Workload, frusta};
use serde::Serialize;

#[derive(Serialize)]
pub struct Report {
    pub frames: usize,
    pub forks: usize,
    /// `Engine::fork`: the store's commit and the shared runs.
    pub fork_median_ms: f64,
    pub fork_p99_ms: f64,
    /// `Session::fork` alone: the memory side.
    pub memory_fork_median_ms: f64,
    pub memory_fork_p99_ms: f64,
    /// Indexing every frame again, what a copying fork would pay at least.
    pub copy_median_ms: f64,
    /// Runs the forked session's history reads after the forks.
    pub runs: usize,
    /// A step's plan over those runs, and over the same frames in one run.
    pub select_runs_median_ms: f64,
    pub select_one_run_median_ms: f64,
}

fn fail(e: EngineError) -> anyhow::Error {
    anyhow!("{}: {}", e.field, e.message)
}

fn median_p99(mut ms: Vec<f64>) -> (f64, f64) {
    ms.sort_by(f64::total_cmp);
    (percentile(&ms, 0.5), percentile(&ms, 0.99))
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

pub fn run(frames: usize, forks: usize, json: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-fork-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let result = measure(&dir, frames.max(1), forks.max(1));
    let _ = std::fs::remove_dir_all(&dir);
    let report = result?;
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print(&report);
    }
    Ok(())
}

fn measure(dir: &std::path::Path, frames: usize, forks: usize) -> Result<Report> {
    let k = world::suite::default_intrinsics(64, 64)?;
    let path = frusta(Workload::Walk, frames + 2 * forks, 5, k);
    let png = world::picture::encode_png(64, 64, &[100; 64 * 64 * 3]);
    let frame = |i: usize| FrameRecord {
        meta: meta(path[i].pose(), i as u64, GENERATED, None, None),
        latent: model::generate::gaussian(i as u64, 4 * 16 * 16),
        png: png.clone(),
        depth_png16: Vec::new(),
    };
    let record = SessionRecord { policy: serde_json::json!({ "kind": "worldpack" }), intrinsics: k, world_seed: None, tenant: None, fork: None };
    let engine = Engine::new(Store::open(&dir.join("fork.redb"))?, None);
    eprintln!("storing a session of {frames} frames ...");
    let records: Vec<FrameRecord> = (0..frames).map(frame).collect();
    let mut parent = engine.create(record.clone(), records.clone(), None).map_err(fail)?;

    let copy: Vec<f64> = (0..5)
        .map(|_| {
            let t = Instant::now();
            Session::restore(0, record.clone(), records.clone(), None).map(|_| ms(t))
        })
        .collect::<Result<_, _>>()
        .map_err(fail)?;
    drop(records);

    let (mut fork_ms, mut memory_ms) = (Vec::new(), Vec::new());
    let mut next = frames;
    let mut add = |parent: &mut Session| -> Result<()> {
        let f = frame(next);
        engine.store.put_frame(parent.id, parent.len(), &f)?;
        parent.push(f.meta.time, *path[next].pose(), f.latent, None, true).map_err(fail)?;
        next += 1;
        Ok(())
    };
    for round in 0..forks {
        add(&mut parent)?;
        let t = Instant::now();
        let fork = engine.fork(&mut parent).map_err(fail)?;
        fork_ms.push(ms(t));
        drop(fork);
        add(&mut parent)?;
        let t = Instant::now();
        let fork = parent.fork(u64::MAX - round as u64, record.clone()).map_err(fail)?;
        memory_ms.push(ms(t));
        drop(fork);
    }

    // The next step's plan over the runs the forks left, and over one run of the same frames.
    let all = engine.store.frames(parent.id)?;
    let one_run = Session::restore(parent.id, parent.record.clone(), all, None).map_err(fail)?;
    let targets: Vec<_> = (0..50).map(|i| path[(i * 197) % path.len()].clone()).collect();
    let time_plans = |s: &Session| -> Result<Vec<f64>> {
        targets
            .iter()
            .map(|target| {
                let t = Instant::now();
                s.plan(&s.policy, target, None).map(|_| ms(t)).map_err(fail)
            })
            .collect()
    };
    let (select_runs, select_one) = (time_plans(&parent)?, time_plans(&one_run)?);
    for target in &targets {
        let (a, b) = (parent.plan(&parent.policy, target, None).map_err(fail)?, one_run.plan(&one_run.policy, target, None).map_err(fail)?);
        if a.plan != b.plan {
            return Err(anyhow!("the plan over {} runs differs from the plan over one", parent.history().segments()));
        }
    }

    let (fork_median_ms, fork_p99_ms) = median_p99(fork_ms);
    let (memory_fork_median_ms, memory_fork_p99_ms) = median_p99(memory_ms);
    Ok(Report {
        frames,
        forks,
        fork_median_ms,
        fork_p99_ms,
        memory_fork_median_ms,
        memory_fork_p99_ms,
        copy_median_ms: median_p99(copy).0,
        runs: parent.history().segments(),
        select_runs_median_ms: median_p99(select_runs).0,
        select_one_run_median_ms: median_p99(select_one).0,
    })
}

fn print(r: &Report) {
    println!("forking a session of {} frames (redb, durable commit), {} forks, each after one new frame", r.frames, r.forks);
    println!("{:<52} {:>12} {:>10}", "what", "median (ms)", "p99 (ms)");
    println!("{:<52} {:>12.4} {:>10.4}", "fork (Engine::fork: store record + link, memory)", r.fork_median_ms, r.fork_p99_ms);
    println!("{:<52} {:>12.4} {:>10.4}", "  of which in memory (Session::fork)", r.memory_fork_median_ms, r.memory_fork_p99_ms);
    println!("{:<52} {:>12.2} {:>10}", format!("a copy instead: indexing {} frames again", r.frames), r.copy_median_ms, "");
    println!("{:<52} {:>12.3} {:>10}", format!("a step's plan over the {} runs the forks left", r.runs), r.select_runs_median_ms, "");
    println!("{:<52} {:>12.3} {:>10}", "  over the same frames in one run", r.select_one_run_median_ms, "");
}
