//! `worldpack bench select`: selection latency against the number of stored
//! frames, indexed against brute force, on one core.

use eval::stats::percentile;
use std::time::Instant;

use memory::covisibility::{self, CoVisibility, DepthGrid};
use memory::overlap::MonteCarlo;
use memory::workload::ground_depth;
use memory::{ContextPlan, Estimator, FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind, select_by_brute_force};
use serde::Serialize;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Workload {
    /// LoopNav-like back-and-forth inside a 50×50-block square: nearly every box meets the query.
    Loop,
    /// A long walk across a large world: the R-tree's case.
    Walk,
}

impl From<Workload> for memory::workload::Workload {
    fn from(w: Workload) -> Self {
        match w {
            Workload::Loop => memory::workload::Workload::Loop,
            Workload::Walk => memory::workload::Workload::Walk,
        }
    }
}

#[derive(Serialize)]
pub struct Row {
    pub frames: usize,
    pub indexed_median_ms: f64,
    pub indexed_p95_ms: f64,
    pub brute_exact_median_ms: f64,
    pub brute_exact_p95_ms: f64,
    pub brute_mc_median_ms: f64,
    pub brute_mc_repeats: usize,
    /// Brute-force median over the indexed median of the same queries (timed alternately).
    pub speedup_vs_brute_exact: f64,
    pub speedup_vs_brute_mc: f64,
    pub exact_evaluations_per_selection: f64,
    pub box_candidates_per_selection: f64,
    pub insert_us_per_frame: f64,
    /// Resident memory the index grew by per stored frame (VmRSS before and after the inserts; Linux).
    pub index_bytes_per_frame: Option<f64>,
    /// Occlusion-aware selection (memory::covisibility, default settings:
    /// frustum top 64, then co-visibility on a 16-column depth grid) over
    /// the same memory with every frame's coarse depth of the workload's ground.
    pub covisibility_median_ms: f64,
    pub covisibility_p95_ms: f64,
    /// Its median over the indexed frustum selection's.
    pub covisibility_vs_indexed: f64,
}

