//! A live session: its policy, its history of frames (runs shared with
//! forks, then its own: `history`), and (in the synthetic world) the player
//! for the motion model. A [`Timeline`] reads a session's history, or that
//! history with an imagined rollout's frames on top, for the step.

use std::collections::HashMap;
use std::sync::Arc;

use memory::covisibility::{CoVisibility, DepthGrid};
use memory::{ContextPlan, Frustum, Intrinsics, Policy, PolicySpec, Pose, Selection};
use model::WarpSource;
use model::warp::coarse_depth;
use world::World;
use motion::{Action, Kinematic, MotionModel};
use world::agent::PlayerState;

pub use crate::history::{DepthFrame, Frame, History, Segment};
use crate::refusal::EngineError;
use crate::store::{FrameMeta, FrameRecord, SessionRecord};

pub struct Session {
    pub id: u64,
    pub record: SessionRecord,
    pub policy: Policy,
    pub last_plan: Option<ContextPlan>,
    pub world: Option<Arc<World>>,
    /// Set by a delete; requests that were queued on the session see it and answer 404.
    pub deleted: bool,
    /// Runs frozen at fork points, oldest first, shared with the sessions
    /// forked there (and with the session this one was forked from).
    shared: Vec<Arc<Segment>>,
    /// The frames since the newest fork point: this session's alone.
    own: Segment,
}

/// A stored frame's `source` when a step made it (else `observed`).
pub const GENERATED: &str = "generated";
pub const OBSERVED: &str = "observed";

pub fn policy_of(spec: &serde_json::Value) -> Result<Policy, EngineError> {
    let spec: PolicySpec = serde_path_to_error::deserialize(spec.clone())
        .map_err(|e| EngineError::invalid(format!("policy.{}", e.path()).trim_end_matches(".").to_string(), e.inner().to_string()))?;
    Ok(spec.into_policy().map_err(|e| e.within("policy"))?)
}

fn pool_depth(depth_mm: &[u16], k: &Intrinsics, cells: u32) -> Result<DepthGrid, EngineError> {
    coarse_depth(depth_mm, k, cells).map_err(|e| EngineError::invalid("covisibility.cells", e.to_string()))
}

pub fn pose_of(meta: &FrameMeta) -> Result<Pose, EngineError> {
    Ok(Pose::from_matrix_rows(meta.c2w)?)
}

impl Session {
    /// A session whose history starts with `shared` (a fork's inherited runs; empty for a new session).
    pub fn new(id: u64, record: SessionRecord, world: Option<Arc<World>>, shared: Vec<Arc<Segment>>) -> Result<Session, EngineError> {
        let policy = policy_of(&record.policy)?;
        let start = shared.last().map_or(0, |s| s.end());
        Ok(Session { id, record, policy, last_plan: None, world, deleted: false, shared, own: Segment::starting_at(start) })
    }

    /// Rebuilds a session from its stored record and frames (server start,
    /// or a session another server made on a shared store).
    pub fn restore(id: u64, record: SessionRecord, frames: Vec<FrameRecord>, world: Option<Arc<World>>) -> Result<Session, EngineError> {
        let mut s = Session::new(id, record, world, Vec::new())?;
        s.append_stored(frames)?;
        Ok(s)
    }

    /// Indexes stored frames that follow the ones indexed already (frames
    /// another server wrote to a shared store, or all of them at a restore).
    pub fn append_stored(&mut self, frames: Vec<FrameRecord>) -> Result<(), EngineError> {
        for f in frames {
            let index = self.len();
            let generated = f.meta.source == GENERATED;
            self.push(f.meta.time, pose_of(&f.meta)?, f.latent, f.meta.player.map(player_from), generated)?;
            if !f.depth_png16.is_empty() {
                // Both were checked when they arrived; a stored frame that no longer decodes is the store's fault.
                let (rgb, w, h) = world::picture::decode_rgb(&f.png).map_err(EngineError::internal)?;
                let (depth, _, _) = world::picture::decode_depth_png16(&f.depth_png16).map_err(EngineError::internal)?;
                self.add_depth(index, rgb, w, h, depth)?;
            }
        }
        Ok(())
    }

