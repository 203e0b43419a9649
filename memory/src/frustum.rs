//! Truncated view frusta: the region of space a camera sees between its near
//! and far planes.
//!
//! Geometry that decides scores (corners, planes, volume, clipping) is kept in
//! f64 in world coordinates. The `parry3d` convex polyhedron is built in the
//! camera's own frame, where f32 is accurate, and placed relative to the other
//! shape only when a query needs it — so frames 100 km from the origin test as
//! precisely as frames at the origin.

use glam::{DQuat, DVec3, Vec3};
use parry3d::math::Pose as ParryPose;
use parry3d::query::PointQuery;
use parry3d::shape::ConvexPolyhedron;

use crate::camera::Intrinsics;
use crate::error::InputError;
use crate::pose::Pose;

/// A plane `normal · p = offset` with a unit normal pointing out of the solid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    pub normal: DVec3,
    pub offset: f64,
}

impl Plane {
    /// Signed distance; negative inside.
    #[inline]
    pub fn distance(&self, p: DVec3) -> f64 {
        self.normal.dot(p) - self.offset
    }
}

/// Axis-aligned box in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub fn from_points(points: &[DVec3]) -> Aabb {
        let (mut min, mut max) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for &p in points {
            min = min.min(p);
            max = max.max(p);
        }
        Aabb { min, max }
    }

    /// Closed intersection test: boxes that touch intersect.
    pub fn intersects(&self, other: &Aabb) -> bool {
        self.min.cmple(other.max).all() && other.min.cmple(self.max).all()
    }
}

/// The frustum as six tetrahedra around its diagonal from corner 0 to corner
/// 6: every face of the frustum holds one of the two, so each face splits
/// into two triangles through it, and each triangle with the opposite end of
/// the diagonal is one tetrahedron.
pub const TETRAHEDRA: [[usize; 4]; 6] = [[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]];

pub(crate) fn tetrahedron_volume(a: DVec3, b: DVec3, c: DVec3, d: DVec3) -> f64 {
    (b - a).cross(c - a).dot(d - a).abs() / 6.0
}

/// Corner order: near plane then far plane, each top-left, top-right,
/// bottom-right, bottom-left as seen in the image.
pub const FACES: [[usize; 4]; 6] = [
    [0, 1, 2, 3], // near
    [4, 7, 6, 5], // far
    [0, 3, 7, 4], // left
    [1, 5, 6, 2], // right
    [0, 4, 5, 1], // top
    [3, 2, 6, 7], // bottom
];

#[derive(Clone, Debug)]
pub struct Frustum {
    pose: Pose,
    intrinsics: Intrinsics,
    corners: [DVec3; 8],
    planes: [Plane; 6],
    volume: f64,
    /// The volumes of its [`TETRAHEDRA`] (closed-form volumes inside planes read them).
    tetrahedra: [f64; 6],
    aabb: Aabb,
    local_shape: ConvexPolyhedron,
}

impl Frustum {
    /// The frustum of a camera at `pose` with validated `intrinsics`.
    pub fn new(pose: Pose, intrinsics: Intrinsics) -> Result<Frustum, InputError> {
        let k = intrinsics.validated()?;
        let (l, r, t, b) = k.edge_slopes();
        let mut local = [DVec3::ZERO; 8];
        for (i, z) in [k.near, k.far].into_iter().enumerate() {
            local[4 * i] = DVec3::new(l * z, t * z, z);
            local[4 * i + 1] = DVec3::new(r * z, t * z, z);
            local[4 * i + 2] = DVec3::new(r * z, b * z, z);
            local[4 * i + 3] = DVec3::new(l * z, b * z, z);
        }
        let corners = local.map(|p| pose.camera_to_world(p));
        let centroid = corners.iter().sum::<DVec3>() / 8.0;
        let planes = FACES.map(|face| {
            let [a, b, c, d] = face.map(|i| corners[i]);
            let mut normal = (c - a).cross(d - b).normalize();
            if normal.dot(centroid - a) > 0.0 {
                normal = -normal;
            }
            Plane { normal, offset: normal.dot(a) }
        });
        let volume = (r - l) * (b - t) * (k.far.powi(3) - k.near.powi(3)) / 3.0;
        let hull: Vec<Vec3> = local.iter().map(|p| p.as_vec3()).collect();
        if !volume.is_finite() || volume <= 0.0 || !hull.iter().all(|p| p.is_finite()) {
            return Err(InputError::invalid("intrinsics", format!("frustum is not finite (volume {volume}); check far and the focal lengths")));
        }
        let local_shape = ConvexPolyhedron::from_convex_hull(&hull).ok_or_else(|| {
            InputError::invalid("intrinsics", "frustum is degenerate in single precision (check near, far and focal lengths)")
        })?;
        let tetrahedra = TETRAHEDRA.map(|[a, b, c, d]| tetrahedron_volume(local[a], local[b], local[c], local[d]));
        Ok(Frustum { pose, intrinsics: k, corners, planes, volume, tetrahedra, aabb: Aabb::from_points(&corners), local_shape })
    }

