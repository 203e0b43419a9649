//! Occlusion-aware selection. Frustum overlap counts the volume two views
//! share, so a frame behind a wall that looks the same way as the target
//! scores high although it saw none of the target's surfaces. With depth,
//! selection can ask what matters: which of the surfaces the target view
//! will show did each stored frame see, unoccluded?
//!
//! Two stages, so the cost stays a small multiple of the frustum path:
//! 1. the `candidates` best frames by the policy's own frustum score
//!    (overlap minus the recency penalty, against the policy's query view:
//!    for WorldPack the newest frame's, one step from the target; the
//!    indexed selection);
//! 2. the target's expected surface: the coarse depth of the newest stored
//!    frame with depth (the paper's query view p_t, one step from the target)
//!    and of the best candidates, `sources` frames in all, splatted into the
//!    target's coarse grid behind one z-buffer (the nearest surface per cell
//!    wins, so what a wrong candidate saw behind a wall stays hidden behind the
//!    wall the newest frame saw); then each candidate's
//!    co-visibility, the share of those surface points that project into its
//!    own coarse depth grid no deeper than the surface it recorded there
//!    (within `tolerance`).
//!
//! Candidates are then scored like WorldPack's frames, with co-visibility in
//! place of overlap (`overlap·c − recency·Δt`), and packed by rank. Frames
//! without depth keep their frustum overlap.

use glam::{DVec2, DVec3};
use serde::Serialize;

use crate::error::InputError;
use crate::index::Stack;
pub use crate::policy::CoVisibility;
use crate::policy::{ContextPlan, Packing, Policy, PolicyKind, Ranking, SelectedFrame, age, rank_order};
use crate::{Estimator, Frustum, Intrinsics, Pose};

/// A frame's depth on a coarse grid: per cell, the nearest surface recorded
/// in it (depth along the optical axis, world units; 0: nothing in range).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthGrid {
    /// The frame's intrinsics resized to the grid.
    pub intrinsics: Intrinsics,
    pub depth: Vec<f32>,
}

impl DepthGrid {
    /// Pools a full-resolution depth map (`intrinsics`' size, row-major,
    /// 0 = nothing in range) into `cells` columns and as many rows as keep
    /// the aspect. Each cell keeps its nearest surface: whatever is behind it
    /// in part of the cell counts as hidden, the conservative side for
    /// occlusion.
    pub fn pool(depth: &[f32], intrinsics: &Intrinsics, cells: u32) -> Result<DepthGrid, InputError> {
        let (w, h) = (intrinsics.width as usize, intrinsics.height as usize);
        if depth.len() != w * h {
            return Err(InputError::invalid("depth", format!("has {} values, the intrinsics say {w}×{h} = {}", depth.len(), w * h)));
        }
        if cells == 0 || cells as usize > w {
            return Err(InputError::invalid("cells", format!("must be in 1..={w}, got {cells}")));
        }
        let rows = ((cells as f64 * h as f64 / w as f64).round() as u32).max(1);
        let grid = intrinsics.resized(cells, rows)?;
        let mut out = vec![0.0f32; (cells * rows) as usize];
        for (v, row) in depth.chunks(w).enumerate() {
            let gy = v * rows as usize / h;
            for (u, &d) in row.iter().enumerate() {
                if d > 0.0 && d.is_finite() {
                    let cell = &mut out[gy * cells as usize + u * cells as usize / w];
                    if *cell == 0.0 || d < *cell {
                        *cell = d;
                    }
                }
            }
        }
        Ok(DepthGrid { intrinsics: grid, depth: out })
    }

    fn at(&self, uv: DVec2) -> Option<f32> {
        let (u, v) = ((uv.x + 0.5).floor(), (uv.y + 0.5).floor());
        let (w, h) = (self.intrinsics.width as f64, self.intrinsics.height as f64);
        (u >= 0.0 && v >= 0.0 && u < w && v < h).then(|| self.depth[v as usize * self.intrinsics.width as usize + u as usize])
    }