/// Times `f` on each query until `queries` are done or `budget_s` is spent (at least `min` runs).
fn timed<T>(queries: usize, min: usize, budget_s: f64, mut f: impl FnMut(usize) -> T) -> Vec<f64> {
    let mut ms = Vec::new();
    let start = Instant::now();
    for q in 0..queries {
        if q >= min && start.elapsed().as_secs_f64() > budget_s {
            break;
        }
        let t = Instant::now();
        std::hint::black_box(f(q));
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    ms
}

pub fn run(workload: Workload, sizes: &[usize], queries: usize, progress: bool) -> Vec<Row> {
    let k = Intrinsics::from_fov(70.0, None, 64, 64).expect("constant intrinsics");
    let worldpack = Policy::preset(PolicyKind::WorldPack);
    let mut monte_carlo = Policy::preset(PolicyKind::WorldPack);
    monte_carlo.estimator = Estimator::MonteCarlo(MonteCarlo { samples: 10_000, seed: 0 });
    let largest = sizes.iter().copied().max().unwrap_or(0);
    let all = memory::workload::frusta(workload.into(), largest + queries, 7, k);
    sizes
        .iter()
        .map(|&n| {
            if progress {
                eprintln!("bench select: {workload:?}, {n} frames");
            }
            let mut frames: Vec<MemoryFrame> =
                (0..n).map(|t| MemoryFrame { id: t as u64, time: t as u64, frustum: all[t].clone() }).collect();
            let rss_before = crate::step::status_kib("VmRSS:").ok();
            let mut memory = FrameMemory::new();
            let insert_start = Instant::now();
            for f in &frames {
                memory.insert(f.clone()).expect("unique ids");
            }
            let insert_us = insert_start.elapsed().as_secs_f64() * 1e6 / n as f64;
            let rss_after = crate::step::status_kib("VmRSS:").ok();
            let index_bytes_per_frame = rss_before.zip(rss_after).map(|(a, b)| b.saturating_sub(a) as f64 * 1024.0 / n as f64);
            // Targets: the poses that follow the stored history.
            let targets: Vec<Frustum> = all[n..n + queries].to_vec();

            // Indexed and brute force alternate query by query, so a slow spell of the
            // machine touches both and the speed-up compares the same queries in the same
            // window. Brute force stops after ~4 s (at least 3 queries). As in a session,
            // each target's frame is stored once its plan is made: WorldPack queries the
            // newest frame's view (Algorithm 1), so each query asks about a new view.
            let settings = CoVisibility::default();
            let mut depth: Vec<DepthGrid> = frames.iter().map(|f| ground_depth(&f.frustum, settings.cells)).collect();
            let (mut covisible, mut last_covisible) = (Vec::new(), None::<ContextPlan>);
            let mut previous: Option<ContextPlan> = None;
            let (mut evaluations, mut candidates) = (0usize, 0usize);
            let (mut indexed, mut brute) = (Vec::new(), Vec::new());
            let brute_start = Instant::now();
            for (q, target) in targets.iter().enumerate() {
                let t = Instant::now();
                let (plan, stats) = memory.select(&worldpack, target, previous.as_ref());
                indexed.push(t.elapsed().as_secs_f64() * 1e3);
                evaluations += stats.overlap_evaluations;
                candidates += stats.box_candidates;
                previous = Some(plan);
                if q < 3 || brute_start.elapsed().as_secs_f64() <= 4.0 {
                    let t = Instant::now();
                    std::hint::black_box(select_by_brute_force(&worldpack, target, &frames));
                    brute.push(t.elapsed().as_secs_f64() * 1e3);
                }
                let t = Instant::now();
                let (plan, _) = covisibility::rerank(&memory, &worldpack, target, &settings, last_covisible.as_ref(), |id| depth.get(id as usize))
                    .expect("valid settings");
                covisible.push(t.elapsed().as_secs_f64() * 1e3);
                last_covisible = Some(plan);
                depth.push(ground_depth(target, settings.cells));
                let stored = MemoryFrame { id: (n + q) as u64, time: (n + q) as u64, frustum: target.clone() };
                memory.insert(stored.clone()).expect("unique ids");
                frames.push(stored);
            }
            let mut paired_indexed = indexed[..brute.len()].to_vec();
            for v in [&mut indexed, &mut brute, &mut paired_indexed, &mut covisible] {
                v.sort_by(f64::total_cmp);
            }
            let mc = timed(queries, 1, 4.0, |q| select_by_brute_force(&monte_carlo, &targets[q], &frames));
            let med = |v: &[f64]| percentile(v, 0.5);
            Row {
                frames: n,
                indexed_median_ms: med(&indexed),
                indexed_p95_ms: percentile(&indexed, 0.95),
                brute_exact_median_ms: med(&brute),
                brute_exact_p95_ms: percentile(&brute, 0.95),
                brute_mc_median_ms: med(&mc),
                brute_mc_repeats: mc.len(),
                speedup_vs_brute_exact: med(&brute) / med(&paired_indexed),
                speedup_vs_brute_mc: med(&mc) / med(&indexed),
                exact_evaluations_per_selection: evaluations as f64 / queries as f64,
                box_candidates_per_selection: candidates as f64 / queries as f64,
                insert_us_per_frame: insert_us,
                index_bytes_per_frame,
                covisibility_median_ms: med(&covisible),
                covisibility_p95_ms: percentile(&covisible, 0.95),
                covisibility_vs_indexed: med(&covisible) / med(&indexed),
            }
        })
        .collect()
}

/// Least-squares slope of log(indexed median) against log(frames).
pub fn loglog_slope(rows: &[Row]) -> f64 {
    let pts: Vec<(f64, f64)> = rows.iter().map(|r| ((r.frames as f64).ln(), r.indexed_median_ms.ln())).collect();
    let n = pts.len() as f64;
    let (mx, my) = (pts.iter().map(|p| p.0).sum::<f64>() / n, pts.iter().map(|p| p.1).sum::<f64>() / n);
    let cov: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let var: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    cov / var
}

pub fn print(workload: Workload, rows: &[Row]) {
    println!("selection (score + plan), WorldPack policy, 22 slots, one core, workload {workload:?}");
    println!(
        "{:>8} | {:>9} {:>9} | {:>10} {:>10} | {:>10} {:>4} | {:>9} {:>9} | {:>8} {:>8} | {:>7} {:>8} | {:>9} {:>7}",
        "frames", "idx med", "idx p95", "brute med", "brute p95", "MC10k med", "reps", "x brute", "x MC", "evals", "boxes", "ins µs", "B/frame", "covis med", "x idx"
    );
    for r in rows {
        println!(
            "{:>8} | {:>7.3}ms {:>7.3}ms | {:>8.2}ms {:>8.2}ms | {:>8.1}ms {:>4} | {:>8.1}x {:>8.0}x | {:>8.1} {:>8.1} | {:>7.1} {:>8} | {:>7.3}ms {:>6.2}x",
            r.frames,
            r.indexed_median_ms,
            r.indexed_p95_ms,
            r.brute_exact_median_ms,
            r.brute_exact_p95_ms,
            r.brute_mc_median_ms,
            r.brute_mc_repeats,
            r.speedup_vs_brute_exact,
            r.speedup_vs_brute_mc,
            r.exact_evaluations_per_selection,
            r.box_candidates_per_selection,
            r.insert_us_per_frame,
            r.index_bytes_per_frame.map_or("n/a".to_string(), |b| format!("{b:.0}")),
            r.covisibility_median_ms,
            r.covisibility_vs_indexed
        );
    }
    if rows.len() >= 2 {
        println!("log-log slope of indexed median against frames: {:.2}", loglog_slope(rows));
    }
}
