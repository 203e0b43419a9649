//! Where methods fail: return-leg targets grouped by what makes them hard
//! for a geometric memory (the paper's "Discussion and Limitation"):
//! views the last few frames do not show, remembered spots hidden behind
//! nearer geometry, places revisited facing the other way, and memories
//! far back in time. Every feature comes from the true poses and depth.

use glam::{DVec2, DVec3};
use memory::{FrameMemory, MemoryFrame, Policy};
use serde::Serialize;

use model::warp::DEPTH_UNIT_M;
use crate::suite::{RETURN_PHASE, SuiteError, Trajectory};

/// What one target asks of the memory.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TargetFeatures {
    pub t: usize,
    /// Share of the target's surface points (pixels with depth) that at
    /// least one of the [`RECENT_FRAMES`] newest frames shows.
    pub recent_visible: f64,
    /// Share that only older frames show: what memory beyond recency can add.
    pub memory_only: f64,
    /// Age in frames of the older frame that shows most of that share
    /// (`None` when no older frame shows any of it).
    pub memory_age: Option<usize>,
    /// Of the target's surface points that fall inside the image of the frame
    /// whose frustum overlaps the target most, the share hidden there behind
    /// nearer geometry (`None`: no such point).
    pub occluded: Option<f64>,
    /// Of exploration frames within [`REVISIT_RADIUS`] blocks, the smallest
    /// angle (degrees) between their view and the target's (`None`: no
    /// exploration frame that close).
    pub revisit_angle_deg: Option<f64>,
    /// Share of the target's surface points that some exploration frame
    /// shows ([`explored_share`]): how much of this view the agent has seen.
    pub explored: f64,
}

pub const RECENT_FRAMES: usize = 4;
pub const REVISIT_RADIUS: f64 = 3.0;
/// Pixel stride of [`explored_share`]'s surface points (as `plan --memory-need`'s).
pub const EXPLORED_STRIDE: usize = 4;
/// The explored share from which a target is a revisit.
pub const REVISIT_SHARE: f64 = 0.5;

/// The groups the report breaks results into. Thresholds were fixed before
/// looking at any model's scores.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stratum {
    All,
    /// At least 10% of the view is shown only by frames older than the 4 newest.
    MemoryDependent,
    /// At least 30% of what the best-overlap frame should show is hidden in it.
    Occluded,
    /// Back near an explored place, but no frame there looked within 90° of this way.
    OppositeRevisit,
    /// That memory-only content is best shown by a frame 100 or more frames old.
    LongHorizon,
    /// At least half of the view was seen during exploration: where memory can bring the scene back.
    Revisit,
    /// Less than half of the view was seen during exploration: where the model has to paint.
    NewGround,
}

impl Stratum {
    pub const ALL: [Stratum; 7] =
        [Stratum::All, Stratum::MemoryDependent, Stratum::Occluded, Stratum::OppositeRevisit, Stratum::LongHorizon, Stratum::Revisit, Stratum::NewGround];

    pub fn name(self) -> &'static str {
        match self {
            Stratum::All => "all",
            Stratum::MemoryDependent => "memory_dependent",
            Stratum::Occluded => "occluded",
            Stratum::OppositeRevisit => "opposite_revisit",
            Stratum::LongHorizon => "long_horizon",
            Stratum::Revisit => "revisit",
            Stratum::NewGround => "new_ground",
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            Stratum::All => "every return-leg target",
            Stratum::MemoryDependent => "≥ 10% of the view is shown only by frames older than the 4 newest",
            Stratum::Occluded => "≥ 30% of the best-overlap frame's in-view points are hidden in it",
            Stratum::OppositeRevisit => "within 3 blocks of an explored pose, none facing within 90°",
            Stratum::LongHorizon => "memory-dependent, and the frame showing most of that memory is ≥ 100 frames old",
            Stratum::Revisit => "≥ 50% of the view was seen by an exploration frame",
            Stratum::NewGround => "< 50% of the view was seen by an exploration frame",
        }
    }

    pub fn contains(self, f: &TargetFeatures) -> bool {
        match self {
            Stratum::All => true,
            Stratum::MemoryDependent => f.memory_only >= 0.1,
            Stratum::Occluded => f.occluded.is_some_and(|o| o >= 0.3),
            Stratum::OppositeRevisit => f.revisit_angle_deg.is_some_and(|a| a > 90.0),
            Stratum::LongHorizon => f.memory_only >= 0.1 && f.memory_age.is_some_and(|a| a >= 100),
            Stratum::Revisit | Stratum::NewGround => self.contains_explored(f.explored),
        }
    }

    /// For the strata a frame's explored share alone decides (revisit and new
    /// ground): whether a frame with that share belongs; false for the others.
    pub fn contains_explored(self, explored: f64) -> bool {
        match self {
            Stratum::Revisit => explored >= REVISIT_SHARE,
            Stratum::NewGround => explored < REVISIT_SHARE,
            _ => false,
        }
    }
}