    /// Every frame, shared and own, read as one.
    pub fn history(&self) -> History<'_> {
        History::new(self.shared.iter().map(|s| &**s).chain([&self.own]).collect())
    }

    /// The history with the session's policy, camera and world, as a step reads it.
    pub fn timeline(&self) -> Timeline<'_> {
        Timeline { session: self, history: self.history() }
    }

    /// Frames in the session (shared ones included): the next frame's index.
    pub fn len(&self) -> u64 {
        self.own.end()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.record.intrinsics
    }

    pub fn frustum(&self, pose: Pose) -> Result<Frustum, EngineError> {
        Ok(Frustum::new(pose, self.record.intrinsics)?)
    }

    /// Adds a committed frame to the in-memory index.
    pub fn push(&mut self, time: u64, pose: Pose, latent: Vec<f32>, player: Option<PlayerState>, generated: bool) -> Result<(), EngineError> {
        let frustum = self.frustum(pose)?;
        self.own.push(frustum, Frame { pose, time, latent, player, generated })
    }

    /// Indexes frame `index`'s depth as a warp source. Frames not at the
    /// session's camera size are left out (the warp needs its intrinsics).
    pub fn add_depth(&mut self, index: u64, rgb: Vec<u8>, width: u32, height: u32, depth_mm: Vec<u16>) -> Result<(), EngineError> {
        let k = self.record.intrinsics;
        if (width, height) != (k.width, k.height) {
            return Ok(());
        }
        let pose = self.history().frame(index).map(|f| f.pose).ok_or_else(|| EngineError::internal(format!("depth for frame {index}, which is not indexed")))?;
        let grid = pool_depth(&depth_mm, &k, CoVisibility::default().cells)?;
        self.own.add_depth(index, self.frustum(pose)?, DepthFrame::new(rgb, depth_mm), grid)
    }

    /// `policy`'s plan for `target` over the session's frames (see [`Timeline::plan`]).
    pub fn plan(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> Result<Selection, EngineError> {
        self.timeline().plan(policy, target, previous)
    }

    /// Freezes the frames since the last fork point into a run shared from
    /// now on (moved behind an `Arc`, not copied); a no-op when there are none.
    pub fn freeze(&mut self) {
        if !self.own.is_empty() {
            let next = Segment::starting_at(self.len());
            let own = std::mem::replace(&mut self.own, next);
            self.shared.push(Arc::new(own));
        }
    }

    /// A session `id` (stored as `record`) whose history is this one's up to
    /// now, shared: the frames since the last fork point are frozen, and both
    /// sessions write their next frames to runs of their own.
    pub fn fork(&mut self, id: u64, record: SessionRecord) -> Result<Session, EngineError> {
        self.freeze();
        let mut fork = Session::new(id, record, self.world.clone(), self.shared.clone())?;
        fork.last_plan = self.last_plan.clone();
        Ok(fork)
    }

    /// The frozen runs that hold exactly frames `0..end`, if a fork point is
    /// at `end` (what a fork made there shares).
    pub fn shared_until(&self, end: u64) -> Option<Vec<Arc<Segment>>> {
        let n = self.shared.partition_point(|s| s.end() <= end);
        (n > 0 && self.shared[n - 1].end() == end).then(|| self.shared[..n].to_vec())
    }
}

/// Rebuilds stored sessions (ordered by id, so a fork comes after the session
/// it was forked from) with their forks sharing their runs, as they did
/// before the restart: each session's frames are frozen at its forks' points.
/// `own_frames(id, start)` reads a session's own stored frames from `start` on.
pub fn restore_all(
    records: Vec<(u64, SessionRecord)>,
    mut own_frames: impl FnMut(u64, u64) -> Result<Vec<FrameRecord>, EngineError>,
    world_of: impl Fn(u64) -> Arc<World>,
) -> Result<Vec<Session>, EngineError> {
    let mut fork_points: HashMap<u64, Vec<u64>> = HashMap::new();
    for (_, r) in &records {
        if let Some(f) = r.fork {
            fork_points.entry(f.parent).or_default().push(f.frames);
        }
    }
    let mut done: HashMap<u64, Session> = HashMap::new();
    let mut order = Vec::with_capacity(records.len());
    for (id, record) in records {
        let restoring = |e: EngineError| EngineError::internal(format!("restoring session {id}: {}", e.message));
        let shared = match record.fork {
            None => Vec::new(),
            Some(f) => done
                .get(&f.parent)
                .and_then(|p| p.shared_until(f.frames))
                .ok_or_else(|| EngineError::internal(format!("restoring session {id}: session {} it was forked from, at frame {}, is not stored", f.parent, f.frames)))?,
        };
        let world = record.world_seed.map(&world_of);
        let mut s = Session::new(id, record, world, shared).map_err(restoring)?;
        let mut frames = own_frames(id, s.len()).map_err(restoring)?.into_iter();
        let mut points = fork_points.remove(&id).unwrap_or_default();
        points.sort_unstable();
        for p in points {
            let take = p.saturating_sub(s.len()) as usize;
            s.append_stored(frames.by_ref().take(take).collect()).map_err(restoring)?;
            s.freeze();
        }
        s.append_stored(frames.collect()).map_err(restoring)?;
        order.push(id);
        done.insert(id, s);
    }
    Ok(order.into_iter().filter_map(|id| done.remove(&id)).collect())
}

