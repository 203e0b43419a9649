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
use smallvec::SmallVec;

use crate::frustum::{FACES, Frustum, Plane, TETRAHEDRA};

/// Relative tolerance for "on the plane".
const ON_PLANE: f64 = 1e-10;

/// Vertices a polytope keeps inline; a frustum clipped by a frustum or a
/// group hull stays well under this, and more spills to the heap.
const INLINE_POINTS: usize = 96;
const INLINE_FACES: usize = 20;
/// Points on one cutting plane kept inline (a cap polygon).
const INLINE_CUT: usize = 24;

type Points = SmallVec<[DVec3; INLINE_POINTS]>;
/// A face: the range `start..start + len` of [`Polytope::points`].
type Faces = SmallVec<[(u16, u16); INLINE_FACES]>;

/// A convex polytope as a list of faces, each a convex polygon in cyclic
/// order, stored flat and inline: a clip allocates nothing and moves nothing
/// (it writes the other of two buffers and switches to it).
#[derive(Clone, Debug, Default)]
pub struct Polytope {
    buffers: [(Points, Faces); 2],
    current: usize,
}

impl Polytope {
    pub fn from_frustum(f: &Frustum) -> Polytope {
        let mut poly = Polytope::default();
        poly.set_frustum(f);
        poly
    }

    /// Becomes the frustum `f`, in place (a polytope is a few kilobytes
    /// inline, so building one per clip and moving it costs a copy).
    pub fn set_frustum(&mut self, f: &Frustum) {
        let c = f.corners();
        self.current = 0;
        let (points, faces) = &mut self.buffers[0];
        points.clear();
        faces.clear();
        for (i, face) in FACES.iter().enumerate() {
            points.extend(face.iter().map(|&k| c[k]));
            faces.push((4 * i as u16, 4));
        }
    }

    fn points(&self) -> &Points {
        &self.buffers[self.current].0
    }

    fn faces(&self) -> &Faces {
        &self.buffers[self.current].1
    }

    pub fn is_empty(&self) -> bool {
        self.faces().is_empty()
    }

    /// Keeps the part with `plane.distance(p) <= eps`; says whether anything was cut away.
    pub fn clip(&mut self, plane: &Plane, eps: f64) -> bool {
        // Most planes cut nothing: leave at once.
        if self.points().iter().all(|&p| plane.distance(p) <= eps) {
            return false;
        }
        let mut cut_points: SmallVec<[DVec3; INLINE_CUT]> = SmallVec::new();
        let mut face_on_plane = false;
        let [a, b] = &mut self.buffers;
        let ((from_points, from_faces), (points, faces)) = if self.current == 0 { (&*a, b) } else { (&*b, a) };
        points.clear();
        faces.clear();
        let mut d: SmallVec<[f64; INLINE_CUT]> = SmallVec::new();
        for &(start, len) in from_faces {
            let face = &from_points[start as usize..(start + len) as usize];
            d.clear();
            d.extend(face.iter().map(|&p| plane.distance(p)));
            let start = points.len();
            if d.iter().all(|&x| x <= eps) {
                if d.iter().all(|&x| x.abs() <= eps) {
                    face_on_plane = true;
                }
                cut_points.extend(face.iter().zip(&d).filter(|(_, x)| x.abs() <= eps).map(|(p, _)| *p));
                points.extend_from_slice(face);
            } else {
                for i in 0..face.len() {
                    let j = (i + 1) % face.len();
                    let (p, q, dp, dq) = (face[i], face[j], d[i], d[j]);
                    if dp <= eps {
                        points.push(p);
                        if dp.abs() <= eps {
                            cut_points.push(p);
                        }
                    }
                    // A strict crossing: one end clearly inside, the other clearly outside.
                    if (dp < -eps && dq > eps) || (dp > eps && dq < -eps) {
                        let x = p + (q - p) * (dp / (dp - dq));
                        points.push(x);
                        cut_points.push(x);
                    }
                }
            }
            push_face(points, faces, start);
        }
        if !face_on_plane {
            let start = points.len();
            cap_polygon(&cut_points, plane.normal, eps, points);
            push_face(points, faces, start);
        }
        if faces.len() < 4 {
            points.clear();
            faces.clear();
        }
        self.current = 1 - self.current;
        true
    }

