//! `FrameMemory`: every stored frame, indexed for selection that stays fast
//! as the history grows.
//!
//! Frames arrive one at a time into an `rstar` R-tree over their frustum
//! bounding boxes (no rebuild). Score-ranked selection then
//! 1. asks the tree for the frames whose box meets the target's box — every
//!    other frame has overlap exactly 0 and is never touched;
//! 2. evaluates those candidates newest first, keeping the best `n` in a heap,
//!    and stops at the first candidate whose best possible score
//!    `w_o − w_t·Δt_i` falls below the current n-th best `s*` (every older
//!    one is worse still); the previous plan's frames are evaluated first so
//!    that `s*` starts high;
//!    with the exact estimator it also skips a frame when a bound in pose
//!    space rules it out: frames are grouped by camera cell (6 blocks) and
//!    view direction (20° of yaw and of pitch), each group keeps a polytope
//!    that contains all its frusta, and `Vol(V_t ∩ group)/Vol(V_t)` (one clip
//!    per group and query) bounds every member's overlap — the bound that
//!    prunes loops, where every box meets the target's;
//! 3. fills the remaining slots with zero-overlap frames, newest first, whose
//!    score `−w_t·Δt_i` is known without any geometry.
//!
//! The result is exactly the brute-force plan of [`crate::policy::select`]
//! (tested), because only frames that provably cannot enter are skipped.

use std::collections::{BinaryHeap, HashMap, HashSet};

use glam::DVec3;
use rstar::{AABB, RTree, RTreeObject};

use crate::error::InputError;
use crate::frustum::{Frustum, Plane};
use crate::overlap::{Estimator, Polytope};
use crate::policy::{ContextPlan, MemoryFrame, Policy, Ranking, SelectedFrame, age, rank_order, select_among};

struct Entry {
    slot: usize,
    envelope: AABB<[f64; 3]>,
}

impl RTreeObject for Entry {
    type Envelope = AABB<[f64; 3]>;

    fn envelope(&self) -> Self::Envelope {
        self.envelope
    }
}

fn envelope(f: &Frustum) -> AABB<[f64; 3]> {
    AABB::from_corners(f.aabb().min.to_array(), f.aabb().max.to_array())
}

/// What one selection cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SelectionStats {
    /// Frames whose box met the target's box.
    pub box_candidates: usize,
    /// Overlap evaluations actually computed.
    pub overlap_evaluations: usize,
    /// Pose-space group bounds computed (one clip each).
    pub group_bounds: usize,
}

/// Side of a group's camera cell, in world units.
const GROUP_CELL: f64 = 6.0;
/// Width of a group's yaw and pitch bins, degrees.
const GROUP_ANGLE_DEG: f64 = 20.0;
/// Added to every group bound so that rounding in the clipper can never make
/// a member's computed overlap exceed its group's bound.
const BOUND_MARGIN: f64 = 1e-6;
/// Smaller groups are cheaper to evaluate member by member than to bound.
const MIN_GROUP_FOR_BOUND: usize = 3;

/// Frames with nearby cameras looking in similar directions, and a polytope
/// containing all their frusta: half-spaces with the first member's six
/// plane normals and the six axis directions, each pushed out to the
/// farthest corner of any member.
struct Group {
    planes: Vec<Plane>,
    members: usize,
}

impl Group {
    fn new(first: &Frustum) -> Group {
        let axes = [DVec3::X, DVec3::NEG_X, DVec3::Y, DVec3::NEG_Y, DVec3::Z, DVec3::NEG_Z];
        let normals = first.planes().iter().map(|p| p.normal).chain(axes);
        Group { planes: normals.map(|normal| Plane { normal, offset: f64::NEG_INFINITY }).collect(), members: 0 }
    }

    fn add(&mut self, f: &Frustum) {
        self.members += 1;
        for plane in &mut self.planes {
            for c in f.corners() {
                plane.offset = plane.offset.max(plane.normal.dot(*c));
            }
        }
    }

    /// An upper bound on the overlap of `target` with any member.
    fn overlap_bound(&self, target: &Frustum) -> f64 {
        let mut poly = Polytope::from_frustum(target);
        for plane in &self.planes {
            poly.clip(plane, 0.0);
            if poly.is_empty() {
                return BOUND_MARGIN;
            }
        }
        (poly.volume() / target.volume()).clamp(0.0, 1.0) + BOUND_MARGIN
    }
}

