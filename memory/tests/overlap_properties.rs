//! Property tests of the overlap estimators over many random pose pairs.

use glam::{DMat3, DVec3, EulerRot};
use memory::overlap::{MonteCarlo, ViewSamples, WorldMemBall, exact_overlap, overlap_unless_below};
use memory::rng::SplitMix64;
use memory::{Estimator, Frustum, Intrinsics, Pose};

fn random_frustum(rng: &mut SplitMix64, spread: f64) -> Frustum {
    let yaw = rng.next_f64() * std::f64::consts::TAU;
    let pitch = (rng.next_f64() - 0.5) * 1.4;
    let roll = if rng.next_f64() < 0.2 { (rng.next_f64() - 0.5) * 0.6 } else { 0.0 };
    let position = DVec3::new(rng.next_f64(), rng.next_f64() * 0.3, rng.next_f64()) * spread;
    let k = Intrinsics::from_fov(60.0 + 50.0 * rng.next_f64(), None, 64, 48).unwrap().with_range(0.1, 30.0).unwrap();
    Frustum::new(Pose::new(DMat3::from_euler(EulerRot::YXZ, yaw, pitch, roll), position).unwrap(), k).unwrap()
}

#[test]
fn monte_carlo_lies_within_four_sigma_of_exact() {
    let mut rng = SplitMix64::new(2024);
    let mc = MonteCarlo { samples: 10_000, seed: 11 };
    let mut nontrivial = 0;
    for pair in 0..300 {
        let q = random_frustum(&mut rng, 40.0);
        let c = random_frustum(&mut rng, 40.0);
        let exact = exact_overlap(&q, &c);
        let est = ViewSamples::monte_carlo(&q, &MonteCarlo { seed: pair, ..mc }).overlap(&c);
        let n = mc.samples as f64;
        let sigma = (exact * (1.0 - exact) / n).sqrt();
        assert!((est - exact).abs() <= 4.0 * sigma + 1.0 / n, "pair {pair}: exact {exact}, MC {est}, σ {sigma}");
        nontrivial += (exact > 0.01 && exact < 0.99) as usize;
    }
    // The property means little unless many pairs partly overlap.
    assert!(nontrivial > 60, "only {nontrivial} pairs partly overlap");
}

#[test]
fn every_estimator_gives_one_for_a_frustum_against_itself() {
    let mut rng = SplitMix64::new(5);
    for _ in 0..50 {
        let f = random_frustum(&mut rng, 1e4);
        assert_eq!(exact_overlap(&f, &f), 1.0);
        let mc = Estimator::MonteCarlo(MonteCarlo::default()).overlaps(&f, [&f])[0];
        assert!(mc >= 0.9999, "{mc}");
        let wm = Estimator::WorldMem(WorldMemBall::default()).overlaps(&f, [&f])[0];
        assert_eq!(wm, 1.0);
    }
}

#[test]
fn disjoint_frusta_give_exactly_zero() {
    let mut rng = SplitMix64::new(9);
    for _ in 0..100 {
        let a = random_frustum(&mut rng, 40.0);
        let mut b = random_frustum(&mut rng, 40.0);
        // Move b beyond the reach of a's far plane (30) plus its own.
        let shifted = Pose::new(b.pose().rotation(), b.pose().position() + DVec3::new(200.0, 0.0, 0.0)).unwrap();
        b = Frustum::new(shifted, *b.intrinsics()).unwrap();
        assert_eq!(exact_overlap(&a, &b), 0.0);
        assert!(!a.intersects(&b));
        assert_eq!(Estimator::MonteCarlo(MonteCarlo::default()).overlaps(&a, [&b])[0], 0.0);
    }
}

#[test]
fn exact_overlap_is_consistent_both_ways_and_with_gjk() {
    let mut rng = SplitMix64::new(77);
    for pair in 0..400 {
        let a = random_frustum(&mut rng, 40.0);
        let b = random_frustum(&mut rng, 40.0);
        let (ab, ba) = (exact_overlap(&a, &b), exact_overlap(&b, &a));
        assert!((0.0..=1.0).contains(&ab) && (0.0..=1.0).contains(&ba));
        // Both ratios measure the same intersection volume.
        let (va, vb) = (ab * a.volume(), ba * b.volume());
        assert!((va - vb).abs() <= 1e-9 * a.volume().max(b.volume()), "pair {pair}: {va} vs {vb}");
        // GJK finding no contact proves a zero overlap; a positive overlap needs contact.
        if !a.intersects(&b) {
            assert_eq!(ab, 0.0, "pair {pair}");
        }
        if ab > 1e-6 {
            assert!(a.intersects(&b), "pair {pair}");
        }
    }
}

#[test]
fn monte_carlo_is_reproducible_for_a_seed() {
    let mut rng = SplitMix64::new(3);
    let (a, b) = (random_frustum(&mut rng, 10.0), random_frustum(&mut rng, 10.0));
    let est = |seed| Estimator::MonteCarlo(MonteCarlo { samples: 2000, seed }).overlaps(&a, [&b])[0];
    assert_eq!(est(1), est(1));
}

#[test]
fn worldmem_quirk_changes_only_pitched_views() {
    let k = Intrinsics::from_fov(90.0, None, 64, 64).unwrap();
    let level = Frustum::new(Pose::from_position(DVec3::ZERO), k).unwrap();
    let quirk = Estimator::WorldMem(WorldMemBall { pitch_sign_quirk: true, ..Default::default() });
    let plain = Estimator::WorldMem(WorldMemBall::default());
    let pitched = Frustum::new(Pose::new(DMat3::from_rotation_x(-0.5), DVec3::ZERO).unwrap(), k).unwrap();
    assert_eq!(quirk.overlaps(&level, [&level]), plain.overlaps(&level, [&level]));
    assert!(quirk.overlaps(&level, [&pitched])[0] != plain.overlaps(&level, [&pitched])[0]);
}

#[test]
fn a_floor_only_decides_whether_the_exact_overlap_is_returned() {
    let mut rng = SplitMix64::new(31);
    let (mut returned, mut ruled_out) = (0, 0);
    for pair in 0..400 {
        let q = random_frustum(&mut rng, 25.0);
        let c = random_frustum(&mut rng, 25.0);
        let exact = exact_overlap(&q, &c);
        // A floor just under the exact overlap must let it through: any bound
        // that undercuts the true volume (a clip's or the closed form's) fails here.
        let at_floor = overlap_unless_below(&q, &c, exact - 1e-10).map(f64::to_bits);
        assert_eq!(at_floor, Some(exact.to_bits()), "pair {pair}: ruled out just under its own overlap {exact}");
        let floor = rng.next_f64();
        match overlap_unless_below(&q, &c, floor) {
            Some(o) => {
                assert_eq!(o.to_bits(), exact.to_bits(), "pair {pair}: the same number as exact_overlap");
                assert!(exact >= floor - 1e-9, "pair {pair}: {exact} below the floor {floor} came back");
                returned += 1;
            }
            None => {
                assert!(exact < floor, "pair {pair}: {exact} ruled out by the floor {floor}");
                ruled_out += 1;
            }
        }
    }
    assert!(returned > 20 && ruled_out > 20, "{returned} returned, {ruled_out} ruled out");
}
