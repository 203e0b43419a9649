//! The context policies on hand-built trajectories.

use memory::overlap::exact_overlap;
use memory::policy::{PolicySpec, Tier};
use memory::{
    AngleUnit, Frustum, Intrinsics, LatentGrid, MemoryFrame, Packing, Policy, PolicyKind, Pose, Pose5, Pose5Convention, Query,
    select_by_brute_force,
};

const ALL: [PolicyKind; 5] = [
    PolicyKind::Baseline,
    PolicyKind::NearestFramePacking,
    PolicyKind::MemoryRetrieval,
    PolicyKind::WorldPack,
    PolicyKind::WorldMemGreedy,
];

fn view(x: f64, z: f64, yaw_deg: f64) -> Frustum {
    let pose = Pose::from_pose5(
        &Pose5 { x, y: 64.0, z, pitch: 0.0, yaw: yaw_deg },
        Pose5Convention::Minecraft,
        AngleUnit::Degrees,
    )
    .unwrap();
    Frustum::new(pose, Intrinsics::from_fov(90.0, None, 64, 64).unwrap()).unwrap()
}

/// Walk 40 steps south (+z) looking south, turn, and walk back north looking
/// north. A target back at the start facing south sees what the first
/// outbound frames saw.
fn out_and_back() -> Vec<MemoryFrame> {
    let mut frames = Vec::new();
    for t in 0..40u64 {
        frames.push(MemoryFrame { id: t, time: t, frustum: view(0.0, t as f64, 0.0) });
    }
    for t in 40..80u64 {
        frames.push(MemoryFrame { id: t, time: t, frustum: view(0.0, (79 - t) as f64, 180.0) });
    }
    frames
}

/// A preset scoring against the frame to generate instead of the current view.
fn looking_ahead(kind: PolicyKind) -> Policy {
    Policy { query: Query::Target, ..Policy::preset(kind) }
}

fn ids(plan: &memory::ContextPlan) -> Vec<u64> {
    plan.selected().map(|(_, f)| f.id).collect()
}

fn rates(plan: &memory::ContextPlan) -> Vec<u32> {
    plan.slots.iter().map(|s| s.rate).collect()
}

#[test]
fn empty_memory_gives_an_empty_plan_for_every_policy() {
    for kind in ALL {
        let plan = select_by_brute_force(&Policy::preset(kind), &view(0.0, 0.0, 0.0), &[]);
        assert!(plan.is_empty(), "{kind:?}");
        assert_eq!(plan.slots.len(), Policy::preset(kind).packing.slots());
    }
}

#[test]
fn baseline_and_nfp_follow_recency() {
    let frames = out_and_back();
    let target = view(0.0, 0.0, 0.0);
    let baseline = select_by_brute_force(&Policy::preset(PolicyKind::Baseline), &target, &frames);
    assert_eq!(ids(&baseline), vec![79, 78, 77, 76]);
    assert_eq!(rates(&baseline), vec![1; 4]);
    let nfp = select_by_brute_force(&Policy::preset(PolicyKind::NearestFramePacking), &target, &frames);
    assert_eq!(ids(&nfp), (58..80).rev().collect::<Vec<_>>());
    let expected_rates: Vec<u32> = [vec![1; 2], vec![4; 4], vec![16; 16]].concat();
    assert_eq!(rates(&nfp), expected_rates);
}

#[test]
fn retrieval_policies_bring_back_the_frames_that_saw_the_target_view() {
    let frames = out_and_back();
    // Back at the start, facing south again: the outbound frames near z = 0 saw this.
    let target = view(0.0, 0.0, 0.0);
    let mr = select_by_brute_force(&looking_ahead(PolicyKind::MemoryRetrieval), &target, &frames);
    assert_eq!(ids(&mr), vec![0, 1, 2, 3], "{mr:?}");
    let wp = select_by_brute_force(&looking_ahead(PolicyKind::WorldPack), &target, &frames);
    assert_eq!(&ids(&wp)[..4], &[0, 1, 2, 3]);
    assert_eq!(wp.slots.len(), 22);
    // The newest frame stands on the target's spot facing the other way: it
    // sees none of the target view and stays out, recent as it is.
    assert!(!ids(&wp).contains(&79));
    assert_eq!(exact_overlap(&target, &frames[79].frustum), 0.0);
    // Scores follow Eq. 7 with the exact overlap.
    for (_, f) in wp.selected() {
        let o = exact_overlap(&target, &frames[f.id as usize].frustum);
        assert!((f.overlap - o).abs() < 1e-12);
        assert!((f.score - (o - 0.2 * (79 - f.time) as f64 / 79.0)).abs() < 1e-12);
    }
    let scores: Vec<f64> = wp.selected().map(|(_, f)| f.score).collect();
    assert!(scores.windows(2).all(|w| w[0] >= w[1]));
}