    /// The world points of every cell with a surface, seen from `pose`.
    fn points<'a>(&'a self, pose: &'a Pose) -> impl Iterator<Item = DVec3> + 'a {
        let w = self.intrinsics.width as usize;
        self.depth.iter().enumerate().filter(|(_, d)| **d > 0.0).map(move |(i, &d)| {
            let uv = DVec2::new((i % w) as f64, (i / w) as f64);
            pose.camera_to_world(self.intrinsics.unproject(uv, d as f64))
        })
    }
}

/// The target's expected surface: the sources' coarse depth splatted into
/// `grid` (the target's intrinsics at the coarse size) from `target`, the
/// nearest point per cell; world points of the filled cells.
pub fn expected_surface(target: &Pose, grid: &Intrinsics, sources: &[(&Pose, &DepthGrid)]) -> Vec<DVec3> {
    let w = grid.width as usize;
    let mut nearest: Vec<Option<(f64, DVec3)>> = vec![None; w * grid.height as usize];
    for (pose, depth) in sources {
        for p in depth.points(pose) {
            let c = target.world_to_camera(p);
            if c.z < grid.near || c.z > grid.far {
                continue;
            }
            let Some(uv) = grid.project(c) else { continue };
            let (u, v) = ((uv.x + 0.5).floor(), (uv.y + 0.5).floor());
            if u < 0.0 || v < 0.0 || u >= grid.width as f64 || v >= grid.height as f64 {
                continue;
            }
            let cell = &mut nearest[v as usize * w + u as usize];
            if cell.is_none_or(|(z, _)| c.z < z) {
                *cell = Some((c.z, p));
            }
        }
    }
    nearest.into_iter().flatten().map(|(_, p)| p).collect()
}

/// The share of `points` a frame at `pose` with `depth` saw unoccluded: in
/// its view and range, and no deeper than its recorded surface there times
/// `1 + tolerance` (a cell with nothing in range hides nothing).
pub fn visible_share(points: &[DVec3], pose: &Pose, depth: &DepthGrid, tolerance: f64) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let k = &depth.intrinsics;
    let seen = points
        .iter()
        .filter(|&&p| {
            let c = pose.world_to_camera(p);
            if c.z < k.near || c.z > k.far {
                return false;
            }
            match k.project(c).and_then(|uv| depth.at(uv)) {
                Some(d) => d == 0.0 || c.z <= d as f64 * (1.0 + tolerance),
                None => false,
            }
        })
        .count();
    seen as f64 / points.len() as f64
}

/// What the co-visibility stage did, for the answer and the benchmarks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CoVisibilityStats {
    /// Frames the frustum stage kept.
    pub candidates: usize,
    /// Of those, frames with depth (scored by co-visibility).
    pub with_depth: usize,
    /// Points of the target's expected surface.
    pub surface_points: usize,
}

