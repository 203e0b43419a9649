//! The indexed selection returns exactly the brute-force plan, for every
//! policy, on random walks, loops and ties.

use glam::{DMat3, DVec3, EulerRot};
use memory::policy::PolicySpec;
use memory::rng::SplitMix64;
use memory::{ContextPlan, FrameMemory, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind, Pose, Stack, select_by_brute_force};

fn frustum(pos: DVec3, yaw: f64, pitch: f64) -> Frustum {
    let k = Intrinsics::from_fov(70.0, None, 64, 64).unwrap();
    Frustum::new(Pose::new(DMat3::from_euler(EulerRot::YXZ, yaw, pitch, 0.0), pos).unwrap(), k).unwrap()
}

/// A LoopNav-like loop inside a 50-block square, or a long walk, with exact
/// repeats of earlier poses so that scores tie.
fn trajectory(rng: &mut SplitMix64, n: usize, walk: bool) -> Vec<(DVec3, f64, f64)> {
    let mut out: Vec<(DVec3, f64, f64)> = Vec::with_capacity(n);
    let (mut pos, mut yaw) = (DVec3::new(0.0, 64.0, 0.0), 0.0f64);
    for i in 0..n {
        if i > 3 && rng.next_f64() < 0.1 {
            let (p, y, pi) = out[(rng.next_f64() * i as f64) as usize];
            out.push((p, y, pi));
            continue;
        }
        yaw += (rng.next_f64() - 0.5) * 0.8;
        pos += DVec3::new(yaw.sin(), 0.0, yaw.cos()) * (0.5 + rng.next_f64());
        if !walk {
            pos.x = pos.x.clamp(-25.0, 25.0);
            pos.z = pos.z.clamp(-25.0, 25.0);
            if pos.x.abs() == 25.0 || pos.z.abs() == 25.0 {
                yaw += std::f64::consts::PI;
            }
        }
        out.push((pos, yaw, (rng.next_f64() - 0.5) * 0.4));
    }
    out
}

