//! The memory server's main job on a built-in trajectory (`worldpack demo`).
//!
//! A LoopNav-style ABA walk (look around at A, walk to B, come back): on
//! every step of the return leg, each policy plans the context for the next
//! frame, and the table shows how much of that frame's view the chosen
//! memories cover, how many come from the exploration leg, and how long the
//! selection took.

use std::time::Instant;

use memory::overlap::{MonteCarlo, ViewSamples};
use memory::{AngleUnit, Frustum, Intrinsics, MemoryFrame, Policy, PolicyKind, Pose, Pose5, Pose5Convention, select_by_brute_force};

/// One ABA trajectory: frames and the index where the return leg starts.
pub struct Trajectory {
    pub frames: Vec<MemoryFrame>,
    pub return_start: usize,
}

/// Looks around at A (yaw 0, 90, 180, 270, 0 in 15° steps), walks `range`
/// blocks to B one block per frame, turns around and walks back to A.
pub fn aba(range: u32, intrinsics: Intrinsics) -> Trajectory {
    let mut poses: Vec<(f64, f64, f64)> = Vec::new(); // (x, z, yaw°)
    for step in 0..=24 {
        poses.push((0.0, 0.0, 15.0 * step as f64));
    }
    // Head for B at yaw −60° (south-east in Minecraft's yaw) with a 15° turn per frame.
    let heading = -60.0;
    turn_to(&mut poses, heading);
    let (dx, dz) = forward_xz(heading);
    for i in 1..=range {
        poses.push((dx * i as f64, dz * i as f64, heading));
    }
    turn_to(&mut poses, heading + 180.0);
    let return_start = poses.len();
    let (bx, bz, _) = *poses.last().expect("walked to B");
    for i in 1..=range {
        poses.push((bx - dx * i as f64, bz - dz * i as f64, heading + 180.0));
    }
    let frames = poses
        .into_iter()
        .enumerate()
        .map(|(t, (x, z, yaw))| {
            let pose = Pose::from_pose5(&Pose5 { x, y: 65.6, z, pitch: 0.0, yaw }, Pose5Convention::Minecraft, AngleUnit::Degrees)
                .expect("finite demo pose");
            let frustum = Frustum::new(pose, intrinsics).expect("valid demo intrinsics");
            MemoryFrame { id: t as u64, time: t as u64, frustum }
        })
        .collect();
    Trajectory { frames, return_start }
}

fn forward_xz(yaw_deg: f64) -> (f64, f64) {
    let y = yaw_deg.to_radians();
    (-y.sin(), y.cos())
}

fn turn_to(poses: &mut Vec<(f64, f64, f64)>, target_yaw: f64) {
    let (x, z, mut yaw) = *poses.last().expect("a start pose");
    let gap = (target_yaw - yaw + 540.0).rem_euclid(360.0) - 180.0;
    let steps = (gap.abs() / 15.0).ceil() as usize;
    for _ in 0..steps {
        yaw += gap / steps as f64;
        poses.push((x, z, yaw));
    }
}

pub struct Row {
    pub policy: PolicyKind,
    pub coverage: f64,
    pub from_exploration: f64,
    pub median_us: f64,
}

/// Runs every policy over the return leg of an ABA trajectory.
pub fn run(range: u32) -> Vec<Row> {
    let k = Intrinsics::from_fov(70.0, None, 64, 64).expect("constant intrinsics");
    let traj = aba(range, k);
    let kinds = [
        PolicyKind::Baseline,
        PolicyKind::NearestFramePacking,
        PolicyKind::MemoryRetrieval,
        PolicyKind::WorldPack,
        PolicyKind::WorldMemGreedy,
    ];
    kinds
        .into_iter()
        .map(|kind| {
            let policy = Policy::preset(kind);
            let (mut coverage, mut from_exploration, mut picked) = (0.0, 0usize, 0usize);
            let mut times = Vec::new();
            let steps = traj.return_start..traj.frames.len();
            for t in steps.clone() {
                let memory = &traj.frames[..t];
                let target = &traj.frames[t].frustum;
                let start = Instant::now();
                let plan = select_by_brute_force(&policy, target, memory);
                times.push(start.elapsed().as_secs_f64() * 1e6);
                let chosen: Vec<&MemoryFrame> = plan.selected().map(|(_, f)| &memory[f.id as usize]).collect();
                coverage += covered_share(target, &chosen);
                from_exploration += chosen.iter().filter(|f| (f.id as usize) < traj.return_start).count();
                picked += chosen.len();
            }
            times.sort_by(f64::total_cmp);
            Row {
                policy: kind,
                coverage: coverage / steps.len() as f64,
                from_exploration: from_exploration as f64 / picked.max(1) as f64,
                median_us: times[times.len() / 2],
            }
        })
        .collect()
}

/// Share of the target frustum seen by at least one chosen frame.
fn covered_share(target: &Frustum, chosen: &[&MemoryFrame]) -> f64 {
    let mut samples = ViewSamples::monte_carlo(target, &MonteCarlo { samples: 2000, seed: 1 });
    let total = samples.len() as f64;
    for f in chosen {
        samples.remove_seen_by(&f.frustum);
    }
    1.0 - samples.len() as f64 / total
}