/// The world points of frame `t`'s pixels that have depth, on every
/// `stride`-th row and column.
fn surface_points(traj: &Trajectory, t: usize, stride: usize) -> Vec<DVec3> {
    let k = &traj.intrinsics;
    let w = k.width as usize;
    let stride = stride.max(1);
    traj.depth(t)
        .iter()
        .enumerate()
        .filter(|(i, d)| **d > 0 && (i % w).is_multiple_of(stride) && (i / w).is_multiple_of(stride))
        .map(|(i, &d)| traj.poses[t].camera_to_world(k.unproject(DVec2::new((i % w) as f64, (i / w) as f64), d as f64 * DEPTH_UNIT_M)))
        .collect()
}

/// Where a world point stands for frame `src`.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Sight {
    /// Behind the camera, outside the image, or where it saw only sky.
    Outside,
    /// Inside the image, with something nearer in front (by more than 5% + 0.1 block).
    Hidden,
    Visible,
}

fn sight(traj: &Trajectory, src: usize, p: DVec3) -> Sight {
    let k = &traj.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let q = traj.poses[src].world_to_camera(p);
    if q.z <= k.near {
        return Sight::Outside;
    }
    let Some(uv) = k.project(q) else { return Sight::Outside };
    let (x, y) = (uv.x.round(), uv.y.round());
    if x < 0.0 || y < 0.0 || x >= w as f64 || y >= h as f64 {
        return Sight::Outside;
    }
    match traj.depth(src)[y as usize * w + x as usize] {
        0 => Sight::Outside,
        seen if q.z > seen as f64 * DEPTH_UNIT_M * 1.05 + 0.1 => Sight::Hidden,
        _ => Sight::Visible,
    }
}

/// Share of `points` inside frame `src`'s image that are hidden there.
pub fn occluded_share(traj: &Trajectory, src: usize, points: &[DVec3]) -> Option<f64> {
    let (mut inside, mut hidden) = (0usize, 0usize);
    for &p in points {
        match sight(traj, src, p) {
            Sight::Outside => {}
            Sight::Hidden => {
                inside += 1;
                hidden += 1;
            }
            Sight::Visible => inside += 1,
        }
    }
    (inside > 0).then(|| hidden as f64 / inside as f64)
}

