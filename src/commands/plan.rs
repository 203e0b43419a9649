//! `worldpack plan`: the context plans a model trains on, written beside a
//! suite or dataset by the same selection code that serves the model, so
//! training and serving pick memories identically.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use memory::{FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind, Pose, Variant};
use serde::Deserialize;

use crate::cli::{bar, threads};

#[derive(clap::Args)]
pub struct Args {
    /// A folder written by `worldpack sim dataset` or `sim loopnav`.
    #[arg(long)]
    pub data: PathBuf,
    /// Comma-separated policies by name (memory::variants): the presets baseline, nearest_frame_packing, memory_retrieval, worldpack, worldmem_greedy, and the options memory_retrieval_target, worldpack_target, worldpack_keep_last.
    #[arg(long, value_delimiter = ',', default_value = "baseline,nearest_frame_packing,memory_retrieval,worldpack",
          value_parser = parse_variant)]
    pub policies: Vec<&'static memory::Variant>,
    /// Also write memory-need.npy per trajectory: the share of each frame's view that only frames older than the 4 newest show (for `train --memory-focus`).
    #[arg(long)]
    pub memory_need: bool,
}

pub const PLANS_FORMAT: &str = "worldpack-plans/1";

#[derive(Deserialize)]
struct Index {
    trajectories: Vec<Entry>,
}

#[derive(Deserialize)]
struct Entry {
    dir: String,
}

#[derive(Deserialize)]
struct Meta {
    intrinsics: Intrinsics,
}

/// The file a variant's plans go to inside each trajectory folder.
pub fn plan_file(variant: &Variant) -> String {
    format!("plan-{}.npy", variant.name)
}

/// A preset's name as a command-line value (serve, eval).
pub fn parse_policy(s: &str) -> Result<PolicyKind, String> {
    let v = memory::variant(s).map_err(|e| e.to_string())?;
    if memory::Policy::preset(v.kind) != v.policy() {
        return Err(format!("{s:?} is an option of the {} policy, not a preset; give a preset here", v.kind.name()));
    }
    Ok(v.kind)
}

/// Any named variant as a command-line value (plan).
pub fn parse_variant(s: &str) -> Result<&'static Variant, String> {
    memory::variant(s).map_err(|e| e.to_string())
}

/// For every trajectory under `data` and every policy, writes
/// `plan-<policy>.npy`: int32 `(T, slots)`, row `t` the frame indices (in
/// slot order, `-1` for an empty slot) chosen as context for predicting frame
/// `t` from frames `0..t`, with frame `t`'s pose as the query. Row 0 is all
/// `-1`. Then `plans.json` at the root describes each policy's slots.
///
/// With `memory_need`, each trajectory also gets `memory-need.npy`: float32
/// `(T,)`, the share of frame `t`'s view that only frames older than the 4
/// newest show ([`eval::strata::memory_need`], every [`NEED_STRIDE`]-th pixel
/// row and column), so training can draw more of the targets where memory
/// beyond recency helps.
pub fn run(a: &Args) -> Result<()> {
    write_plans(&a.data, &a.policies, a.memory_need)
}

