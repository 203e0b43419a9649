//! How much a score can move when a pose moves: a Lipschitz bound on the
//! overlap `o = Vol(V_i ∩ V_t) / Vol(V_t)` (paper Eq. 6).
//!
//! Derivation (every frustum here has the same intrinsics, so the same
//! volume `V` and surface area `S`):
//!
//! 1. Move a frustum `F` rigidly to `F' = g(F)`, where `g` takes camera
//!    centre `c` to `c'` and turns by an angle `θ`. A point `x` at distance
//!    `r` from `c` moves by at most `|c' − c| + θ r` (the chord `2 sin(θ/2) r`
//!    is at most `θ r`). For the inverse map and points of `F'` the same
//!    holds with `r ≤ ρ + |c' − c|`, where `ρ` is the largest distance from
//!    the camera centre to a corner. So every point of `F ∪ F'` is moved by
//!    `g` or `g⁻¹` by at most `d = |c' − c| (1 + θ) + θ ρ`.
//! 2. A point of `F` at least `d` inside its boundary is mapped by `g⁻¹` to a
//!    point still in `F`, so it lies in `F'`. Hence `F \ F'` lies in the inner
//!    shell of `F` of width `d`, whose volume is at most `d S` for a convex
//!    body (the inner parallel bodies are convex and no larger). The same
//!    holds for `F' \ F`, so `Vol(F Δ F') ≤ 2 d S`.
//! 3. `|Vol(A ∩ F') − Vol(A ∩ F)| ≤ Vol(F Δ F')` for any `A`, and rigid motion
//!    keeps `V`. Moving the target by `d_t` and the candidate by `d_i` thus
//!    changes the overlap by at most `2 S (d_t + d_i) / V`, and a
//!    score `w_o o − w_t Δt` by `w_o` times that (the age does not move).
//!
//! `tests/lipschitz.rs` checks the bound on random frusta and perturbations.

use crate::{Frustum, Pose};

/// Surface area of the truncated pyramid (six planar quadrilaterals).
pub fn surface_area(f: &Frustum) -> f64 {
    let c = f.corners();
    crate::frustum::FACES
        .iter()
        .map(|&[a, b, d, e]| {
            // A planar quadrilateral's area is half the cross product of its diagonals.
            0.5 * (c[d] - c[a]).cross(c[e] - c[b]).length()
        })
        .sum()
}

/// Largest distance from the camera centre to a point of the frustum (a far corner).
pub fn reach(f: &Frustum) -> f64 {
    let centre = f.pose().position();
    f.corners().iter().map(|p| p.distance(centre)).fold(0.0, f64::max)
}

/// The rotation angle (radians) taking `from`'s orientation to `to`'s.
pub fn rotation_angle(from: &Pose, to: &Pose) -> f64 {
    let r = to.rotation() * from.rotation().transpose();
    // trace = 1 + 2 cos θ; clamp against rounding.
    (((r.x_axis.x + r.y_axis.y + r.z_axis.z) - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// `d` of step 1: no point of the frustum (or of its image) moves farther
/// than this when the camera goes from `from` to `to`.
pub fn displacement_bound(from: &Pose, to: &Pose, reach: f64) -> f64 {
    let shift = from.position().distance(to.position());
    let theta = rotation_angle(from, to);
    shift * (1.0 + theta) + theta * reach
}

/// The largest change of the overlap of candidate `i` with target `t` when
/// the target camera moves by `d_target` and the candidate by `d_candidate`
/// (each from [`displacement_bound`]); `frustum` gives the shared shape.
pub fn overlap_change_bound(frustum: &Frustum, d_target: f64, d_candidate: f64) -> f64 {
    (2.0 * surface_area(frustum) * (d_target + d_candidate) / frustum.volume()).min(1.0)
}
