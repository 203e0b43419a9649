//! Exact `Vol(V_i ∩ V_t) / Vol(V_t)` by clipping one convex polyhedron with
//! the other's planes, in f64.
//!
//! parry has no convex–convex intersection volume, so the query frustum is
//! kept as a list of polygonal faces and clipped plane by plane
//! (Sutherland–Hodgman on each face, plus a cap polygon on the cut). Points
//! within a scale-relative tolerance of a plane count as *on* it; that makes
//! identical, coplanar and touching frusta come out exactly 1 or 0 rather
//! than off by rounding.

use glam::DVec3;

use crate::frustum::{FACES, Frustum, Plane};

/// Relative tolerance for "on the plane".
const ON_PLANE: f64 = 1e-10;

/// A convex polytope as a list of faces, each a convex polygon in cyclic order.
#[derive(Clone, Debug, Default)]
pub struct Polytope {
    faces: Vec<Vec<DVec3>>,
}

impl Polytope {
    pub fn from_frustum(f: &Frustum) -> Polytope {
        let c = f.corners();
        Polytope { faces: FACES.iter().map(|face| face.iter().map(|&i| c[i]).collect()).collect() }
    }

    pub fn is_empty(&self) -> bool {
        self.faces.is_empty()
    }

    /// Keeps the part with `plane.distance(p) <= 0`.
    pub fn clip(&mut self, plane: &Plane, eps: f64) {
        // Most planes cut nothing: leave without allocating.
        if self.faces.iter().flatten().all(|&p| plane.distance(p) <= eps) {
            return;
        }
        let mut cut_points: Vec<DVec3> = Vec::new();
        let mut face_on_plane = false;
        let mut clipped_faces = Vec::with_capacity(self.faces.len() + 1);
        let mut d: Vec<f64> = Vec::new();
        for face in std::mem::take(&mut self.faces) {
            d.clear();
            d.extend(face.iter().map(|&p| plane.distance(p)));
            if d.iter().all(|&x| x <= eps) {
                if d.iter().all(|&x| x.abs() <= eps) {
                    face_on_plane = true;
                }
                cut_points.extend(face.iter().zip(&d).filter(|(_, x)| x.abs() <= eps).map(|(p, _)| *p));
                clipped_faces.push(face);
                continue;
            }
            let mut out = Vec::with_capacity(face.len() + 1);
            for i in 0..face.len() {
                let j = (i + 1) % face.len();
                let (p, q, dp, dq) = (face[i], face[j], d[i], d[j]);
                if dp <= eps {
                    out.push(p);
                    if dp.abs() <= eps {
                        cut_points.push(p);
                    }
                }
                // A strict crossing: one end clearly inside, the other clearly outside.
                if (dp < -eps && dq > eps) || (dp > eps && dq < -eps) {
                    let x = p + (q - p) * (dp / (dp - dq));
                    out.push(x);
                    cut_points.push(x);
                }
            }
            if out.len() >= 3 {
                clipped_faces.push(out);
            }
        }
        if !face_on_plane {
            if let Some(cap) = cap_polygon(cut_points, plane.normal, eps) {
                clipped_faces.push(cap);
            }
        }
        self.faces = if clipped_faces.len() >= 4 { clipped_faces } else { Vec::new() };
    }

    /// Volume by summing pyramids from an interior point to every face.
    pub fn volume(&self) -> f64 {
        let n: usize = self.faces.iter().map(Vec::len).sum();
        if n == 0 {
            return 0.0;
        }
        let reference = self.faces.iter().flatten().sum::<DVec3>() / n as f64;
        let mut volume = 0.0;
        for face in &self.faces {
            let p0 = face[0];
            let mut area2 = DVec3::ZERO;
            for w in face.windows(2).skip(1) {
                area2 += (w[0] - p0).cross(w[1] - p0);
            }
            let len = area2.length();
            if len > 0.0 {
                volume += len * (area2 / len).dot(p0 - reference).abs() / 6.0;
            }
        }
        volume
    }
}

/// Orders the points on a cutting plane into a convex polygon, or `None` if
/// fewer than three distinct points remain.
fn cap_polygon(mut points: Vec<DVec3>, normal: DVec3, eps: f64) -> Option<Vec<DVec3>> {
    let mut unique: Vec<DVec3> = Vec::with_capacity(points.len());
    for p in points.drain(..) {
        if unique.iter().all(|q| (*q - p).length() > eps) {
            unique.push(p);
        }
    }
    if unique.len() < 3 {
        return None;
    }
    let centre = unique.iter().sum::<DVec3>() / unique.len() as f64;
    let u = normal.any_orthonormal_vector();
    let v = normal.cross(u);
    let mut keyed: Vec<(f64, DVec3)> = unique
        .into_iter()
        .map(|p| {
            let r = p - centre;
            (pseudo_angle(r.dot(u), r.dot(v)), p)
        })
        .collect();
    keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
    Some(keyed.into_iter().map(|(_, p)| p).collect())
}

/// A number in [0, 4) that grows with the angle of `(x, y)` from the x axis,
/// as `atan2` does, without trigonometry (ordering is all the cap needs).
fn pseudo_angle(x: f64, y: f64) -> f64 {
    let r = x.abs() + y.abs();
    if r == 0.0 {
        return 0.0;
    }
    let (x, y) = (x / r, y / r);
    match (x >= 0.0, y >= 0.0) {
        (true, true) => y,
        (false, true) => 1.0 - x,
        (false, false) => 2.0 - y,
        (true, false) => 3.0 + x,
    }
}