/// A session's history as a step reads it: the session's own, or with an
/// imagined rollout's frames on top ([`Timeline::with`]).
pub struct Timeline<'a> {
    pub session: &'a Session,
    pub history: History<'a>,
}

/// Stored frames' coarse depth at a co-visibility grid: the pooled grids
/// kept at the default size, or pooled now at another.
enum Grids<'a> {
    Kept(&'a History<'a>),
    Pooled(HashMap<u64, DepthGrid>),
}

impl Grids<'_> {
    fn get(&self, index: u64) -> Option<&DepthGrid> {
        match self {
            Grids::Kept(h) => h.depth_grid(index),
            Grids::Pooled(m) => m.get(&index),
        }
    }
}

impl<'a> Timeline<'a> {
    /// This timeline with `top`'s frames after its own.
    pub fn with(&self, top: &'a Segment) -> Timeline<'a> {
        Timeline { session: self.session, history: self.history.with(top) }
    }

    /// Every observed frame's depth pooled to `cells` columns (metres;
    /// memory::covisibility), by frame index.
    fn depth_grids(&self, cells: u32) -> Result<Grids<'_>, EngineError> {
        if cells == CoVisibility::default().cells {
            return Ok(Grids::Kept(&self.history));
        }
        let k = self.session.intrinsics();
        Ok(Grids::Pooled(self.history.depth_frames().map(|(id, d)| Ok((id, pool_depth(&d.depth_mm, k, cells)?))).collect::<Result<_, EngineError>>()?))
    }