fn policies() -> Vec<Policy> {
    let mut out = Vec::new();
    for kind in [PolicyKind::Baseline, PolicyKind::NearestFramePacking, PolicyKind::MemoryRetrieval, PolicyKind::WorldPack, PolicyKind::WorldMemGreedy] {
        for keep_last in [false, true] {
            let mut p = Policy::preset(kind);
            p.keep_last = keep_last;
            if kind == PolicyKind::WorldMemGreedy {
                p.estimator = memory::Estimator::WorldMem(memory::overlap::WorldMemBall { samples: 500, ..Default::default() });
            }
            out.push(p);
        }
    }
    for estimator in [r#"{"kind": "monte_carlo", "samples": 500, "seed": 4}"#, r#"{"kind": "worldmem", "samples": 500, "radius": 30, "hfov_deg": 105, "vfov_deg": 75, "seed": 4}"#] {
        let json = format!(r#"{{"kind": "worldpack", "estimator": {estimator}}}"#);
        out.push(serde_json::from_str::<PolicySpec>(&json).unwrap().into_policy().unwrap());
    }
    out
}

/// 160 poses of a loop or walk, their frames (two a time step, so times tie), and the generator, to draw on.
fn workload(walk: bool, seed: u64) -> (Vec<(DVec3, f64, f64)>, Vec<MemoryFrame>, SplitMix64) {
    let mut rng = SplitMix64::new(seed);
    let poses = trajectory(&mut rng, 160, walk);
    let frames = poses
        .iter()
        .enumerate()
        .map(|(t, &(p, y, pi))| MemoryFrame { id: 1000 + t as u64, time: t as u64 / 2, frustum: frustum(p, y, pi) })
        .collect();
    (poses, frames, rng)
}

fn check(walk: bool, seed: u64) {
    let (poses, frames, _) = workload(walk, seed);
    let mut memory = FrameMemory::new();
    let policies = policies();
    let mut previous: Vec<Option<ContextPlan>> = vec![None; policies.len()];
    for (t, frame) in frames.iter().enumerate() {
        memory.insert(frame.clone()).unwrap();
        if t % 9 != 0 && t != frames.len() - 1 {
            continue;
        }
        let (p, y, pi) = if t + 1 < poses.len() { poses[t + 1] } else { poses[0] };
        let target = frustum(p, y, pi);
        for (i, policy) in policies.iter().enumerate() {
            let want = select_by_brute_force(policy, &target, &frames[..=t]);
            let (got, _) = memory.select(policy, &target, previous[i].as_ref());
            assert_eq!(got, want, "{:?} keep_last={} at t={t} (walk={walk})", policy.kind, policy.keep_last);
            // A stale or unrelated warm start must not change the answer either.
            let (cold, _) = memory.select(policy, &target, None);
            assert_eq!(cold, want);
            previous[i] = Some(got);
        }
    }
}

#[test]
fn indexed_equals_brute_force_on_loops() {
    for seed in 0..3 {
        check(false, seed);
    }
}

#[test]
fn indexed_equals_brute_force_on_walks() {
    for seed in 10..13 {
        check(true, seed);
    }
}

/// A fork's memory: the history cut into layers at random points (each a
/// `FrameMemory` of its own, as forks freeze them), read as one `Stack`.
/// Every policy plans exactly what brute force over all the frames plans,
/// warm and cold, and the stack lists its frames as one memory would.
fn check_stack(walk: bool, seed: u64) {
    let (poses, frames, mut rng) = workload(walk, seed);
    let mut layers: Vec<FrameMemory> = vec![FrameMemory::new()];
    let mut whole = FrameMemory::new();
    let policies = policies();
    let mut previous: Vec<Option<ContextPlan>> = vec![None; policies.len()];
    for (t, frame) in frames.iter().enumerate() {
        // A fork point about every 30 frames, one of them right at the start.
        if t > 0 && (t == 1 || rng.next_f64() < 1.0 / 30.0) {
            layers.push(FrameMemory::new());
        }
        layers.last_mut().unwrap().insert(frame.clone()).unwrap();
        whole.insert(frame.clone()).unwrap();
        if t % 13 != 0 && t != frames.len() - 1 {
            continue;
        }
        let stack = Stack::new(layers.iter().collect());
        assert_eq!(stack.len(), t + 1);
        let order = |it: &mut dyn Iterator<Item = &MemoryFrame>| it.map(|f| f.id).collect::<Vec<_>>();
        assert_eq!(order(&mut stack.newest_first()), order(&mut whole.newest_first()));
        assert_eq!(stack.get(frame.id).map(|f| f.time), Some(frame.time));
        let (p, y, pi) = if t + 1 < poses.len() { poses[t + 1] } else { poses[0] };
        let target = frustum(p, y, pi);
        for (i, policy) in policies.iter().enumerate() {
            let want = select_by_brute_force(policy, &target, &frames[..=t]);
            let (got, _) = stack.select(policy, &target, previous[i].as_ref());
            assert_eq!(got, want, "{:?} keep_last={} at t={t} over {} layers (walk={walk})", policy.kind, policy.keep_last, layers.len());
            assert_eq!(stack.select(policy, &target, None).0, want, "cold");
            previous[i] = Some(got);
        }
    }
    assert!(layers.len() >= 3, "the history was cut into {} layers", layers.len());
}

#[test]
fn a_stack_of_layers_selects_as_one_memory() {
    for seed in [0, 1] {
        check_stack(false, seed);
    }
    check_stack(true, 10);
}

#[test]
fn frames_out_of_time_order_and_duplicate_ids() {
    let mut memory = FrameMemory::new();
    let f = |time| MemoryFrame { id: time * 10, time, frustum: frustum(DVec3::new(time as f64, 64.0, 0.0), 0.0, 0.0) };
    for time in [5, 1, 9, 3] {
        memory.insert(f(time)).unwrap();
    }
    let err = memory.insert(f(9)).unwrap_err();
    assert_eq!(err.field(), "id");
    assert_eq!(memory.len(), 4, "a refused insert stores nothing");
    let (plan, _) = memory.select(&Policy::preset(PolicyKind::Baseline), &frustum(DVec3::ZERO, 0.0, 0.0), None);
    let ids: Vec<u64> = plan.selected().map(|(_, f)| f.id).collect();
    assert_eq!(ids, vec![90, 50, 30, 10]);
}

#[test]
fn a_long_walk_touches_only_nearby_frames() {
    // 2,000 frames along a straight 2 km line; the target is at the end.
    let mut memory = FrameMemory::new();
    for t in 0..2000u64 {
        let fr = frustum(DVec3::new(0.0, 64.0, t as f64), 0.0, 0.0);
        memory.insert(MemoryFrame { id: t, time: t, frustum: fr }).unwrap();
    }
    let target = frustum(DVec3::new(0.0, 64.0, 2000.0), 0.0, 0.0);
    let (plan, stats) = memory.select(&Policy::preset(PolicyKind::WorldPack), &target, None);
    assert!(stats.box_candidates < 100, "{stats:?}");
    assert!(stats.overlap_evaluations <= stats.box_candidates);
    let brute = select_by_brute_force(&Policy::preset(PolicyKind::WorldPack), &target, memory.frames());
    assert_eq!(plan, brute);
}

#[test]
fn pose_space_bounds_prune_a_dense_loop() {
    // 3,000 frames pacing a 50-block square: every box meets the target's,
    // so only the group bounds can skip frames.
    let mut rng = SplitMix64::new(77);
    let poses = trajectory(&mut rng, 3001, false);
    let mut memory = FrameMemory::new();
    for (t, &(p, y, pi)) in poses[..3000].iter().enumerate() {
        memory.insert(MemoryFrame { id: t as u64, time: t as u64, frustum: frustum(p, y, pi) }).unwrap();
    }
    let (p, y, pi) = poses[3000];
    let target = frustum(p, y, pi);
    let policy = Policy::preset(PolicyKind::WorldPack);
    let (plan, stats) = memory.select(&policy, &target, None);
    assert_eq!(plan, select_by_brute_force(&policy, &target, memory.frames()));
    assert!(stats.box_candidates > 1000, "{stats:?}");
    // Measured: 1,165 of 2,084 candidates evaluated, 293 group bounds. The
    // recency bound alone evaluates all of them on loops.
    assert!(stats.group_bounds > 0 && stats.overlap_evaluations * 4 < stats.box_candidates * 3, "{stats:?}");
    // Most evaluations stop part-way, once clipping proves the frame cannot enter.
    assert!(stats.cut_short * 2 > stats.overlap_evaluations, "{stats:?}");
}