    /// Volume by summing pyramids from an interior point to every face.
    pub fn volume(&self) -> f64 {
        let points = self.points();
        if points.is_empty() {
            return 0.0;
        }
        let reference = points.iter().sum::<DVec3>() / points.len() as f64;
        let mut volume = 0.0;
        for &(start, len) in self.faces() {
            let face = &points[start as usize..(start + len) as usize];
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

/// Ends the face whose points begin at `start`: kept with three points or
/// more, else its points are dropped.
fn push_face(points: &mut Points, faces: &mut Faces, start: usize) {
    let len = points.len() - start;
    if len >= 3 {
        faces.push((start as u16, len as u16));
    } else {
        points.truncate(start);
    }
}

/// Appends the points on a cutting plane to `out`, ordered into a convex
/// polygon (duplicates within `eps` dropped); fewer than three distinct
/// points make no polygon, which the caller drops.
fn cap_polygon(points: &[DVec3], normal: DVec3, eps: f64, out: &mut Points) {
    let mut unique: SmallVec<[DVec3; INLINE_CUT]> = SmallVec::new();
    for &p in points {
        if unique.iter().all(|q| (*q - p).length() > eps) {
            unique.push(p);
        }
    }
    if unique.len() < 3 {
        return;
    }
    let centre = unique.iter().sum::<DVec3>() / unique.len() as f64;
    let u = normal.any_orthonormal_vector();
    let v = normal.cross(u);
    let mut keyed: SmallVec<[(f64, DVec3); INLINE_CUT]> = unique
        .into_iter()
        .map(|p| {
            let r = p - centre;
            (pseudo_angle(r.dot(u), r.dot(v)), p)
        })
        .collect();
    keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
    out.extend(keyed.into_iter().map(|(_, p)| p));
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
    overlap_unless_below(query, candidate, f64::NEG_INFINITY).expect("no floor rules any overlap out")
}

/// [`exact_overlap`] (the same number, computed the same way), or `None` as
/// soon as the clipping proves the overlap is below `floor`: each clip only
/// removes volume, so a partly clipped polytope already bounds the overlap,
/// and the planes left are skipped. Selection asks with the overlap a frame
/// would need to enter the plan, so most frames that cannot enter cost a
/// fraction of a full clip.
///
/// The candidate's planes are applied deepest cut first (by how far the
/// query's corners lie beyond each), so the bound falls fastest; planes
/// that leave every corner inside cut nothing and are skipped. The order
/// depends on the two frusta only, so every caller gets the same number.
pub fn overlap_unless_below(query: &Frustum, candidate: &Frustum, floor: f64) -> Option<f64> {
    if !query.aabb().intersects(candidate.aabb()) {
        return zero_unless_below(floor);
    }
    overlap_within_unless_below(query, candidate.planes(), candidate.scale(), floor)
}

/// [`overlap_unless_below`] for a candidate given by its planes and
/// [`Frustum::scale`] (whose box is known to meet the query's): the index
/// keeps these beside each member, so ranking reads no stored frame.
pub(crate) fn overlap_within_unless_below(query: &Frustum, planes: &[Plane; 6], scale: f64, floor: f64) -> Option<f64> {
    let eps = ON_PLANE * query.scale().max(scale);
    // Rounding in a partial volume must never reject a frame at its floor.
    let volume = clipped_volume(query, planes, eps, (floor - BELOW_MARGIN) * query.volume(), Need::Exact)?;
    let overlap = (volume / query.volume()).clamp(0.0, 1.0);
    if overlap == 0.0 { zero_unless_below(floor) } else { (overlap >= floor - BELOW_MARGIN).then_some(overlap) }
}

/// An overlap of exactly 0, unless `floor` rules it out.
fn zero_unless_below(floor: f64) -> Option<f64> {
    (0.0 >= floor - BELOW_MARGIN).then_some(0.0)
}

/// What a caller of [`clipped_volume`] needs once the volume is not below its floor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    /// The volume itself, computed the same way whatever the floor.
    Exact,
    /// Any upper bound on it (a group hull's): once the volume is proved to
    /// reach the floor, a looser bound in closed form will do.
    Bound,
}

/// The volume of `query` inside every plane of `planes` (normals outward,
/// tolerance `eps`), or `None` once it is proved below `floor_volume`.
/// Planes are applied deepest cut first (by how far the query's corners lie
/// beyond each), so the volume falls fastest; a plane that leaves every
/// corner inside cuts nothing and is skipped (the query is their hull). The
/// order depends on the inputs only, so every caller gets the same number.
/// With [`Need::Bound`] the answer may be an upper bound settled in closed
/// form, without clipping.
pub fn clipped_volume(query: &Frustum, planes: &[Plane], eps: f64, floor_volume: f64, need: Need) -> Option<f64> {
    let mut cutting: SmallVec<[(f64, usize); 12]> = SmallVec::new();
    let mut distances: SmallVec<[[f64; 8]; 12]> = SmallVec::new();
    for (i, plane) in planes.iter().enumerate() {
        let d = query.corners().map(|c| plane.distance(c));
        let depth: f64 = d.iter().map(|&x| if x > eps { x } else { 0.0 }).sum();
        if depth > 0.0 {
            cutting.push((depth, i));
        }
        distances.push(d);
    }
    if cutting.is_empty() {
        return Some(query.volume());
    }
    cutting.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    // The query's volume inside one plane, or inside the two deepest at once,
    // in closed form, already bounds the volume inside all of them: most
    // frames that cannot enter are proved so without building a polytope.
    if floor_volume > 0.0 && cutting.len() > 1 {
        let tetrahedra = Tetrahedra::of(query);
        let mut inside: SmallVec<[f64; 12]> = SmallVec::new();
        let mut upper = f64::INFINITY;
        for &(_, i) in cutting.iter().take(SINGLE_PLANE_TRIES) {
            inside.push(tetrahedra.inside(&distances[i]));
            upper = upper.min(inside[inside.len() - 1]);
            if upper < floor_volume {
                return None;
            }
        }
        if cutting.len() > 2 {
            upper = upper.min(tetrahedra.inside_both(&distances[cutting[0].1], &distances[cutting[1].1]));
            if upper < floor_volume {
                return None;
            }
        }
        // A bound may stop here once the volume is proved to reach the floor:
        // what each plane cuts off, added up, is at least what all of them cut
        // off together, so the volume is at least the rest.
        if need == Need::Bound {
            for &(_, i) in &cutting[inside.len()..] {
                inside.push(tetrahedra.inside(&distances[i]));
                upper = upper.min(inside[inside.len() - 1]);
            }
            if upper < floor_volume {
                return None;
            }
            let cut_off: f64 = inside.iter().map(|v| query.volume() - v).sum();
            if query.volume() - cut_off >= floor_volume {
                return Some(upper);
            }
        }
    }
    let mut poly = Polytope::default();
    poly.set_frustum(query);
    for (n, &(_, i)) in cutting.iter().enumerate() {
        let cut = poly.clip(&planes[i], eps);
        if poly.is_empty() {
            return Some(0.0);
        }
        if cut && floor_volume > 0.0 && n + 1 < cutting.len() && poly.volume() < floor_volume {
            return None;
        }
    }
    Some(poly.volume())
}

/// Slack below a floor within which [`overlap_unless_below`] still computes
/// the exact overlap (far above the clipper's rounding).
const BELOW_MARGIN: f64 = 1e-9;

/// Planes (deepest cut first) whose closed-form bound is tried before clipping.
const SINGLE_PLANE_TRIES: usize = 2;

/// A frustum as its [`TETRAHEDRA`], with their volumes, for volumes inside
/// planes in closed form.
struct Tetrahedra<'a> {
    corners: &'a [DVec3; 8],
    volumes: &'a [f64; 6],
}

impl<'a> Tetrahedra<'a> {
    fn of(f: &'a Frustum) -> Self {
        Tetrahedra { corners: f.corners(), volumes: f.tetrahedra() }
    }

