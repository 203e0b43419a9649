//! The overlap is Lipschitz in the poses, with the constant derived in
//! `memory::stability`: a small pose change can only move a score a little.

use glam::{DMat3, DVec3, EulerRot};
use memory::overlap::exact_overlap;
use memory::rng::SplitMix64;
use memory::stability::{displacement_bound, overlap_change_bound, reach, rotation_angle, surface_area};
use memory::{Frustum, Intrinsics, Pose};

fn intrinsics() -> Intrinsics {
    Intrinsics::from_fov(70.0, None, 64, 64).unwrap().with_range(0.1, 30.0).unwrap()
}

fn pose(yaw: f64, pitch: f64, position: DVec3) -> Pose {
    Pose::new(DMat3::from_euler(EulerRot::YXZ, yaw, pitch, 0.0), position).unwrap()
}

/// `p` moved by up to `shift` blocks and turned by up to `turn` radians about a random axis.
fn perturbed(rng: &mut SplitMix64, p: &Pose, shift: f64, turn: f64) -> Pose {
    let mut unit = || DVec3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, rng.next_f64() - 0.5).normalize();
    let (axis, direction) = (unit(), unit());
    let dr = DMat3::from_axis_angle(axis, turn * rng.next_f64());
    Pose::new(dr * p.rotation(), p.position() + direction * shift * rng.next_f64()).unwrap()
}

#[test]
fn surface_area_matches_the_closed_form_of_a_square_pyramid() {
    // 90° square view: side slopes ±1, so the faces are squares 2z wide and
    // four trapezoids of slant height (far − near)·√2.
    let k = Intrinsics::from_fov(90.0, Some(90.0), 64, 64).unwrap().with_range(0.5, 10.0).unwrap();
    let f = Frustum::new(pose(0.3, 0.1, DVec3::new(3.0, 1.0, -2.0)), k).unwrap();
    let (n, far) = (0.5f64, 10.0f64);
    let expected = 4.0 * n * n + 4.0 * far * far + 4.0 * 2f64.sqrt() * (far * far - n * n);
    assert!((surface_area(&f) - expected).abs() < 1e-9 * expected, "{} vs {expected}", surface_area(&f));
    assert!((reach(&f) - (far * far * 3.0).sqrt()).abs() < 1e-9);
}

#[test]
fn rotation_angle_reads_back_a_known_turn() {
    let a = pose(0.2, 0.0, DVec3::ZERO);
    let b = pose(0.2 + 0.05, 0.0, DVec3::ZERO);
    assert!((rotation_angle(&a, &b) - 0.05).abs() < 1e-9);
    assert_eq!(rotation_angle(&a, &a), 0.0);
}

#[test]
fn a_small_pose_change_moves_the_overlap_no_more_than_the_bound() {
    let k = intrinsics();
    let mut rng = SplitMix64::new(77);
    let (mut checked, mut worst_ratio) = (0, 0.0f64);
    for case in 0..400 {
        // Pairs close enough to overlap partly, as on a loop's return leg.
        let t = pose(rng.next_f64() * 6.3, (rng.next_f64() - 0.5) * 0.4, DVec3::ZERO);
        let i = pose(
            t.rotation().to_euler(EulerRot::YXZ).0 + (rng.next_f64() - 0.5) * 1.5,
            (rng.next_f64() - 0.5) * 0.4,
            DVec3::new(rng.next_f64() - 0.5, 0.0, rng.next_f64() - 0.5) * 20.0,
        );
        let (ft, fi) = (Frustum::new(t, k).unwrap(), Frustum::new(i, k).unwrap());
        let before = exact_overlap(&ft, &fi);
        // Small noise: up to half a block and 3°, on the target, the candidate or both.
        let (shift, turn) = (0.5 * rng.next_f64(), 3f64.to_radians() * rng.next_f64());
        let t2 = if case % 3 != 1 { perturbed(&mut rng, &t, shift, turn) } else { t };
        let i2 = if case % 3 != 0 { perturbed(&mut rng, &i, shift, turn) } else { i };
        let after = exact_overlap(&Frustum::new(t2, k).unwrap(), &Frustum::new(i2, k).unwrap());
        let r = reach(&ft);
        let bound = overlap_change_bound(&ft, displacement_bound(&t, &t2, r), displacement_bound(&i, &i2, r));
        let change = (after - before).abs();
        assert!(change <= bound + 1e-9, "case {case}: overlap {before} → {after}, change {change} > bound {bound}");
        if before > 0.05 && bound < 1.0 {
            checked += 1;
            worst_ratio = worst_ratio.max(change / bound);
        }
    }
    // The check means something only if many pairs overlap and the bound is not trivially 1.
    assert!(checked > 100, "only {checked} informative cases");
    eprintln!("largest change / bound: {worst_ratio:.3} over {checked} cases");
}

#[test]
fn the_bound_shrinks_linearly_with_the_motion() {
    let k = intrinsics();
    let f = Frustum::new(pose(0.0, 0.0, DVec3::ZERO), k).unwrap();
    let moved = |s: f64| pose(0.0, 0.0, DVec3::new(s, 0.0, 0.0));
    let b1 = overlap_change_bound(&f, displacement_bound(f.pose(), &moved(0.01), reach(&f)), 0.0);
    let b2 = overlap_change_bound(&f, displacement_bound(f.pose(), &moved(0.02), reach(&f)), 0.0);
    assert!((b2 / b1 - 2.0).abs() < 1e-9);
    // A sideways step of 0.01 block moves the overlap by at most a few hundredths for this view.
    assert!(b1 < 0.01, "bound {b1}");
    let real = 1.0 - exact_overlap(&f, &Frustum::new(moved(0.01), k).unwrap());
    assert!(real <= b1 && real > 0.0);
}