fn group_key(f: &Frustum) -> [i64; 5] {
    let p = f.pose().position() / GROUP_CELL;
    let fwd = f.pose().forward();
    let yaw = fwd.x.atan2(fwd.z).to_degrees();
    let pitch = fwd.y.clamp(-1.0, 1.0).asin().to_degrees();
    [p.x.floor() as i64, p.y.floor() as i64, p.z.floor() as i64, (yaw / GROUP_ANGLE_DEG).floor() as i64, (pitch / GROUP_ANGLE_DEG).floor() as i64]
}

#[derive(Default)]
pub struct FrameMemory {
    frames: Vec<MemoryFrame>,
    /// Slots ordered oldest to newest by `(time, id)`.
    by_recency: Vec<usize>,
    slot_of: HashMap<u64, usize>,
    tree: RTree<Entry>,
    groups: Vec<Group>,
    group_of: Vec<usize>,
    group_index: HashMap<[i64; 5], usize>,
}

impl FrameMemory {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    pub fn get(&self, id: u64) -> Option<&MemoryFrame> {
        self.slot_of.get(&id).map(|&s| &self.frames[s])
    }

    /// All frames in insertion order.
    pub fn frames(&self) -> &[MemoryFrame] {
        &self.frames
    }

    /// Adds a frame. Ids must be unique; times may arrive out of order.
    pub fn insert(&mut self, frame: MemoryFrame) -> Result<(), InputError> {
        if self.slot_of.contains_key(&frame.id) {
            return Err(InputError::invalid("id", format!("a frame with id {} is already stored", frame.id)));
        }
        let slot = self.frames.len();
        let key = (frame.time, frame.id);
        // Appending is the common case; a late frame is placed by binary search.
        let pos = self.by_recency.partition_point(|&s| (self.frames[s].time, self.frames[s].id) < key);
        self.by_recency.insert(pos, slot);
        self.slot_of.insert(frame.id, slot);
        self.tree.insert(Entry { slot, envelope: envelope(&frame.frustum) });
        let next_group = self.groups.len();
        let g = *self.group_index.entry(group_key(&frame.frustum)).or_insert(next_group);
        if g == next_group {
            self.groups.push(Group::new(&frame.frustum));
        }
        self.groups[g].add(&frame.frustum);
        self.group_of.push(g);
        self.frames.push(frame);
        Ok(())
    }

    /// The plan for `target`, exactly as brute force would choose it.
    /// `previous` (the last plan for a nearby target) only speeds things up.
    pub fn select(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, SelectionStats) {
        let n = policy.packing.slots();
        match policy.ranking {
            Ranking::Score => self.select_by_score(policy, target, previous),
            Ranking::Recency => {
                // The newest n frames are all that recency can pick.
                let newest: Vec<&MemoryFrame> = self.by_recency.iter().rev().take(n).map(|&s| &self.frames[s]).collect();
                let stats = SelectionStats { overlap_evaluations: newest.len(), ..SelectionStats::default() };
                (select_among(policy, target, &newest), stats)
            }
            Ranking::GreedyCoverage => {
                // Coverage changes every round; scored by brute force.
                let all: Vec<&MemoryFrame> = self.frames.iter().collect();
                let stats =
                    SelectionStats { box_candidates: all.len(), overlap_evaluations: all.len() * n, ..SelectionStats::default() };
                (select_among(policy, target, &all), stats)
            }
        }
    }

