//! `worldpack bench serve`: what HTTP adds to a step, and how the server
//! holds up under concurrent sessions. The library side calls the same
//! `api::engine::Engine::step` the server's handler calls, with the same
//! durable write, interleaved with the HTTP steps so machine drift hits both.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use api::engine::{Engine, StepOptions};
use api::store::Store;
use model::{RuntimeOptions, Sampler};
use serde::Serialize;
use serde_json::{Value, json};
use motion::Action;

use eval::stats::percentile;

#[derive(Serialize)]
struct Report {
    model: String,
    steps: usize,
    calls: usize,
    library_median_ms: f64,
    library_p95_ms: f64,
    http_median_ms: f64,
    http_p95_ms: f64,
    http_over_library: f64,
    concurrency: Vec<ConcurrencyRow>,
}

#[derive(Serialize)]
struct ConcurrencyRow {
    /// The batching window in ms (0: each step calls the model alone).
    batch_window_ms: u64,
    sessions: usize,
    steps: usize,
    throughput_steps_per_s: f64,
    p50_ms: f64,
    p99_ms: f64,
}

fn action(i: usize) -> Action {
    Action { forward: true, yaw_deg: if i.is_multiple_of(4) { 8.0 } else { 0.0 }, ..Action::default() }
}

fn post(url: &str, body: &Value) -> Result<Value> {
    let r = ureq::post(url).set("Content-Type", "application/json").send_string(&body.to_string());
    match r {
        Ok(resp) => Ok(resp.into_json()?),
        Err(ureq::Error::Status(code, resp)) => Err(anyhow!("{url}: HTTP {code}: {}", resp.into_string().unwrap_or_default())),
        Err(e) => Err(anyhow!("{url}: {e}")),
    }
}