/// Re-ranks by co-visibility (module docs): `policy` gives the packing and
/// the score weights; `depth_of` the coarse depth of a stored frame, if any.
/// [`Stack::plan`] calls it for a policy with `covisibility` set.
/// Without any candidate depth this is `policy`'s own frustum-score ranking.
/// `previous` (the last plan for a nearby target) only speeds the first stage up.
/// The policy's `keep_last` pin is not applied: every slot is ranked by score.
pub fn rerank<'a, 'm>(
    memory: impl Into<Stack<'m>>,
    policy: &Policy,
    target: &Frustum,
    settings: &CoVisibility,
    previous: Option<&ContextPlan>,
    depth_of: impl Fn(u64) -> Option<&'a DepthGrid>,
) -> Result<(ContextPlan, CoVisibilityStats), InputError> {
    let memory: Stack<'m> = memory.into();
    let settings = settings.validated()?;
    // Stage 1 scores like the policy, against its own query view (for
    // WorldPack the newest frame, one step from the target), so the index
    // prunes as it does there; it keeps `candidates` frames.
    let stage1 = Policy {
        kind: PolicyKind::WorldPack,
        ranking: Ranking::Score,
        packing: Packing::uncompressed(settings.candidates),
        estimator: Estimator::Exact,
        weights: policy.weights,
        keep_last: false,
        query: policy.query,
        covisibility: None,
    };
    let (first, _) = memory.select(&stage1, target, previous);
    let candidates: Vec<SelectedFrame> = first.selected().map(|(_, f)| *f).collect();
    let posed = |f: &SelectedFrame| memory.get(f.id).map(|m| m.frustum.pose());
    let newest = memory.newest_first().find(|f| depth_of(f.id).is_some()).map(|f| f.id);
    let mut source_ids: Vec<u64> = newest.into_iter().collect();
    source_ids.extend(candidates.iter().map(|f| f.id).filter(|&id| Some(id) != newest && depth_of(id).is_some()));
    source_ids.truncate(settings.sources);
    let sources: Vec<(&Pose, &DepthGrid)> =
        source_ids.iter().filter_map(|&id| Some((memory.get(id)?.frustum.pose(), depth_of(id)?))).collect();
    let k = target.intrinsics();
    let rows = (settings.cells as f64 * k.height as f64 / k.width as f64).round().max(1.0) as u32;
    let surface = expected_surface(target.pose(), &k.resized(settings.cells, rows)?, &sources);
    let t_now = memory.newest_first().next().map_or(0, |f| f.time);
    let mut with_depth = 0;
    let mut ranked: Vec<SelectedFrame> = candidates
        .iter()
        .map(|f| {
            let seen = match (surface.is_empty(), posed(f).zip(depth_of(f.id))) {
                (false, Some((pose, depth))) => {
                    with_depth += 1;
                    visible_share(&surface, pose, depth, settings.tolerance)
                }
                _ => f.overlap,
            };
            SelectedFrame { id: f.id, time: f.time, overlap: seen, score: policy.weights.score(seen, age(f.time, t_now)) }
        })
        .collect();
    ranked.sort_by(rank_order);
    let stats = CoVisibilityStats { candidates: candidates.len(), with_depth, surface_points: surface.len() };
    Ok((ContextPlan::from_ranked(&policy.packing, &ranked), stats))
}

#[cfg(test)]
mod tests {
    use glam::DMat3;

    use super::*;
    use crate::{FrameMemory, MemoryFrame};

    /// Axis-aligned boxes as (min, max) corners.
    type Scene = [(DVec3, DVec3)];

    /// Depth along the optical axis of the nearest box each pixel's ray meets (0: none in range).
    fn render_depth(scene: &Scene, pose: &Pose, k: &Intrinsics) -> Vec<f32> {
        let mut out = Vec::with_capacity((k.width * k.height) as usize);
        for v in 0..k.height {
            for u in 0..k.width {
                // Camera ray with z = 1, so the ray parameter is the depth.
                let ray_cam = k.unproject(DVec2::new(u as f64, v as f64), 1.0);
                let (o, d) = (pose.position(), pose.rotation() * ray_cam);
                let mut best = f64::INFINITY;
                for (lo, hi) in scene {
                    let (t1, t2) = ((*lo - o) / d, (*hi - o) / d);
                    let (near, far) = (t1.min(t2).max_element(), t1.max(t2).min_element());
                    if near <= far && near > k.near && near < best {
                        best = near;
                    }
                }
                out.push(if best <= k.far { best as f32 } else { 0.0 });
            }
        }
        out
    }

    /// A camera at (x, 0, z) turned `yaw_deg` about the vertical (negative: towards -x).
    fn camera(x: f64, z: f64, yaw_deg: f64) -> Pose {
        Pose::new(DMat3::from_rotation_y(yaw_deg.to_radians()), DVec3::new(x, 0.0, z)).unwrap()
    }