#[test]
fn algorithm_1_scores_against_the_current_view() {
    // The paper's Algorithm 1: frames 0..t scored against p_t, the newest
    // frame's pose. That frame has overlap 1 and age 0, so it always leads;
    // the rest are the frames that saw the current view.
    let frames = out_and_back();
    let target = view(0.0, 0.0, 0.0);
    for kind in [PolicyKind::MemoryRetrieval, PolicyKind::WorldPack] {
        let policy = Policy::preset(kind);
        assert_eq!(policy.query, Query::Current, "{kind:?}");
        let plan = select_by_brute_force(&policy, &target, &frames);
        let first = plan.selected().next().unwrap().1;
        assert_eq!((first.id, first.overlap, first.score), (79, 1.0, 1.0), "{kind:?}");
        // Next: the way back's frames (facing north as frame 79 does), not the outbound start.
        assert_eq!(&ids(&plan)[1..4], &[78, 77, 76], "{kind:?}");
    }
    // The same query through a spec, and the look-ahead query as an override.
    let spec = |json: &str| serde_json::from_str::<PolicySpec>(json).unwrap().into_policy().unwrap();
    assert_eq!(spec(r#"{"kind": "worldpack"}"#).query, Query::Current);
    assert_eq!(ids(&select_by_brute_force(&spec(r#"{"kind": "worldpack", "query": "target"}"#), &target, &frames))[0], 0);
}

#[test]
fn ties_go_to_the_more_recent_frame_then_the_larger_id() {
    let same = || view(5.0, 5.0, 90.0);
    let frames = vec![
        MemoryFrame { id: 10, time: 3, frustum: same() },
        MemoryFrame { id: 11, time: 7, frustum: same() },
        MemoryFrame { id: 12, time: 7, frustum: same() },
        MemoryFrame { id: 13, time: 1, frustum: same() },
    ];
    let plan = select_by_brute_force(&Policy::preset(PolicyKind::MemoryRetrieval), &same(), &frames);
    assert_eq!(ids(&plan), vec![12, 11, 10, 13]);
}

#[test]
fn keep_last_pins_the_most_recent_frame_first() {
    let frames = out_and_back();
    let target = view(0.0, 0.0, 0.0);
    let mut policy = looking_ahead(PolicyKind::WorldPack);
    policy.keep_last = true;
    let plan = select_by_brute_force(&policy, &target, &frames);
    assert_eq!(ids(&plan)[0], 79);
    assert_eq!(&ids(&plan)[1..4], &[0, 1, 2]);
    assert_eq!(ids(&plan).iter().filter(|&&i| i == 79).count(), 1);
}

#[test]
fn greedy_coverage_prefers_a_new_region_over_a_duplicate() {
    // Two identical frames look west-ish, one looks east-ish; the target sees both sides.
    let frames = vec![
        MemoryFrame { id: 0, time: 0, frustum: view(0.0, 0.0, 45.0) },
        MemoryFrame { id: 1, time: 1, frustum: view(0.0, 0.0, 45.0) },
        MemoryFrame { id: 2, time: 2, frustum: view(0.0, 0.0, -45.0) },
    ];
    let target = view(0.0, 0.0, 0.0);
    let mut greedy = Policy::preset(PolicyKind::WorldMemGreedy);
    greedy.packing = Packing::uncompressed(2);
    let picked = ids(&select_by_brute_force(&greedy, &target, &frames));
    assert!(picked.contains(&2) && picked.len() == 2, "{picked:?}");
    // Plain score ranking over the same views happily takes a duplicate; make
    // the duplicates clearly better-scoring by tilting the target toward them.
    let mut by_score = looking_ahead(PolicyKind::MemoryRetrieval);
    by_score.packing = Packing::uncompressed(2);
    let tilted = view(0.0, 0.0, 30.0);
    assert_eq!(ids(&select_by_brute_force(&by_score, &tilted, &frames)), vec![1, 0]);
    assert!(ids(&select_by_brute_force(&greedy, &tilted, &frames)).contains(&2));
}

#[test]
fn scores_stay_finite_when_every_frame_is_from_time_zero() {
    let frames = vec![MemoryFrame { id: 7, time: 0, frustum: view(0.0, 0.0, 0.0) }];
    for kind in ALL {
        let plan = select_by_brute_force(&Policy::preset(kind), &view(0.0, 0.0, 0.0), &frames);
        let (_, f) = plan.selected().next().unwrap();
        assert!(f.score.is_finite() && f.overlap.is_finite(), "{kind:?}: {f:?}");
    }
}

#[test]
fn packed_context_costs_as_many_tokens_as_the_baseline_when_sizes_divide() {
    let frames = out_and_back();
    let target = view(0.0, 0.0, 0.0);
    let full = |kind| select_by_brute_force(&Policy::preset(kind), &target, &frames);
    // 32×32 latent, patch 2: every kernel divides, so 2·256 + 4·64 + 16·16 = 4·256.
    let even = LatentGrid { height: 32, width: 32, patch: 2 };
    assert_eq!(full(PolicyKind::WorldPack).tokens(&even), (1024, 1024));
    assert_eq!(full(PolicyKind::Baseline).tokens(&even), (1024, 1024));
    // SD-VAE 28×28 latent: rate 16 pads to 32, so 844 tokens, not 784 (DESIGN §4).
    let sd = LatentGrid { height: 28, width: 28, patch: 2 };
    assert_eq!(full(PolicyKind::WorldPack).tokens(&sd), (844, 844));
    assert_eq!(full(PolicyKind::Baseline).tokens(&sd), (784, 784));
    // A half-filled plan reports what it uses and what the tensor holds.
    let plan = select_by_brute_force(&Policy::preset(PolicyKind::WorldPack), &target, &frames[..3]);
    assert_eq!(plan.tokens(&sd), (2 * 196 + 49, 844));
    // Huge shapes count in 64 bits instead of overflowing.
    let huge = LatentGrid { height: u32::MAX, width: u32::MAX, patch: u32::MAX };
    assert_eq!(huge.tokens_at_rate(16), 1);
}

#[test]
fn policy_specs_validate_their_overrides() {
    let spec = |json: &str| serde_json::from_str::<PolicySpec>(json).unwrap().into_policy();
    let p = spec(r#"{"kind": "worldpack", "keep_last": true, "tiers": [{"slots": 1, "rate": 1}, {"slots": 8, "rate": 4}]}"#)
        .unwrap();
    assert!(p.keep_last);
    assert_eq!(p.packing.tiers(), &[Tier { slots: 1, rate: 1 }, Tier { slots: 8, rate: 4 }]);
    let err = spec(r#"{"kind": "worldpack", "tiers": [{"slots": 2, "rate": 8}]}"#).unwrap_err();
    assert_eq!(err.field(), "tiers[0].rate");
    let err = spec(r#"{"kind": "worldpack", "tiers": [{"slots": 0, "rate": 1}]}"#).unwrap_err();
    assert_eq!(err.field(), "tiers");
    let err = spec(r#"{"kind": "baseline", "weights": {"overlap": 1.0, "recency": -1}}"#).unwrap_err();
    assert_eq!(err.field(), "weights.recency");
    let err = spec(r#"{"kind": "worldpack", "estimator": {"kind": "monte_carlo", "samples": 0, "seed": 1}}"#).unwrap_err();
    assert_eq!(err.field(), "estimator.samples");
    let err = spec(r#"{"kind": "worldpack", "tiers": [{"slots": 2, "rate": 4294967295}]}"#).unwrap_err();
    assert_eq!(err.field(), "tiers[0].rate");
    assert!(serde_json::from_str::<PolicySpec>(r#"{"kind": "bogus"}"#).is_err());
    assert_eq!(Packing::geometric(2, &[(2, 0), (4, 2), (16, 4)]).unwrap(), Packing::worldpack());
}

#[test]
fn each_estimator_can_drive_worldpack() {
    let frames = out_and_back();
    let target = view(0.0, 0.0, 0.0);
    let first_pick = |estimator: &str| {
        let json = format!(r#"{{"kind": "worldpack", "query": "target", "estimator": {estimator}}}"#);
        let policy = serde_json::from_str::<PolicySpec>(&json).unwrap().into_policy().unwrap();
        ids(&select_by_brute_force(&policy, &target, &frames))[0]
    };
    // Frustum estimators rank the frame taken at the target's exact pose first.
    assert_eq!(first_pick(r#"{"kind": "exact"}"#), 0);
    assert_eq!(first_pick(r#"{"kind": "monte_carlo", "samples": 4000, "seed": 3}"#), 0);
    // WorldMem's test has no range limit on the candidate: frame 40, 39 blocks
    // away and looking back at the target's region, "sees" nearly every point
    // of the ball and, being more recent, outranks the frame at the target pose.
    let wm = r#"{"kind": "worldmem", "samples": 4000, "radius": 30, "hfov_deg": 105, "vfov_deg": 75, "seed": 3}"#;
    assert_eq!(first_pick(wm), 40);
}

#[test]
fn frames_far_beyond_the_frustum_score_zero_overlap() {
    let mut frames = out_and_back();
    frames.push(MemoryFrame { id: 999, time: 80, frustum: view(5000.0, 0.0, 0.0) });
    let plan = select_by_brute_force(&Policy::preset(PolicyKind::Baseline), &view(0.0, 0.0, 0.0), &frames);
    let first = plan.selected().next().unwrap().1;
    assert_eq!((first.id, first.overlap), (999, 0.0));
}
