//! Selection under small pose noise keeps most of its set. The thresholds
//! were set from measured runs (printed with `--nocapture`; see
//! docs/results.md, "Stability tests"): each sits well below what was measured,
//! so the test fails on a real regression, not on seed luck.

use eval::noise::{PoseNoise, apply, selection_agreement};
use memory::workload::{Workload, frusta};
use memory::{Frustum, Intrinsics, Policy, PolicyKind, Pose};

fn camera() -> Intrinsics {
    Intrinsics::from_fov(70.0, None, 64, 64).unwrap().with_range(0.1, 30.0).unwrap()
}

/// Mean Jaccard and mean rank agreement of `policy` on a workload under `noise`, over every 5th frame.
fn agreement(workload: Workload, n: usize, policy: &Policy, noise: PoseNoise, seed: u64) -> (f64, f64) {
    let truth = frusta(workload, n, 11, camera());
    let poses: Vec<Pose> = truth.iter().map(|f| *f.pose()).collect();
    let believed: Vec<Frustum> = apply(&poses, noise, seed).into_iter().map(|p| Frustum::new(p, camera()).unwrap()).collect();
    let targets: Vec<usize> = (30..n).step_by(5).collect();
    let a = selection_agreement(policy, &truth, &believed, &targets);
    let jaccard = a.iter().map(|x| x.jaccard).sum::<f64>() / a.len() as f64;
    let ranks: Vec<f64> = a.iter().filter_map(|x| x.rank).collect();
    (jaccard, ranks.iter().sum::<f64>() / ranks.len() as f64)
}

fn small() -> PoseNoise {
    PoseNoise::Independent { translation: 0.1, rotation_deg: 1.0 }
}

#[test]
fn worldpack_keeps_most_of_its_set_under_small_noise() {
    let wp = Policy::preset(PolicyKind::WorldPack);
    // Measured over seeds 1..=8: Loop Jaccard 0.95–0.97, ρ 0.98–0.99; Walk Jaccard 0.98–0.99, ρ 0.99.
    for (workload, min_jaccard, min_rank) in [(Workload::Loop, 0.90, 0.93), (Workload::Walk, 0.93, 0.95)] {
        let (j, r) = agreement(workload, 400, &wp, small(), 3);
        eprintln!("{workload:?}: WorldPack under σ 0.1 block, 1°: Jaccard {j:.3}, rank ρ {r:.3}");
        assert!(j >= min_jaccard && r >= min_rank, "{workload:?}: Jaccard {j:.3} (≥ {min_jaccard}), rank ρ {r:.3} (≥ {min_rank})");
    }
}

#[test]
fn memory_retrieval_keeps_most_of_its_set_under_small_noise() {
    let mr = Policy::preset(PolicyKind::MemoryRetrieval);
    let (j, r) = agreement(Workload::Loop, 400, &mr, small(), 3);
    eprintln!("Loop: MR under σ 0.1 block, 1°: Jaccard {j:.3}, rank ρ {r:.3}");
    // Measured over seeds 1..=8: Jaccard 0.91–0.95, ρ 0.84–0.89. MR picks only 4
    // frames, so one swap among them moves both measures more than among WorldPack's 22.
    assert!(j >= 0.85 && r >= 0.70, "Jaccard {j:.3}, rank ρ {r:.3}");
}

#[test]
fn recency_policies_ignore_the_poses() {
    let big = PoseNoise::Independent { translation: 5.0, rotation_deg: 30.0 };
    for kind in [PolicyKind::Baseline, PolicyKind::NearestFramePacking] {
        let (j, r) = agreement(Workload::Loop, 200, &Policy::preset(kind), big, 1);
        assert_eq!((j, r), (1.0, 1.0), "{kind:?}");
    }
}

#[test]
fn agreement_falls_as_the_noise_grows() {
    let wp = Policy::preset(PolicyKind::WorldPack);
    let levels = [0.05, 0.3, 1.5];
    let j: Vec<f64> = levels
        .iter()
        .map(|&s| agreement(Workload::Loop, 300, &wp, PoseNoise::Independent { translation: s, rotation_deg: 10.0 * s }, 5).0)
        .collect();
    eprintln!("WorldPack Jaccard at σ {levels:?} (blocks; 10× in degrees): {j:?}");
    assert!(j[0] > j[1] && j[1] > j[2], "{j:?}");
    assert!(j[2] < 0.8, "large noise should change the selection: {j:?}");
}

#[test]
#[ignore = "measurement: prints agreement over seeds to set the thresholds above"]
fn measure_over_seeds() {
    for seed in 1..=8 {
        let wp = Policy::preset(PolicyKind::WorldPack);
        let mr = Policy::preset(PolicyKind::MemoryRetrieval);
        let l = agreement(Workload::Loop, 400, &wp, small(), seed);
        let w = agreement(Workload::Walk, 400, &wp, small(), seed);
        let m = agreement(Workload::Loop, 400, &mr, small(), seed);
        eprintln!("seed {seed}: WP loop {l:.3?} walk {w:.3?}; MR loop {m:.3?}");
    }
}