fn temp_store(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("worldpack-bench-serve-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir.join("store.redb")
}

pub fn run(
    model_dir: &Path,
    runtime: RuntimeOptions,
    steps: usize,
    calls: usize,
    sessions: &[usize],
    per_session: usize,
    batch_window_ms: u64,
    model_backend: Option<&str>,
    json_out: bool,
) -> Result<()> {
    let policy = json!({ "kind": "worldpack" });
    // The library path: an engine with its own store, no HTTP.
    let lib_store = temp_store("library");
    let engine = Engine::new(Store::open(&lib_store)?, Some(api::load_model(model_dir, model_backend, runtime).map_err(anyhow::Error::msg)?));
    let sampler = Sampler::new(&engine.model.as_ref().unwrap().manifest().diffusion, steps, model::Method::Ancestral, 0.0)?;
    let mut session = engine.create_synthetic(policy.clone(), 3, None, None, None).map_err(|e| anyhow!("{}", e.message))?;

    // The HTTP path: the real server on loopback, in this process.
    let http_store = temp_store("http");
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let serve = |store: &Path, batch_window: Option<std::time::Duration>| -> Result<String> {
        let config = api::Config {
            addr: "127.0.0.1:0".parse()?,
            store: store.to_path_buf(),
            model: Some(model_dir.to_path_buf()),
            model_backend: model_backend.map(String::from),
            runtime,
            steps,
            batch_window,
            batch_max: sessions.iter().copied().max().unwrap_or(1),
            ..api::Config::default()
        };
        let server = rt.block_on(api::Server::bind(config)).map_err(anyhow::Error::msg)?;
        let base = format!("http://{}", server.local_addr());
        rt.spawn(server.run());
        Ok(base)
    };
    let base = serve(&http_store, None)?;
    let id = post(&format!("{base}/v1/sessions"), &json!({ "synthetic": { "seed": 3 }, "policy": policy }))?["session"].as_u64().context("session id")?;

    let (mut lib_ms, mut http_ms) = (Vec::new(), Vec::new());
    for i in 0..calls + 2 {
        let a = action(i);
        let t = Instant::now();
        engine.step(&mut session, &a, &sampler, &StepOptions::default()).map_err(|e| anyhow!("{}", e.message))?;
        let l = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        post(&format!("{base}/v1/sessions/{id}/step"), &json!({ "action": a }))?;
        let h = t.elapsed().as_secs_f64() * 1e3;
        if i >= 2 {
            lib_ms.push(l);
            http_ms.push(h);
        }
    }
    lib_ms.sort_by(f64::total_cmp);
    http_ms.sort_by(f64::total_cmp);

    let mut concurrency = concurrent_steps(&base, 0, sessions, per_session)?;
    if batch_window_ms > 0 {
        // The same rows against a second server that batches across sessions.
        let batched_store = temp_store("batched");
        let batched = serve(&batched_store, Some(std::time::Duration::from_millis(batch_window_ms)))?;
        concurrency.extend(concurrent_steps(&batched, batch_window_ms, sessions, per_session)?);
        let _ = std::fs::remove_dir_all(batched_store.parent().unwrap());
    }
    let report = Report {
        model: model_dir.display().to_string(),
        steps,
        calls,
        library_median_ms: percentile(&lib_ms, 0.5),
        library_p95_ms: percentile(&lib_ms, 0.95),
        http_median_ms: percentile(&http_ms, 0.5),
        http_p95_ms: percentile(&http_ms, 0.95),
        http_over_library: percentile(&http_ms, 0.5) / percentile(&lib_ms, 0.5),
        concurrency,
    };
    let _ = std::fs::remove_dir_all(lib_store.parent().unwrap());
    let _ = std::fs::remove_dir_all(http_store.parent().unwrap());
    if json_out {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!("model {}, {} sampler steps, WorldPack policy, {} interleaved steps each\n", report.model, steps, calls);
    println!("{:<34} {:>12} {:>10}", "one step", "median (ms)", "p95 (ms)");
    println!("{:<34} {:>12.2} {:>10.2}", "library (engine.step + commit)", report.library_median_ms, report.library_p95_ms);
    println!("{:<34} {:>12.2} {:>10.2}", "HTTP (POST .../step)", report.http_median_ms, report.http_p95_ms);
    println!("\nHTTP / library: {:.3}x (target <= 1.05x)\n", report.http_over_library);
    println!("{:>10} {:>9} {:>7} {:>16} {:>10} {:>10}", "batching", "sessions", "steps", "steps/s", "p50 (ms)", "p99 (ms)");
    for r in &report.concurrency {
        let batching = if r.batch_window_ms == 0 { "off".to_string() } else { format!("{} ms", r.batch_window_ms) };
        println!("{:>10} {:>9} {:>7} {:>16.2} {:>10.1} {:>10.1}", batching, r.sessions, r.steps, r.throughput_steps_per_s, r.p50_ms, r.p99_ms);
    }
    Ok(())
}

/// Steps/s, p50 and p99 with `n` sessions stepping at once, for each `n`.
fn concurrent_steps(base: &str, batch_window_ms: u64, sessions: &[usize], per_session: usize) -> Result<Vec<ConcurrencyRow>> {
    let mut concurrency = Vec::new();
    for &n in sessions {
        let ids: Vec<u64> = (0..n)
            .map(|k| post(&format!("{base}/v1/sessions"), &json!({ "synthetic": { "seed": k % 4 } })).map(|v| v["session"].as_u64().unwrap_or(0)))
            .collect::<Result<_>>()?;
        let started = Instant::now();
        let results: Vec<Result<Vec<f64>>> = std::thread::scope(|s| {
            let workers: Vec<_> = ids
                .iter()
                .map(|&sid| {
                    s.spawn(move || {
                        (0..per_session)
                            .map(|i| {
                                let t = Instant::now();
                                post(&format!("{base}/v1/sessions/{sid}/step"), &json!({ "action": action(i) }))?;
                                Ok(t.elapsed().as_secs_f64() * 1e3)
                            })
                            .collect::<Result<Vec<f64>>>()
                    })
                })
                .collect();
            workers.into_iter().map(|w| w.join().expect("bench client panicked")).collect()
        });
        let wall = started.elapsed().as_secs_f64();
        let mut all: Vec<f64> = results.into_iter().collect::<Result<Vec<_>>>()?.into_iter().flatten().collect();
        all.sort_by(f64::total_cmp);
        concurrency.push(ConcurrencyRow {
            batch_window_ms,
            sessions: n,
            steps: all.len(),
            throughput_steps_per_s: all.len() as f64 / wall,
            p50_ms: percentile(&all, 0.5),
            p99_ms: percentile(&all, 0.99),
        });
    }
    Ok(concurrency)
}