    pub fn pose(&self) -> &Pose {
        &self.pose
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// The eight corners in world coordinates, in [`FACES`]' order.
    pub fn corners(&self) -> &[DVec3; 8] {
        &self.corners
    }

    /// The six bounding planes (near, far, left, right, top, bottom), normals outward.
    pub fn planes(&self) -> &[Plane; 6] {
        &self.planes
    }

    /// The volumes of its [`TETRAHEDRA`].
    pub fn tetrahedra(&self) -> &[f64; 6] {
        &self.tetrahedra
    }

    /// Exact volume of the truncated pyramid.
    pub fn volume(&self) -> f64 {
        self.volume
    }

    pub fn aabb(&self) -> &Aabb {
        &self.aabb
    }

    /// The frustum as a `parry3d` convex polyhedron in the camera's frame.
    pub fn local_shape(&self) -> &ConvexPolyhedron {
        &self.local_shape
    }

    /// Whether a world point lies inside or on the boundary (tolerance `eps`).
    #[inline]
    pub fn contains(&self, p: DVec3, eps: f64) -> bool {
        self.planes.iter().all(|pl| pl.distance(p) <= eps)
    }

    /// The same test done by parry on its polyhedron (single precision); used
    /// to cross-check the f64 planes.
    pub fn contains_parry(&self, p: DVec3) -> bool {
        self.local_shape.contains_local_point(self.pose.world_to_camera(p).as_vec3())
    }

    /// GJK intersection test between two frusta (parry). Touching counts as
    /// intersecting, so a `false` proves the overlap is exactly zero.
    pub fn intersects(&self, other: &Frustum) -> bool {
        let rel = other.pose.relative_to(&self.pose);
        let q = DQuat::from_mat3(&rel.rotation()).normalize().as_quat();
        let pos12 = ParryPose::from_parts(rel.position().as_vec3(), q);
        parry3d::query::intersection_test(&ParryPose::IDENTITY, &self.local_shape, &pos12, &other.local_shape)
            .map(|r| r.intersecting)
            // Polyhedron pairs are always supported; fall back to "maybe" if not.
            .unwrap_or(true)
    }

    /// Characteristic length used to scale numerical tolerances.
    pub(crate) fn scale(&self) -> f64 {
        1.0 + self.pose.position().abs().max_element() + self.intrinsics.far
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;
    use parry3d::shape::Shape;

    fn frustum(pose: Pose) -> Frustum {
        let k = Intrinsics::from_fov(90.0, Some(60.0), 64, 48).unwrap().with_range(0.5, 20.0).unwrap();
        Frustum::new(pose, k).unwrap()
    }

    #[test]
    fn volume_matches_parry_and_the_closed_form() {
        let f = frustum(Pose::new(DMat3::from_rotation_y(0.5), DVec3::new(3.0, 1.0, -2.0)).unwrap());
        let parry_volume = f.local_shape().mass_properties(1.0).mass() as f64;
        assert!((parry_volume - f.volume()).abs() / f.volume() < 1e-5, "{parry_volume} vs {}", f.volume());
        let (h, v) = (45f64.to_radians().tan(), 30f64.to_radians().tan());
        let expected = 4.0 * h * v * (20f64.powi(3) - 0.5f64.powi(3)) / 3.0;
        assert!((f.volume() - expected).abs() / expected < 1e-12);
    }

    #[test]
    fn planes_point_outward_and_corners_lie_on_three_planes() {
        let f = frustum(Pose::new(DMat3::from_rotation_x(-0.3), DVec3::new(0.0, 5.0, 0.0)).unwrap());
        let inside = f.pose().camera_to_world(DVec3::new(0.0, 0.0, 10.0));
        assert!(f.planes().iter().all(|p| p.distance(inside) < 0.0));
        for c in f.corners() {
            let on = f.planes().iter().filter(|p| p.distance(*c).abs() < 1e-9).count();
            assert_eq!(on, 3);
        }
    }

    #[test]
    fn containment_agrees_with_parry() {
        let f = frustum(Pose::new(DMat3::from_rotation_y(2.0), DVec3::new(100.0, 0.0, 40.0)).unwrap());
        let mut rng = crate::rng::SplitMix64::new(7);
        let lo = f.aabb().min - DVec3::splat(1.0);
        let ext = f.aabb().max - f.aabb().min + DVec3::splat(2.0);
        let mut agree = 0;
        for _ in 0..2000 {
            let p = lo + ext * DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64());
            agree += (f.contains(p, 0.0) == f.contains_parry(p)) as usize;
        }
        // Single-precision parry may disagree only for points within ~1e-5 of a face.
        assert!(agree >= 1998, "{agree}/2000");
    }

    #[test]
    fn absurd_ranges_are_refused_not_panicked_on() {
        let k = Intrinsics::from_fov(90.0, None, 64, 64).unwrap();
        for far in [1e39, 1e200] {
            let err = Frustum::new(Pose::from_position(DVec3::ZERO), k.with_range(0.1, far).unwrap()).unwrap_err();
            assert_eq!(err.field(), "intrinsics");
        }
    }

    #[test]
    fn aabb_holds_every_corner() {
        let f = frustum(Pose::new(DMat3::from_rotation_z(0.7), DVec3::ZERO).unwrap());
        for c in f.corners() {
            assert!(c.cmpge(f.aabb().min).all() && c.cmple(f.aabb().max).all());
        }
    }

    #[test]
    fn gjk_separates_cameras_looking_away_from_each_other() {
        let a = frustum(Pose::new(DMat3::from_rotation_y(std::f64::consts::PI), DVec3::ZERO).unwrap());
        let b = frustum(Pose::from_position(DVec3::new(0.0, 0.0, 1.0)));
        assert!(!a.intersects(&b));
        let c = frustum(Pose::from_position(DVec3::new(1.0, 0.0, 0.0)));
        assert!(b.intersects(&c));
    }
}