/// The features of each of `targets` (increasing frame indices).
pub fn features(traj: &Trajectory, targets: &[usize]) -> Result<Vec<TargetFeatures>, SuiteError> {
    let frusta = traj.frusta()?;
    let best = Policy::best_overlap();
    let mut store = FrameMemory::new();
    let mut out = Vec::with_capacity(targets.len());
    let mut next = targets.iter().peekable();
    let explored: Vec<usize> = (0..traj.len()).filter(|&i| traj.phase[i] != RETURN_PHASE).collect();
    for (t, frustum) in frusta.iter().enumerate() {
        if next.peek() == Some(&&t) {
            next.next();
            let points = surface_points(traj, t, 1);
            let n = points.len().max(1) as f64;
            let recent = t.saturating_sub(RECENT_FRAMES);
            let mut seen: Vec<bool> = points.iter().map(|&p| (recent..t).any(|i| sight(traj, i, p) == Sight::Visible)).collect();
            let recent_visible = seen.iter().filter(|&&s| s).count() as f64 / n;
            // Older frames, best first by how much of the rest they show.
            let mut gains: Vec<(usize, Vec<usize>)> = (0..recent)
                .filter(|&i| frusta[i].aabb().intersects(frustum.aabb()))
                .map(|i| (i, (0..points.len()).filter(|&j| !seen[j] && sight(traj, i, points[j]) == Sight::Visible).collect::<Vec<_>>()))
                .filter(|(_, g)| !g.is_empty())
                .collect();
            gains.sort_by_key(|(i, g)| (std::cmp::Reverse(g.len()), std::cmp::Reverse(*i)));
            let memory_age = gains.first().map(|(i, _)| t - i);
            for (_, g) in &gains {
                for &j in g {
                    seen[j] = true;
                }
            }
            let memory_only = seen.iter().filter(|&&s| s).count() as f64 / n - recent_visible;
            let (plan, _) = store.select(&best, frustum, None);
            // Frame 0 has no stored frame to be hidden in.
            let src = plan.selected().next().map(|(_, f)| f.id as usize).or(t.checked_sub(1));
            let here = traj.poses[t];
            let revisit_angle_deg = explored
                .iter()
                .filter(|&&i| i < t && traj.poses[i].position().distance(here.position()) <= REVISIT_RADIUS)
                .map(|&i| traj.poses[i].forward().angle_between(here.forward()).to_degrees())
                .reduce(f64::min);
            let explored = explored_share(traj, &frusta, t, EXPLORED_STRIDE);
            out.push(TargetFeatures { t, recent_visible, memory_only, memory_age, occluded: src.and_then(|s| occluded_share(traj, s, &points)), revisit_angle_deg, explored });
        }
        if next.peek().is_none() {
            break;
        }
        store
            .insert(MemoryFrame { id: t as u64, time: t as u64, frustum: frustum.clone() })
            .expect("frame ids are new and increasing");
    }
    Ok(out)
}

/// Share of frame `t`'s surface points (every `stride`-th row and column)
/// that at least one earlier exploration frame shows; 0 when it has none.
/// Every frame of a rollout's return leg is generated, so this is what an
/// observed memory could bring back.
pub fn explored_share(traj: &Trajectory, frusta: &[memory::Frustum], t: usize, stride: usize) -> f64 {
    let points = surface_points(traj, t, stride);
    if points.is_empty() {
        return 0.0;
    }
    let explored: Vec<usize> = (0..t).filter(|&i| traj.phase[i] != RETURN_PHASE && frusta[i].aabb().intersects(frusta[t].aabb())).collect();
    let seen = points.iter().filter(|&&p| explored.iter().any(|&i| sight(traj, i, p) == Sight::Visible)).count();
    seen as f64 / points.len() as f64
}