/// `Vol(candidate ∩ query) / Vol(query)`, exactly (up to f64 rounding).
pub fn exact_overlap(query: &Frustum, candidate: &Frustum) -> f64 {
    if !query.aabb().intersects(candidate.aabb()) {
        return 0.0;
    }
    let eps = ON_PLANE * query.scale().max(candidate.scale());
    if query.corners().iter().all(|&c| candidate.contains(c, eps)) {
        return 1.0;
    }
    let mut poly = Polytope::from_frustum(query);
    for plane in candidate.planes() {
        poly.clip(plane, eps);
        if poly.is_empty() {
            return 0.0;
        }
    }
    (poly.volume() / query.volume()).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::pose::Pose;
    use glam::DMat3;

    fn intrinsics(near: f64, far: f64) -> Intrinsics {
        Intrinsics::from_fov(90.0, Some(60.0), 64, 48).unwrap().with_range(near, far).unwrap()
    }

    fn at(rotation: DMat3, position: DVec3, near: f64, far: f64) -> Frustum {
        Frustum::new(Pose::new(rotation, position).unwrap(), intrinsics(near, far)).unwrap()
    }

    #[test]
    fn a_frustum_overlaps_itself_fully() {
        for (i, rot) in [DMat3::IDENTITY, DMat3::from_rotation_y(1.234), DMat3::from_euler(glam::EulerRot::YXZ, 2.0, 0.4, 0.0)]
            .into_iter()
            .enumerate()
        {
            let f = at(rot, DVec3::new(1e4 * i as f64, 64.0, -3.0), 0.1, 30.0);
            assert_eq!(exact_overlap(&f, &f), 1.0);
            assert!((Polytope::from_frustum(&f).volume() - f.volume()).abs() / f.volume() < 1e-12);
        }
    }

    #[test]
    fn nested_frusta_give_the_volume_ratio() {
        let inner = at(DMat3::IDENTITY, DVec3::ZERO, 0.1, 10.0);
        let outer = at(DMat3::IDENTITY, DVec3::ZERO, 0.1, 30.0);
        assert_eq!(exact_overlap(&inner, &outer), 1.0);
        let expected = inner.volume() / outer.volume();
        assert!((exact_overlap(&outer, &inner) - expected).abs() < 1e-12);
    }

    #[test]
    fn disjoint_and_touching_frusta_give_exactly_zero() {
        let a = at(DMat3::IDENTITY, DVec3::ZERO, 0.1, 10.0);
        let far_away = at(DMat3::IDENTITY, DVec3::new(500.0, 0.0, 0.0), 0.1, 10.0);
        assert_eq!(exact_overlap(&a, &far_away), 0.0);
        // Same camera, ranges [0.1, 10] and [10, 20]: they share the plane z = 10.
        let b = at(DMat3::IDENTITY, DVec3::ZERO, 10.0, 20.0);
        assert_eq!(exact_overlap(&a, &b), 0.0);
        assert_eq!(exact_overlap(&b, &a), 0.0);
        // Looking in opposite directions from the same point share only the apex region.
        let back = at(DMat3::from_rotation_y(std::f64::consts::PI), DVec3::ZERO, 0.1, 10.0);
        assert_eq!(exact_overlap(&a, &back), 0.0);
    }

    #[test]
    fn coplanar_side_faces_split_the_volume() {
        // A 90° horizontal FoV turned by exactly 45° shares a side plane with the original.
        let a = at(DMat3::IDENTITY, DVec3::ZERO, 0.1, 10.0);
        let b = at(DMat3::from_rotation_y(std::f64::consts::FRAC_PI_2), DVec3::ZERO, 0.1, 10.0);
        assert_eq!(exact_overlap(&a, &b), 0.0, "touching along a shared side plane");
        let c = at(DMat3::from_rotation_y(std::f64::consts::FRAC_PI_4), DVec3::ZERO, 0.1, 10.0);
        let o = exact_overlap(&a, &c);
        assert!(o > 0.3 && o < 0.7, "{o}");
    }

    #[test]
    fn shifted_box_like_overlap_matches_closed_form() {
        // Shift a camera sideways along x: at depth z the two image footprints
        // overlap over width (2z − s) (90° hFoV) for z > s/2, so the shared
        // volume is ∫ (2z − s)·(2z·tan 30°) dz over [max(near, s/2), far].
        let (near, far, s) = (0.1, 10.0, 4.0);
        let a = at(DMat3::IDENTITY, DVec3::ZERO, near, far);
        let b = at(DMat3::IDENTITY, DVec3::new(s, 0.0, 0.0), near, far);
        let t = 30f64.to_radians().tan();
        let z0 = f64::max(near, s / 2.0);
        let integral = |z: f64| 2.0 * t * (2.0 * z.powi(3) / 3.0 - s * z * z / 2.0);
        let expected = (integral(far) - integral(z0)) / a.volume();
        let got = exact_overlap(&a, &b);
        assert!((got - expected).abs() < 1e-9, "{got} vs {expected}");
    }
}
