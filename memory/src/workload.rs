//! The synthetic camera paths the selection benchmarks run on (the CLI's
//! `bench select` and the criterion benches share them).

use glam::{DMat3, DVec3, EulerRot};

use crate::covisibility::DepthGrid;
use crate::rng::SplitMix64;
use crate::{Frustum, Intrinsics, Pose};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Workload {
    /// LoopNav-like back-and-forth inside a 50×50-block square: nearly every box meets the query.
    Loop,
    /// A long walk across a large world: the R-tree's case.
    Walk,
}

/// Camera frusta along the workload, one block per step, seeded.
pub fn frusta(workload: Workload, n: usize, seed: u64, k: Intrinsics) -> Vec<Frustum> {
    let mut rng = SplitMix64::new(seed);
    let (mut pos, mut yaw) = (DVec3::new(0.0, 65.6, 0.0), 0.0f64);
    (0..n)
        .map(|_| {
            yaw += (rng.next_f64() - 0.5) * 0.6;
            pos += DVec3::new(-yaw.sin(), 0.0, yaw.cos());
            if workload == Workload::Loop && (pos.x.abs() > 25.0 || pos.z.abs() > 25.0) {
                pos.x = pos.x.clamp(-25.0, 25.0);
                pos.z = pos.z.clamp(-25.0, 25.0);
                yaw += std::f64::consts::PI; // turn back, as LoopNav's agent returns
            }
            let pitch = (rng.next_f64() - 0.5) * 0.3;
            let pose = Pose::new(DMat3::from_euler(EulerRot::YXZ, yaw, pitch, 0.0), pos).expect("finite workload pose");
            Frustum::new(pose, k).expect("valid workload intrinsics")
        })
        .collect()
}

/// The workload's ground, y = 64 (the cameras stand 1.6 above it): a
/// frame's coarse depth of it, `cells` columns, 0 where a ray misses it
/// within range. What occlusion-aware selection reads in the benchmarks.
pub fn ground_depth(frustum: &Frustum, cells: u32) -> DepthGrid {
    let k = frustum.intrinsics();
    let rows = ((cells as f64 * k.height as f64 / k.width as f64).round() as u32).max(1);
    let grid = k.resized(cells, rows).expect("workload intrinsics resize");
    let pose = frustum.pose();
    let mut depth = Vec::with_capacity((cells * rows) as usize);
    for v in 0..rows {
        for u in 0..cells {
            let ray = pose.rotation() * grid.unproject(glam::DVec2::new(u as f64, v as f64), 1.0);
            let t = (64.0 - pose.position().y) / ray.y;
            depth.push(if t > grid.near && t <= grid.far { t as f32 } else { 0.0 });
        }
    }
    DepthGrid { intrinsics: grid, depth }
}
