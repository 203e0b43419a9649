//! `worldpack bench store`: the two embedded databases the server could use,
//! on frames of the size it writes (a 4x16x16 f32 latent plus a 64x64 PNG),
//! one durable transaction per frame: redb (what `api::store` uses) against
//! SQLite in WAL mode with `synchronous = FULL` (rusqlite, bundled).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use api::store::{FrameMeta, FrameRecord, SessionRecord, Store};
use serde::Serialize;

use eval::stats::percentile;

#[derive(Serialize)]
struct Row {
    store: &'static str,
    frames: usize,
    bytes_per_frame: usize,
    commit_median_ms: f64,
    commit_p99_ms: f64,
    commits_per_s: f64,
    read_all_ms: f64,
    file_mib: f64,
}

/// A frame like the server's: latent noise and a PNG of a rendered view.
fn sample_frame(world: &world::World, i: u64) -> FrameRecord {
    let k = world::suite::default_intrinsics(64, 64).expect("default camera");
    let cell = world::agent::spawn_point(world, None).expect("a spawn");
    let player = world::agent::PlayerState::at_cell(cell, (i * 37 % 360) as f64);
    let frame = world::render::render(world, &player.camera(), &k, &world::render::RenderSettings::default());
    FrameRecord {
        meta: FrameMeta { c2w: player.camera().matrix_rows(), time: i, source: "generated".into(), action: Some(vec![1.0, 0.0, 0.0, 0.0, 0.0, 5.0, 0.0]), player: None },
        latent: model::generate::gaussian(i, 4 * 16 * 16),
        png: world::picture::encode_png(64, 64, &frame.rgb),
        depth_png16: Vec::new(),
    }
}

fn dir() -> PathBuf {
    let d = std::env::temp_dir().join(format!("worldpack-bench-store-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn row(store: &'static str, bytes: usize, mut ms: Vec<f64>, total_s: f64, read_all_ms: f64, file: &std::path::Path) -> Row {
    ms.sort_by(f64::total_cmp);
    let size: u64 = std::fs::read_dir(file.parent().unwrap())
        .map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().starts_with(&*file.file_name().unwrap().to_string_lossy())).map(|e| e.metadata().map_or(0, |m| m.len())).sum())
        .unwrap_or(0);
    Row {
        store,
        frames: ms.len(),
        bytes_per_frame: bytes,
        commit_median_ms: percentile(&ms, 0.5),
        commit_p99_ms: percentile(&ms, 0.99),
        commits_per_s: ms.len() as f64 / total_s,
        read_all_ms,
        file_mib: size as f64 / (1 << 20) as f64,
    }
}

pub fn run(frames: usize, json: bool) -> Result<()> {
    let base = dir();
    let world = world::World::generate(1);
    let samples: Vec<FrameRecord> = (0..16).map(|i| sample_frame(&world, i)).collect();
    let bytes = samples.iter().map(|f| f.encode().len()).sum::<usize>() / samples.len();
    let record = SessionRecord { policy: serde_json::json!({ "kind": "worldpack" }), tenant: None, intrinsics: world::suite::default_intrinsics(64, 64)?, world_seed: None, fork: None };

    // redb, through the server's own store.
    let path = base.join("frames.redb");
    let store = Store::open(&path)?;
    let id = store.create_session(&record, &samples[0])?;
    let mut ms = Vec::new();
    let start = Instant::now();
    for i in 1..=frames as u64 {
        let t = Instant::now();
        store.put_frame(id, i, &samples[i as usize % samples.len()])?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let total = start.elapsed().as_secs_f64();
    let t = Instant::now();
    let n = store.frames(id)?.len();
    anyhow::ensure!(n == frames + 1, "redb read back {n} frames, wrote {}", frames + 1);
    let redb_row = row("redb (Durability::Immediate)", bytes, ms, total, t.elapsed().as_secs_f64() * 1e3, &path);
    drop(store);

    // SQLite, WAL, full sync: the same bytes per frame, one transaction each.
    let path = base.join("frames.sqlite");
    let db = rusqlite::Connection::open(&path)?;
    db.pragma_update(None, "journal_mode", "WAL")?;
    db.pragma_update(None, "synchronous", "FULL")?;
    db.execute("CREATE TABLE frames (session INTEGER, idx INTEGER, data BLOB, PRIMARY KEY (session, idx))", [])?;
    let mut ms = Vec::new();
    let start = Instant::now();
    for i in 1..=frames as u64 {
        let t = Instant::now();
        let tx = db.unchecked_transaction()?;
        tx.execute("INSERT INTO frames VALUES (1, ?1, ?2)", rusqlite::params![i as i64, samples[i as usize % samples.len()].encode()])?;
        tx.commit()?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let total = start.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut stmt = db.prepare("SELECT data FROM frames WHERE session = 1 ORDER BY idx")?;
    let decoded: Vec<FrameRecord> = stmt
        .query_map([], |r| r.get::<_, Vec<u8>>(0))?
        .map(|b| Ok(FrameRecord::decode(&b?)?))
        .collect::<Result<_>>()?;
    anyhow::ensure!(decoded.len() == frames, "SQLite read back {} frames, wrote {frames}", decoded.len());
    let sqlite_row = row("SQLite (WAL, synchronous=FULL)", bytes, ms, total, t.elapsed().as_secs_f64() * 1e3, &path);
    let _ = std::fs::remove_dir_all(&base);

    let rows = [redb_row, sqlite_row];
    if json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
        return Ok(());
    }
    println!("{frames} frames of {bytes} bytes, one durable transaction each, in {}\n", std::env::temp_dir().display());
    println!("{:<32} {:>12} {:>10} {:>10} {:>14} {:>10}", "store", "commit (ms)", "p99 (ms)", "commits/s", "read all (ms)", "file (MiB)");
    for r in &rows {
        println!(
            "{:<32} {:>12.3} {:>10.3} {:>10.1} {:>14.1} {:>10.2}",
            r.store, r.commit_median_ms, r.commit_p99_ms, r.commits_per_s, r.read_all_ms, r.file_mib
        );
    }
    Ok(())
}