    /// `policy`'s plan for `target` (memory::selection) over every frame of
    /// the timeline: co-visibility reads the observed frames' depth at the policy's grid.
    pub fn plan(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> Result<Selection, EngineError> {
        self.plan_in(&self.history.memory(), policy, target, previous)
    }

    fn plan_in(&self, memory: &memory::Stack, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> Result<Selection, EngineError> {
        let grids = match &policy.covisibility {
            Some(c) => Some(self.depth_grids(c.cells)?),
            None => None,
        };
        Ok(memory.plan(policy, target, previous, |id| grids.as_ref().and_then(|g| g.get(id)))?)
    }

    /// The indices of the `count` observed frames with depth that overlap
    /// `target` most (or, when the session's policy asks for co-visibility,
    /// that saw most of its expected surface unoccluded), best first (none
    /// when no frame with depth sees it).
    pub fn warp_frames(&self, target: &Frustum, count: usize) -> Result<Vec<u64>, EngineError> {
        let best = Policy { covisibility: self.session.policy.covisibility, ..Policy::best_overlap_frames(count) };
        let plan = self.plan_in(&self.history.depth_memory(), &best, target, None)?.plan;
        Ok(plan.selected().map(|(_, f)| f.id).filter(|&id| self.history.depth_frame(id).is_some()).collect())
    }

    /// Frames `ids` (observed, with depth) with their poses, in that order; ids without depth are left out.
    pub fn depth_frames_of<'i>(&'i self, ids: &'i [u64]) -> impl Iterator<Item = (&'a DepthFrame, &'a Pose)> + 'i {
        ids.iter().filter_map(|&id| Some((self.history.depth_frame(id)?, &self.history.frame(id)?.pose)))
    }

    /// Frames `ids` (observed, with depth) ready to warp at the session's size, in that order.
    pub fn warp_sources_of(&self, ids: &[u64]) -> Vec<WarpSource<'a>> {
        let intrinsics = self.session.intrinsics();
        self.depth_frames_of(ids).map(|(d, pose)| WarpSource { rgb: &d.rgb, depth_mm: &d.depth_mm, pose, intrinsics }).collect()
    }

    /// The pose after `action`: the world's physics in a synthetic session,
    /// else the kinematic model.
    pub fn motion(&self, action: &Action) -> Result<(Pose, Option<PlayerState>), EngineError> {
        let last = self.history.last().ok_or_else(|| EngineError::internal("session without frames"))?;
        match (&self.session.world, last.player) {
            (Some(world), Some(player)) => {
                let physics = world::agent::Physics { world };
                let next = physics.step(&player, action);
                Ok((physics.camera(&next), Some(next)))
            }
            _ => Ok((Kinematic.step(&last.pose, action), None)),
        }
    }
}

pub fn player_from(p: [f64; 5]) -> PlayerState {
    PlayerState { feet: [p[0], p[1], p[2]], yaw_deg: p[3], pitch_deg: p[4] }
}

pub fn player_to(p: &PlayerState) -> [f64; 5] {
    [p.feet[0], p.feet[1], p.feet[2], p.yaw_deg, p.pitch_deg]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::ForkOf;

    fn record(fork: Option<ForkOf>) -> SessionRecord {
        let intrinsics = Intrinsics::from_fov(70.0, None, 8, 8).unwrap();
        SessionRecord { policy: serde_json::json!({ "kind": "worldpack" }), intrinsics, world_seed: None, tenant: None, fork }
    }

    fn frame(x: f64) -> FrameRecord {
        let c2w = [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        FrameRecord { meta: FrameMeta { c2w, time: x as u64, source: OBSERVED.into(), action: None, player: None }, latent: vec![x as f32], png: Vec::new(), depth_png16: Vec::new() }
    }

    fn shares(a: &Session, b: &Session) -> usize {
        a.shared.iter().filter(|s| b.shared.iter().any(|t| Arc::ptr_eq(s, t))).count()
    }

    /// A fork holds its parent's runs, not copies; a restart rebuilds the same sharing.
    #[test]
    fn forks_share_runs_in_memory_and_after_a_restore() {
        let mut parent = Session::restore(1, record(None), (0..5).map(|x| frame(x as f64)).collect(), None).unwrap();
        let mut child = parent.fork(2, record(Some(ForkOf { parent: 1, frames: 5 }))).unwrap();
        assert_eq!((child.len(), shares(&parent, &child)), (5, 1));
        child.append_stored(vec![frame(5.0), frame(6.0)]).unwrap();
        parent.append_stored(vec![frame(50.0)]).unwrap();
        let grandchild = child.fork(3, record(Some(ForkOf { parent: 2, frames: 7 }))).unwrap();
        assert_eq!(shares(&child, &grandchild), 2, "the parent's run and the fork's own");
        assert_eq!(grandchild.history().frame(6).map(|f| f.latent[0]), Some(6.0));
        assert_eq!(parent.history().frame(5).map(|f| f.latent[0]), Some(50.0), "the parent's step is its own");

        // The same three stored: their own rows, read back with the links.
        let own: HashMap<u64, Vec<FrameRecord>> = HashMap::from([
            (1, vec![0.0, 1.0, 2.0, 3.0, 4.0, 50.0].into_iter().map(frame).collect()),
            (2, vec![frame(5.0), frame(6.0)]),
            (3, Vec::new()),
        ]);
        let records = vec![(1, record(None)), (2, record(Some(ForkOf { parent: 1, frames: 5 }))), (3, record(Some(ForkOf { parent: 2, frames: 7 })))];
        let restored = restore_all(records, |id, start| Ok(own[&id].iter().filter(|f| f.meta.time >= start).cloned().collect()), |_| unreachable!()).unwrap();
        let [p, c, g] = &restored[..] else { panic!("three sessions") };
        assert_eq!((p.len(), c.len(), g.len()), (6, 7, 7));
        assert_eq!((shares(p, c), shares(c, g)), (1, 2));
        let latents = |s: &Session| (0..s.len()).map(|i| s.history().frame(i).unwrap().latent[0]).collect::<Vec<_>>();
        assert_eq!(latents(g), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(latents(p), [0.0, 1.0, 2.0, 3.0, 4.0, 50.0]);

        // A link to a session that is not stored is named, not a panic.
        let orphan = restore_all(vec![(4, record(Some(ForkOf { parent: 9, frames: 1 })))], |_, _| Ok(Vec::new()), |_| unreachable!());
        assert!(orphan.err().unwrap().message.contains("session 9"));
    }
}