    /// A room split by a wall along x = 0. The target and the newest frame look
    /// down the left half; frame A stands in the right half looking the same
    /// way, so its frustum shares much of the target's volume but it saw none
    /// of the target's surfaces; frame B stands where the target does, turned
    /// 40° left, and saw part of them.
    #[test]
    fn a_wall_fools_frustum_overlap_but_not_co_visibility() {
        let v = |x, y, z| DVec3::new(x, y, z);
        let scene = [
            (v(-0.5, -20.0, 2.0), v(0.5, 20.0, 40.0)),    // the dividing wall
            (v(-60.0, -20.0, 35.0), v(60.0, 20.0, 36.0)), // the far wall
            (v(-31.0, -20.0, -10.0), v(-30.0, 20.0, 40.0)), // the left wall
        ];
        let k = Intrinsics::from_fov(70.0, None, 64, 48).unwrap().with_range(0.1, 40.0).unwrap();
        let target = Frustum::new(camera(-5.0, 0.0, 0.0), k).unwrap();
        let frames = [(1, camera(5.0, 0.0, 0.0)), (2, camera(-5.0, 0.0, -40.0)), (3, camera(-5.0, 0.0, -1.0))];
        let (a, b, newest) = (1u64, 2u64, 3u64);
        let mut memory = FrameMemory::new();
        let mut depth = std::collections::HashMap::new();
        for (id, pose) in frames {
            memory.insert(MemoryFrame { id, time: id, frustum: Frustum::new(pose, k).unwrap() }).unwrap();
            depth.insert(id, DepthGrid::pool(&render_depth(&scene, &pose, &k), &k, 16).unwrap());
        }
        let policy = Policy::preset(crate::PolicyKind::WorldPack);
        let order = |plan: &ContextPlan| plan.selected().map(|(_, f)| f.id).collect::<Vec<_>>();
        let frustum_first = order(&memory.select(&Policy::best_overlap_frames(3), &target, None).0);
        assert_eq!(frustum_first, [newest, a, b], "frustum overlap ranks the frame behind the wall above B");

        // The policy without co-visibility plans as the index does; with it, the plan re-ranks.
        let frustum_plan = memory.plan(&policy, &target, None, |id| depth.get(&id)).unwrap();
        assert_eq!((frustum_plan.plan, frustum_plan.covisibility), (memory.select(&policy, &target, None).0, None));
        let policy = Policy { covisibility: Some(CoVisibility::default()), ..policy };
        let chosen = memory.plan(&policy, &target, None, |id| depth.get(&id)).unwrap();
        let (plan, stats) = (chosen.plan, chosen.covisibility.expect("co-visibility's stats"));
        assert_eq!(order(&plan), [newest, b, a], "co-visibility sees through the trick");
        assert_eq!((stats.candidates, stats.with_depth), (3, 3));
        assert!(stats.surface_points > 100, "{stats:?}");
        let seen: std::collections::HashMap<u64, f64> = plan.selected().map(|(_, f)| (f.id, f.overlap)).collect();
        assert!(seen[&newest] > 0.9 && seen[&b] > 0.2 && seen[&a] < 0.05, "co-visibility {seen:?}");

        // Without depth the stage falls back to frustum overlap against the target.
        let (plan, stats) = rerank(&memory, &policy, &target, &CoVisibility::default(), None, |_| None).unwrap();
        assert_eq!((stats.with_depth, stats.surface_points), (0, 0));
        assert_eq!(order(&plan)[1], a);
    }

    #[test]
    fn pooling_keeps_the_nearest_surface_and_names_bad_input() {
        let k = Intrinsics::from_fov(70.0, None, 4, 2).unwrap();
        let grid = DepthGrid::pool(&[5.0, 2.0, 0.0, 0.0, 7.0, 9.0, 0.0, 3.0], &k, 2).unwrap();
        assert_eq!((grid.intrinsics.width, grid.intrinsics.height), (2, 1));
        assert_eq!(grid.depth, [2.0, 3.0]);
        let err = DepthGrid::pool(&[1.0; 3], &k, 2).unwrap_err().to_string();
        assert!(err.contains("depth") && err.contains("4×2"), "{err}");
        let err = DepthGrid::pool(&[1.0; 8], &k, 5).unwrap_err().to_string();
        assert!(err.contains("cells"), "{err}");
        let bad = CoVisibility { tolerance: f64::NAN, ..CoVisibility::default() };
        assert!(bad.validated().unwrap_err().to_string().contains("covisibility.tolerance"));
        let bad = CoVisibility { candidates: CoVisibility::MAX_CANDIDATES + 1, ..CoVisibility::default() };
        assert!(bad.validated().unwrap_err().to_string().contains("covisibility.candidates"));
    }
}