    /// The volume where the signed distance `d` (one per corner, to a plane,
    /// linear in space) is ≤ 0.
    fn inside(&self, d: &[f64; 8]) -> f64 {
        TETRAHEDRA.iter().zip(self.volumes).map(|(t, v)| v * fraction_inside(t.map(|i| d[i]))).sum()
    }

    /// The volume where both `a` and `b` are ≤ 0: each tetrahedron's part
    /// inside `a`, cut into tetrahedra, then each of those cut by `b`.
    fn inside_both(&self, a: &[f64; 8], b: &[f64; 8]) -> f64 {
        let mut volume = 0.0;
        for (t, whole) in TETRAHEDRA.iter().zip(self.volumes) {
            let (da, db) = (t.map(|i| a[i]), t.map(|i| b[i]));
            match (fraction_inside(da), fraction_inside(db)) {
                (0.0, _) | (_, 0.0) => {}
                (1.0, f) | (f, 1.0) => volume += whole * f,
                _ => {
                    for (v, e) in tetrahedra_inside(t.map(|i| self.corners[i]), da, db) {
                        volume += tetrahedron_inside(v, e);
                    }
                }
            }
        }
        volume
    }
}

/// The part of tetrahedron `v` where the linear function with values `d` at
/// its vertices is ≤ 0, as at most three tetrahedra, each with the values
/// of a second linear function `e` at its vertices (interpolated, as `e` is
/// linear along every edge).
fn tetrahedra_inside(v: [DVec3; 4], d: [f64; 4], e: [f64; 4]) -> SmallVec<[([DVec3; 4], [f64; 4]); 3]> {
    let inside = d.map(|x| x <= 0.0);
    let count = inside.iter().filter(|&&i| i).count();
    // Where the plane crosses the edge from vertex i to vertex j, and `e` there.
    let cross = |i: usize, j: usize| {
        let s = d[i] / (d[i] - d[j]);
        (v[i] + (v[j] - v[i]) * s, e[i] + (e[j] - e[i]) * s)
    };
    let mut out = SmallVec::new();
    match count {
        0 => {}
        4 => out.push((v, e)),
        1 => {
            let lone = (0..4).find(|&i| inside[i]).expect("one vertex inside");
            let o: SmallVec<[usize; 3]> = (0..4).filter(|&i| i != lone).collect();
            let [(p, ep), (q, eq), (r, er)] = [cross(lone, o[0]), cross(lone, o[1]), cross(lone, o[2])];
            out.push(([v[lone], p, q, r], [e[lone], ep, eq, er]));
        }
        _ => {
            // A prism between the triangle of inside vertices (or, with two
            // inside, each inside vertex's two crossings) and its image: three
            // inside (x, y, z) map to their crossings towards the outside one;
            // two inside (a, b) give triangles (a, ac, ae) and (b, bc, be).
            let i: SmallVec<[usize; 3]> = (0..4).filter(|&k| inside[k]).collect();
            let o: SmallVec<[usize; 2]> = (0..4).filter(|&k| !inside[k]).collect();
            let (bottom, top) = if count == 3 {
                let [x, y, z] = [i[0], i[1], i[2]];
                ([(v[x], e[x]), (v[y], e[y]), (v[z], e[z])], [cross(x, o[0]), cross(y, o[0]), cross(z, o[0])])
            } else {
                let (a, b) = (i[0], i[1]);
                ([(v[a], e[a]), cross(a, o[0]), cross(a, o[1])], [(v[b], e[b]), cross(b, o[0]), cross(b, o[1])])
            };
            // Prism (x, y, z) / (x', y', z') as tetrahedra (x, y, z, x'), (y, z, x', y'), (z, x', y', z').
            for [p, q, r, s] in [[bottom[0], bottom[1], bottom[2], top[0]], [bottom[1], bottom[2], top[0], top[1]], [bottom[2], top[0], top[1], top[2]]] {
                out.push(([p.0, q.0, r.0, s.0], [p.1, q.1, r.1, s.1]));
            }
        }
    }
    out
}

/// The part of tetrahedron `v` where the linear function with values `d` at
/// its vertices is ≤ 0.
fn tetrahedron_inside(v: [DVec3; 4], d: [f64; 4]) -> f64 {
    match fraction_inside(d) {
        0.0 => 0.0,
        f => f * crate::frustum::tetrahedron_volume(v[0], v[1], v[2], v[3]),
    }
}

/// The share of a tetrahedron's volume where the linear function with
/// values `d` at its vertices is ≤ 0. A vertex tetrahedron cut off by the
/// plane is the whole one scaled by where the plane crosses its three
/// edges (`s = d_i / (d_i − d_j)` along each), so no coordinates are needed.
fn fraction_inside(d: [f64; 4]) -> f64 {
    // Bit k set: vertex k inside. Called for every tetrahedron of every
    // bound, so it looks the case up by the mask instead of counting.
    let mask = (d[0] <= 0.0) as usize | ((d[1] <= 0.0) as usize) << 1 | ((d[2] <= 0.0) as usize) << 2 | ((d[3] <= 0.0) as usize) << 3;
    let [a, b, c, e] = SPLITS[mask].map(usize::from);
    // How far along the edge from vertex i to vertex j the plane crosses it.
    let s = |i: usize, j: usize| d[i] / (d[i] - d[j]);
    match INSIDE_COUNT[mask] {
        0 => 0.0,
        4 => 1.0,
        // One vertex inside (a): the corner tetrahedron cut off at it.
        1 => s(a, b) * s(a, c) * s(a, e),
        // One vertex outside (e): the whole less the corner cut off at e.
        3 => 1.0 - s(e, a) * s(e, b) * s(e, c),
        _ => {
            // Inside a, b; outside c, e: the prism (a, ac, ae) / (b, bc, be)
            // as three tetrahedra, (a, ac, ae, b), (ac, ae, b, bc) and
            // (ae, b, bc, be), whose shares of the whole are these products.
            let (s1, s2, s3, s4) = (s(a, c), s(a, e), s(b, c), s(b, e));
            s1 * s2 + s2 * s3 * (1.0 - s1) + s3 * s4 * (1.0 - s2)
        }
    }
}

/// Vertices inside (bit set in the mask) per mask.
const INSIDE_COUNT: [u8; 16] = [0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4];

/// Per mask, the four vertices with those inside first, each side in index order.
const SPLITS: [[u8; 4]; 16] = {
    let mut splits = [[0u8; 4]; 16];
    let mut mask = 0;
    while mask < 16 {
        let mut n = 0;
        let mut side = 0;
        while side < 2 {
            let mut k = 0;
            while k < 4 {
                if ((mask >> k) & 1 == 1) == (side == 0) {
                    splits[mask][n] = k as u8;
                    n += 1;
                }
                k += 1;
            }
            side += 1;
        }
        mask += 1;
    }
    splits
};

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
    fn the_closed_form_volumes_inside_one_and_two_planes_are_the_clipped_volumes() {
        let mut rng = crate::rng::SplitMix64::new(3);
        let mut u = move || rng.next_f64();
        for case in 0..2000 {
            let rot = DMat3::from_euler(glam::EulerRot::YXZ, 6.3 * u(), 1.2 * (u() - 0.5), 0.3 * (u() - 0.5));
            let f = at(rot, DVec3::new(4.0 * u(), 60.0 + 4.0 * u(), 4.0 * u()), 0.1 + u(), 5.0 + 30.0 * u());
            // Planes through random points of the frustum's box, random normals.
            let b = f.aabb();
            let mut plane = || {
                let point = b.min + (b.max - b.min) * DVec3::new(u(), u(), u());
                let normal = DVec3::new(u() - 0.5, u() - 0.5, u() - 0.5).normalize();
                Plane { normal, offset: normal.dot(point) }
            };
            let (p, q) = (plane(), plane());
            let distances = |plane: &Plane| f.corners().map(|c| plane.distance(c));
            let tetrahedra = Tetrahedra::of(&f);
            let mut poly = Polytope::from_frustum(&f);
            poly.clip(&p, 0.0);
            let one = tetrahedra.inside(&distances(&p));
            assert!((one - poly.volume()).abs() <= 1e-9 * f.volume(), "case {case}, one plane: {one} vs {}", poly.volume());
            poly.clip(&q, 0.0);
            let two = tetrahedra.inside_both(&distances(&p), &distances(&q));
            assert!((two - poly.volume()).abs() <= 1e-9 * f.volume(), "case {case}, two planes: {two} vs {}", poly.volume());
        }
    }

