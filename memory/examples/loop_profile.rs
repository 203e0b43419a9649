//! Where loop selection spends its effort, without the CLI: builds the
//! `bench select` loop memory of N frames (default 100,000), prints for three
//! targets how far every candidate's overlap falls short of what it would need
//! to enter the plan, then the median over 30 targets of each target's best
//! time in five passes (robust to a busy machine; each pass stores the
//! targets as `bench select` does) with the selection's counts.
//!   cargo run --release -p memory --example loop_profile [N] [PASSES]

use std::time::Instant;

use memory::overlap::exact_overlap;
use memory::policy::age;
use memory::workload::{Workload, frusta};
use memory::{ContextPlan, FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind};

const QUERIES: usize = 30;

fn main() {
    let arg = |i: usize, default: usize| match std::env::args().nth(i).map(|s| s.parse()) {
        None => default,
        Some(Ok(n)) if n > 0 => n,
        Some(_) => {
            eprintln!("usage: loop_profile [FRAMES > 0] [PASSES > 0]");
            std::process::exit(2);
        }
    };
    let (n, passes) = (arg(1, 100_000), arg(2, 5));
    let k = Intrinsics::from_fov(70.0, None, 64, 64).expect("constant intrinsics");
    let views = frusta(Workload::Loop, n + QUERIES, 7, k);
    let memory = stored(&views[..n]);
    let policy = Policy::preset(PolicyKind::WorldPack);
    for target in &views[n..n + 3] {
        shortfalls(&memory, &policy, target);
    }
    // As `bench select` does: each target's frame is stored once its plan is
    // made (WorldPack queries the newest frame's view), so every pass starts
    // from a fresh copy of the same n frames.
    let mut best = vec![f64::INFINITY; QUERIES];
    let mut counts = [0usize; 4];
    for pass in 0..passes {
        let mut memory = stored(&views[..n]);
        let mut previous: Option<ContextPlan> = None;
        for (q, target) in views[n..].iter().enumerate() {
            let start = Instant::now();
            let (plan, stats) = timed_select(&memory, &policy, target, previous.as_ref());
            best[q] = best[q].min(start.elapsed().as_secs_f64() * 1e3);
            if pass == 0 {
                for (c, v) in counts.iter_mut().zip([stats.overlap_evaluations, stats.cut_short, stats.group_bounds, stats.box_candidates]) {
                    *c += v;
                }
            }
            previous = Some(plan);
            let t = (n + q) as u64;
            memory.insert(MemoryFrame { id: t, time: t, frustum: target.clone() }).expect("unique ids");
        }
    }
    best.sort_by(f64::total_cmp);
    let [evals, cut, bounds, boxes] = counts.map(|c| c / QUERIES);
    println!("{n} frames: {:.3} ms; per selection {evals} evaluations ({cut} cut short), {bounds} hull bounds, {boxes} box candidates", best[QUERIES / 2]);
}

/// The timed call, on its own so that a profiler can count it alone
/// (`valgrind --tool=callgrind --toggle-collect='*timed_select*'`).
#[inline(never)]
fn timed_select(memory: &FrameMemory, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, memory::SelectionStats) {
    memory.select(policy, target, previous)
}

fn stored(views: &[Frustum]) -> FrameMemory {
    let mut memory = FrameMemory::new();
    for (t, f) in views.iter().enumerate() {
        memory.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: f.clone() }).expect("unique ids");
    }
    memory
}

/// How many stored frames fall short of the overlap they would need to enter
/// the plan (the 22nd-best score plus their age's penalty), by how much.
fn shortfalls(memory: &FrameMemory, policy: &Policy, target: &Frustum) {
    let (plan, _) = memory.select(policy, target, None);
    let worst = plan.selected().map(|(_, f)| f.score).fold(f64::INFINITY, f64::min);
    let t_now = memory.frames().iter().map(|f| f.time).max().unwrap_or(0);
    let edges = [0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7];
    let mut bins = [0usize; 8];
    for f in memory.frames().iter().filter(|f| f.frustum.aabb().intersects(target.aabb())) {
        let need = (worst + policy.weights.recency * age(f.time, t_now)) / policy.weights.overlap;
        let gap = need - exact_overlap(target, &f.frustum);
        bins[edges.iter().filter(|&&e| gap > e).count()] += 1;
    }
    println!("22nd-best score {worst:.3}; frames whose box meets the target's, by shortfall (≤0, ≤.05, ≤.1, ≤.2, ≤.3, ≤.5, ≤.7, more): {bins:?}");
}