/// Every frame's share of its view that only frames older than the
/// [`RECENT_FRAMES`] newest show: [`TargetFeatures::memory_only`] for all
/// frames of a trajectory (0 for frame 0), from the surface points on every
/// `stride`-th row and column. Training uses it to find the targets where
/// memory beyond recency can help (`worldpack plan --memory-need`).
pub fn memory_need(traj: &Trajectory, stride: usize) -> Result<Vec<f32>, SuiteError> {
    let frusta = traj.frusta()?;
    let mut need = vec![0.0f32; traj.len()];
    for t in 1..traj.len() {
        let points = surface_points(traj, t, stride);
        if points.is_empty() {
            continue;
        }
        let recent = t.saturating_sub(RECENT_FRAMES);
        let older: Vec<usize> = (0..recent).filter(|&i| frusta[i].aabb().intersects(frusta[t].aabb())).collect();
        let only_older = points
            .iter()
            .filter(|&&p| {
                !(recent..t).any(|i| sight(traj, i, p) == Sight::Visible) && older.iter().any(|&i| sight(traj, i, p) == Sight::Visible)
            })
            .count();
        need[t] = only_older as f32 / points.len() as f32;
    }
    Ok(need)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::suite::Entry;
    use glam::DMat3;
    use memory::{Intrinsics, Pose};

    /// Frames 0–1 face a wall 5 blocks ahead (+z), frames 2–5 face the other
    /// way into open sky, frame 6 (the return) faces the wall again from the
    /// same spot. `near_wall_in_1` puts something 2 blocks ahead in frame 1.
    fn turn_away_and_back(near_wall_in_1: bool) -> Trajectory {
        let k = Intrinsics::from_fov(60.0, None, 16, 16).unwrap().with_range(0.1, 30.0).unwrap();
        let n = 16 * 16;
        let (ahead, behind) = (Pose::from_position(glam::DVec3::ZERO), Pose::new(DMat3::from_rotation_y(std::f64::consts::PI), glam::DVec3::ZERO).unwrap());
        let poses = vec![ahead, ahead, behind, behind, behind, behind, ahead];
        let mut depth_mm = Vec::new();
        for (t, p) in poses.iter().enumerate() {
            let d = if p.forward().z > 0.0 { if near_wall_in_1 && t == 1 { 2000 } else { 5000 } } else { 0 };
            depth_mm.extend(std::iter::repeat_n(d as u16, n));
        }
        let entry = Entry { dir: "turn".into(), task: "aba".into(), range: 5, frames: 7, returning_point: 6 };
        Trajectory { entry, intrinsics: k, rgb: vec![0; 7 * n * 3], depth_mm, has_depth: true, poses, phase: vec![0, 0, 0, 0, 0, 0, RETURN_PHASE], actions: vec![[0.0; 7]; 7] }
    }

    #[test]
    fn a_view_only_old_frames_show_is_memory_dependent() {
        let f = features(&turn_away_and_back(false), &[6]).unwrap()[0];
        assert_eq!(f.recent_visible, 0.0, "the 4 newest frames face away");
        assert_eq!(f.memory_only, 1.0);
        assert_eq!(f.memory_age, Some(5), "frame 1 shows all of it and is the newest that does");
        assert_eq!(f.occluded, Some(0.0));
        assert_eq!(f.revisit_angle_deg, Some(0.0));
        assert!(Stratum::MemoryDependent.contains(&f) && !Stratum::LongHorizon.contains(&f) && !Stratum::OppositeRevisit.contains(&f));
        // Frames 0–1 (exploration) saw the whole wall.
        assert_eq!(f.explored, 1.0);
        assert!(Stratum::Revisit.contains(&f));
    }

    #[test]
    fn a_nearer_surface_in_the_remembered_frame_hides_the_view() {
        let f = features(&turn_away_and_back(true), &[6]).unwrap()[0];
        // Frame 1 (the best-overlap frame: same pose as the target, newest) saw
        // something at 2 blocks where the target sees the wall at 5: all hidden.
        assert_eq!(f.occluded, Some(1.0));
        assert!(Stratum::Occluded.contains(&f));
        // Only frame 0 still shows the wall.
        assert_eq!(f.memory_age, Some(6));
        assert_eq!(f.memory_only, 1.0);
    }

    #[test]
    fn a_view_no_exploration_frame_showed_is_not_a_revisit() {
        let mut traj = turn_away_and_back(false);
        // Frames 0–1 face the wall but belong to the return leg now: nothing explored shows it.
        traj.phase = vec![RETURN_PHASE; 7];
        let f = features(&traj, &[6]).unwrap()[0];
        assert_eq!(f.explored, 0.0);
        assert!(!Stratum::Revisit.contains(&f));
        // Half the wall hidden behind a nearer surface in frame 1 (the only explored frame facing it)
        // leaves half of the view explored.
        let mut traj = turn_away_and_back(true);
        traj.phase[0] = RETURN_PHASE;
        let n = 16 * 16;
        for d in &mut traj.depth_mm[n..n + n / 2] {
            *d = 5000;
        }
        let share = explored_share(&traj, &traj.frusta().unwrap(), 6, 1);
        assert_eq!(share, 0.5);
    }

    #[test]
    fn memory_need_matches_the_features_on_every_frame() {
        for near in [false, true] {
            let traj = turn_away_and_back(near);
            let all: Vec<usize> = (0..traj.len()).collect();
            let want: Vec<f32> = features(&traj, &all).unwrap().iter().map(|f| f.memory_only as f32).collect();
            assert_eq!(memory_need(&traj, 1).unwrap(), want);
            // Only the return, facing the wall last seen 5 frames back, needs memory.
            assert_eq!(memory_need(&traj, 3).unwrap(), vec![0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        }
    }
}