    #[test]
    fn a_bound_is_never_below_the_volume_and_rules_out_only_what_is_below_the_floor() {
        let mut rng = crate::rng::SplitMix64::new(5);
        let mut u = move || rng.next_f64();
        let mut settled = 0;
        for case in 0..3000 {
            let frustum = |u: &mut dyn FnMut() -> f64| {
                let rot = DMat3::from_euler(glam::EulerRot::YXZ, 0.8 * u(), 0.4 * (u() - 0.5), 0.0);
                at(rot, DVec3::new(4.0 * u(), 60.0 + u(), 4.0 * u()), 0.1, 20.0 + 10.0 * u())
            };
            let (query, other) = (frustum(&mut u), frustum(&mut u));
            // The other's planes, and every other case also the six axis planes
            // around its corners, as a group hull has.
            let mut planes = other.planes().to_vec();
            if case % 2 == 1 {
                for normal in [DVec3::X, DVec3::NEG_X, DVec3::Y, DVec3::NEG_Y, DVec3::Z, DVec3::NEG_Z] {
                    planes.push(Plane { normal, offset: other.corners().iter().map(|c| normal.dot(*c)).fold(f64::MIN, f64::max) });
                }
            }
            let exact = clipped_volume(&query, &planes, 0.0, f64::NEG_INFINITY, Need::Exact).expect("no floor");
            let floor = exact * (0.5 + u());
            let tolerance = 1e-9 * query.volume();
            for need in [Need::Exact, Need::Bound] {
                match clipped_volume(&query, &planes, 0.0, floor, need) {
                    Some(v) if need == Need::Exact => assert!((v - exact).abs() <= tolerance, "case {case}: {v} vs {exact}"),
                    Some(v) => {
                        assert!(v >= exact - tolerance, "case {case}: bound {v} below the volume {exact}");
                        settled += (v > exact + tolerance) as usize;
                    }
                    None => assert!(exact < floor + tolerance, "case {case}: {exact} ruled out below the floor {floor}"),
                }
            }
        }
        assert!(settled > 100, "only {settled} bounds were settled in closed form");
    }

    #[test]
    fn the_case_tables_split_every_mask() {
        for mask in 0..16usize {
            let count = INSIDE_COUNT[mask] as usize;
            assert_eq!(count, mask.count_ones() as usize);
            let split = SPLITS[mask].map(usize::from);
            let mut seen = split.to_vec();
            seen.sort();
            assert_eq!(seen, [0, 1, 2, 3], "mask {mask:04b}: every vertex once");
            assert!(split.iter().enumerate().all(|(n, &k)| ((mask >> k) & 1 == 1) == (n < count)), "mask {mask:04b}: inside first");
        }
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