fn write_plans(data: &Path, variants: &[&'static Variant], memory_need: bool) -> Result<()> {
    let index_path = data.join("index.json");
    let text = std::fs::read_to_string(&index_path)
        .with_context(|| format!("--data: no suite at {} (make one with `worldpack sim dataset`)", index_path.display()))?;
    let index: Index = serde_json::from_str(&text).with_context(|| format!("--data: {} is not a suite index", index_path.display()))?;
    if variants.is_empty() {
        bail!("--policies: name at least one policy");
    }
    let policies: Vec<Policy> = variants.iter().map(|v| v.policy()).collect();
    // The need reads depth and every field of the suite index; only load those when asked.
    let suite_entries = if memory_need { Some(eval::suite::entries(data).context("--data")?) } else { None };

    let progress = bar(index.trajectories.len(), "plan");
    let next = AtomicUsize::new(0);
    let failures: Vec<anyhow::Error> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads())
            .map(|_| {
                scope.spawn(|| {
                    let mut failed = Vec::new();
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(entry) = index.trajectories.get(i) else { break };
                        let dir = data.join(&entry.dir);
                        let need = suite_entries.as_ref().map(|all| write_memory_need(data, &all[i]));
                        if let Err(e) = plan_trajectory(&dir, variants).and(need.unwrap_or(Ok(()))) {
                            failed.push(e.context(dir.display().to_string()));
                        }
                        progress.set_message(entry.dir.clone());
                        progress.inc(1);
                    }
                    failed
                })
            })
            .collect();
        workers.into_iter().flat_map(|w| w.join().expect("plan worker panicked")).collect()
    });
    progress.finish();
    if let Some(first) = failures.into_iter().next() {
        return Err(first);
    }

    // Entries of earlier runs for other policies stay (e.g. keep-last plans beside plain ones).
    let previous: Vec<serde_json::Value> = std::fs::read_to_string(data.join("plans.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["policies"].as_array().cloned())
        .unwrap_or_default();
    let names: Vec<&str> = variants.iter().map(|v| v.name).collect();
    let mut described: Vec<_> = previous.into_iter().filter(|e| !names.iter().any(|n| e["name"] == *n)).collect();
    described.extend(variants.iter().zip(&policies).map(|(v, p)| {
        serde_json::json!({
            "name": v.name,
            "file": plan_file(v),
            "rates": p.packing.rates().collect::<Vec<_>>(),
            "policy": p,
        })
    }));
    let out = serde_json::json!({
        "format": PLANS_FORMAT,
        "query": "each policy's own (policy.query): current = frame t-1's pose (Algorithm 1), target = frame t's; candidates are all earlier frames of the trajectory",
        "empty_slot": -1,
        "policies": described,
    });
    std::fs::write(data.join("plans.json"), serde_json::to_string_pretty(&out)?)?;
    println!("wrote plans for {} trajectories, policies {names:?} -> {}", index.trajectories.len(), data.join("plans.json").display());
    Ok(())
}

/// Pixel stride of the surface points [`run`] scores the memory need on
/// (every 4th row and column: 256 points of a 64×64 frame).
pub const NEED_STRIDE: usize = 4;

fn write_memory_need(data: &Path, entry: &eval::suite::Entry) -> Result<()> {
    let traj = eval::suite::Trajectory::load(data, entry)?;
    let need = eval::strata::memory_need(&traj, NEED_STRIDE)?;
    world::npy::write(&data.join(&entry.dir).join("memory-need.npy"), &[need.len()], &need)?;
    Ok(())
}

fn plan_trajectory(dir: &Path, variants: &[&Variant]) -> Result<()> {
    let meta: Meta = serde_json::from_str(&std::fs::read_to_string(dir.join("meta.json"))?).context("meta.json")?;
    let (shape, poses) = world::npy::read::<f64>(&dir.join("poses.npy")).context("poses.npy")?;
    if shape.len() != 3 || shape[1..] != [4, 4] {
        bail!("poses.npy: expected shape (T, 4, 4), got {shape:?}");
    }
    let frusta = poses
        .chunks_exact(16)
        .map(|m| {
            let rows = [0, 1, 2, 3].map(|i| [m[4 * i], m[4 * i + 1], m[4 * i + 2], m[4 * i + 3]]);
            Frustum::new(Pose::from_matrix_rows(rows)?, meta.intrinsics)
        })
        .collect::<Result<Vec<_>, _>>()
        .context("poses.npy")?;
    for variant in variants {
        let policy = &variant.policy();
        let slots = policy.packing.slots();
        let mut rows = vec![-1i32; frusta.len() * slots];
        let mut store = FrameMemory::new();
        let mut previous = None;
        for (t, frustum) in frusta.iter().enumerate() {
            if t > 0 {
                let (plan, _) = store.select(policy, frustum, previous.as_ref());
                for (slot, chosen) in plan.slots.iter().enumerate() {
                    if let Some(f) = chosen.frame {
                        rows[t * slots + slot] = f.id as i32;
                    }
                }
                previous = Some(plan);
            }
            store.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: frustum.clone() })?;
        }
        world::npy::write(&dir.join(plan_file(variant)), &[frusta.len(), slots], &rows)?;
    }
    Ok(())
}