    fn select_by_score(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, SelectionStats) {
        let mut stats = SelectionStats::default();
        let Some(&newest) = self.by_recency.last() else {
            return (ContextPlan::from_ranked(&policy.packing, &[]), stats);
        };
        let t_now = self.frames[newest].time;
        let pinned = policy.keep_last.then_some(newest);
        let n = policy.packing.slots() - pinned.is_some() as usize;
        let samples = policy.estimator.samples(target);
        let overlap_of = |f: &MemoryFrame| match &samples {
            Some(s) => s.overlap(&f.frustum),
            None => crate::overlap::exact_overlap(target, &f.frustum),
        };
        let describe = |slot: usize, overlap: f64| {
            let f = &self.frames[slot];
            SelectedFrame { id: f.id, time: f.time, overlap, score: policy.weights.score(overlap, age(f.time, t_now)) }
        };

        // WorldMem's angular test has no range: a box cannot rule a frame out.
        let mut candidates: Vec<usize> = if matches!(policy.estimator, Estimator::WorldMem(_)) {
            self.by_recency.clone()
        } else {
            self.tree.locate_in_envelope_intersecting(envelope(target)).map(|e| e.slot).collect()
        };
        candidates.retain(|&s| Some(s) != pinned);
        stats.box_candidates = candidates.len();
        let recency_key = |s: &usize| (self.frames[*s].time, self.frames[*s].id);
        candidates.sort_unstable_by_key(|s| std::cmp::Reverse(recency_key(s)));

        // Group bounds hold for the exact overlap only (an estimate may
        // exceed them), and only rank correctly while the score grows with it.
        let mut group_bounds: Option<HashMap<usize, f64>> =
            (matches!(policy.estimator, Estimator::Exact) && policy.weights.overlap > 0.0).then(HashMap::new);
        let mut best = TopN::new(n);
        let mut done: HashSet<usize> = HashSet::new();
        let is_candidate: HashSet<usize> = candidates.iter().copied().collect();
        if n > 0 {
            // Warm start: last plan's frames that are still candidates.
            for id in previous.iter().flat_map(|p| p.selected().map(|(_, f)| f.id)) {
                if let Some(&slot) = self.slot_of.get(&id) {
                    if is_candidate.contains(&slot) && done.insert(slot) {
                        stats.overlap_evaluations += 1;
                        best.push(describe(slot, overlap_of(&self.frames[slot])));
                    }
                }
            }
            for &slot in &candidates {
                if done.contains(&slot) {
                    continue;
                }
                let frame_age = age(self.frames[slot].time, t_now);
                if best.cannot_admit(policy.weights.score(1.0, frame_age)) {
                    break; // older candidates have lower bounds still
                }
                let g = self.group_of[slot];
                if let Some(bounds) = group_bounds.as_mut().filter(|_| self.groups[g].members >= MIN_GROUP_FOR_BOUND) {
                    let bound = *bounds.entry(g).or_insert_with(|| {
                        stats.group_bounds += 1;
                        self.groups[g].overlap_bound(target)
                    });
                    if best.cannot_admit(policy.weights.score(bound, frame_age)) {
                        continue;
                    }
                }
                done.insert(slot);
                stats.overlap_evaluations += 1;
                best.push(describe(slot, overlap_of(&self.frames[slot])));
            }
            // Zero-overlap frames: scores need no geometry, newest is best.
            for &slot in self.by_recency.iter().rev() {
                if Some(slot) == pinned || is_candidate.contains(&slot) {
                    continue;
                }
                let entry = describe(slot, 0.0);
                if best.cannot_admit(entry.score) {
                    break;
                }
                best.push(entry);
            }
        }
        let mut ranked = best.into_sorted();
        if let Some(slot) = pinned {
            stats.overlap_evaluations += 1;
            ranked.insert(0, describe(slot, overlap_of(&self.frames[slot])));
        }
        (ContextPlan::from_ranked(&policy.packing, &ranked), stats)
    }
}

/// The best `n` entries seen so far; the root of the heap is the worst kept.
struct TopN {
    n: usize,
    heap: BinaryHeap<Ranked>,
}

/// Orders entries so that the heap's maximum is the *worst* by [`rank_order`].
struct Ranked(SelectedFrame);

impl PartialEq for Ranked {
    fn eq(&self, other: &Self) -> bool {
        rank_order(&self.0, &other.0).is_eq()
    }
}
impl Eq for Ranked {}
impl PartialOrd for Ranked {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Ranked {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        rank_order(&self.0, &other.0)
    }
}

impl TopN {
    fn new(n: usize) -> Self {
        TopN { n, heap: BinaryHeap::with_capacity(n + 1) }
    }

    /// True when the heap is full and a score of `upper` would rank below its
    /// worst entry even if it won every tie-break. Equal scores are admitted,
    /// since the tie-break may favour them.
    fn cannot_admit(&self, upper: f64) -> bool {
        self.heap.len() == self.n && self.heap.peek().is_some_and(|worst| upper < worst.0.score)
    }

    fn push(&mut self, entry: SelectedFrame) {
        self.heap.push(Ranked(entry));
        if self.heap.len() > self.n {
            self.heap.pop();
        }
    }

    fn into_sorted(self) -> Vec<SelectedFrame> {
        let mut v: Vec<SelectedFrame> = self.heap.into_iter().map(|r| r.0).collect();
        v.sort_by(rank_order);
        v
    }
}
