//! `worldpack bench walk`: the main job's step, stage by stage (the workload
//! is `api::walk_bench`; this prints it).

use std::path::Path;

use anyhow::{Result, anyhow};
use api::engine::Engine;
use api::store::Store;
use api::walk_bench::{self, STAGES};
use model::{Method, RuntimeOptions, Sampler};
use serde_json::json;

pub struct Options {
    pub steps: usize,
    pub method: Method,
    pub covisible: bool,
    pub walk_steps: usize,
    pub explore: usize,
}

pub fn run(model_dir: &Path, runtime: RuntimeOptions, o: &Options, sessions: &[usize], json_out: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-walk-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let model = api::load_model(model_dir, None, runtime).map_err(anyhow::Error::msg)?;
    let sampler = Sampler::new(&model.manifest().diffusion, o.steps, o.method, 0.0)?;
    let mut engine = Engine::new(Store::open(&dir.join("store.redb"))?, Some(model));
    engine.covisible = o.covisible;
    let policy = json!({ "kind": "worldpack" });
    let rows = sessions
        .iter()
        .map(|&n| walk_bench::run(&engine, &policy, &sampler, n, o.walk_steps, o.explore).map_err(|e| anyhow!("{}: {}", e.field, e.message)))
        .collect::<Result<Vec<_>>>();
    drop(engine);
    let _ = std::fs::remove_dir_all(&dir);
    let rows = rows?;
    if json_out {
        let report = json!({ "model": model_dir, "steps": o.steps, "method": o.method.name(), "covisible": o.covisible,
                             "threads": runtime.threads, "explore": o.explore, "stages": STAGES, "rows": rows });
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "model {}, {} {} steps, covisible {}, {} intra-op thread(s); {} observed steps, then the way back generated\n",
        model_dir.display(), o.steps, o.method.name(), o.covisible, runtime.threads, o.explore
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
