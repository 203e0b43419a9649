//! `FrameMemory`: every stored frame, indexed for selection that stays fast
//! as the history grows.
//!
//! Frames are grouped as they arrive (no rebuild) by camera cell (6 blocks)
//! and view direction (20° of yaw and of pitch). Each group keeps its members
//! newest first, the box around their frusta, and a polytope that contains
//! them all; an `rstar` R-tree holds the group boxes. Score-ranked selection
//! 1. asks the tree for the groups whose box meets the target's box — every
//!    frame of every other group has overlap exactly 0 and is never touched;
//! 2. evaluates the previous plan's frames first, so that the `n`-th best
//!    score `s*` starts high, then visits the groups newest first, keeping
//!    the best `n` in a heap:
//!    - it stops at the first group whose newest member's best possible score
//!      `w_o − w_t·Δt` falls below `s*` (every later group is older still);
//!    - with the exact estimator it skips a whole group when
//!      `w_o·b − w_t·Δt` cannot reach `s*`, where `b = Vol(V_t ∩ hull)/Vol(V_t)`
//!      bounds every member's overlap — the bound that prunes loops, where
//!      every box meets the target's. A coarse group's bound (3× the cell and
//!      the bins) is taken at once; a group's own is taken lazily, when the
//!      group reaches the head of a best-first queue;
//!    - inside a group it stops at the first member that the same bound rules
//!      out (older members are worse still), and skips members whose own box
//!      misses the target's;
//! 3. fills the remaining slots with zero-overlap frames, newest first, whose
//!    score `−w_t·Δt_i` is known without any geometry.
//!
//! Every clip here, of a hull or of a member, stops as soon as the partly
//! clipped target proves the bound below what the frame (or the group's
//! newest member) would need to enter (`overlap::overlap_unless_below`).
//! Before any clip, the target's volume inside each of the two deepest
//! cutting planes, and inside both at once, in closed form, settles nine in
//! ten of them; a hull proved in closed form to reach the floor keeps a
//! closed-form bound and is not clipped at all.
//!
//! Rejected groups cost one clip and nothing per member. The result is
//! exactly the brute-force plan of [`crate::policy::select`] (tested),
//! because only frames that provably cannot enter are skipped.

use std::collections::{BinaryHeap, HashMap};

use glam::DVec3;
use rstar::{AABB, RTree, RTreeObject};

use crate::error::InputError;
use crate::frustum::{Aabb, Frustum, Plane};
use crate::overlap::{Estimator, Need, clipped_volume};
use crate::policy::{ContextPlan, MemoryFrame, Policy, Ranking, SelectedFrame, age, rank_order, select_by_brute_force_among};

/// A group's box in the R-tree.
#[derive(Clone, Copy, Debug, PartialEq)]
struct GroupBox {
    group: usize,
    envelope: AABB<[f64; 3]>,
}

impl RTreeObject for GroupBox {
    type Envelope = AABB<[f64; 3]>;

    fn envelope(&self) -> Self::Envelope {
        self.envelope
    }
}

fn envelope(b: &Aabb) -> AABB<[f64; 3]> {
    AABB::from_corners(b.min.to_array(), b.max.to_array())
}

/// What one selection cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SelectionStats {
    /// Frames in the groups whose box met the target's box: every frame
    /// the selection looked at.
    pub box_candidates: usize,
    /// Overlap evaluations actually computed.
    pub overlap_evaluations: usize,
    /// Pose-space group bounds computed (one clip each).
    pub group_bounds: usize,
    /// Of the overlap evaluations, those stopped part-way because the
    /// clipping proved the frame could not enter the plan.
    pub cut_short: usize,
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
/// A coarse group spans this many fine cells and angle bins along each axis.
const COARSE_FACTOR: i64 = 3;

/// A polytope containing every frustum added to it: half-spaces with the
/// first frustum's six plane normals and the six axis directions, each
/// pushed out to the farthest corner of any member.
struct Hull {
    planes: Vec<Plane>,
}

impl Hull {
    fn new(first: &Frustum) -> Hull {
        let axes = [DVec3::X, DVec3::NEG_X, DVec3::Y, DVec3::NEG_Y, DVec3::Z, DVec3::NEG_Z];
        let normals = first.planes().iter().map(|p| p.normal).chain(axes);
        Hull { planes: normals.map(|normal| Plane { normal, offset: f64::NEG_INFINITY }).collect() }
    }

    fn cover(&mut self, f: &Frustum) {
        for plane in &mut self.planes {
            for c in f.corners() {
                plane.offset = plane.offset.max(plane.normal.dot(*c));
            }
        }
    }

    /// An upper bound on the overlap of `target` with any member; once it
    /// is proved below `floor`, a looser bound that is still below it, and
    /// once proved to reach it, possibly a looser one in closed form (loose
    /// bounds prune fewer old members, but clipping every hull costs more).
    fn overlap_bound(&self, target: &Frustum, floor: f64) -> f64 {
        let floor_volume = (floor - 2.0 * BOUND_MARGIN) * target.volume();
        let volume = clipped_volume(target, &self.planes, 0.0, floor_volume, Need::Bound).unwrap_or(floor_volume);
        (volume / target.volume()).clamp(0.0, 1.0) + BOUND_MARGIN
    }
}

/// A group's member: what selection reads of it before any geometry, kept
/// beside its group's other members (a stored frame is ~800 bytes, so
/// reading these from the frames themselves cost a cache miss each).
#[derive(Clone, Copy)]
struct Member {
    slot: usize,
    time: u64,
    aabb: Aabb,
    planes: [Plane; 6],
    scale: f64,
}

/// Frames with nearby cameras looking in similar directions.
struct Group {
    hull: Hull,
    /// Members, oldest to newest by `(time, id)`.
    members: Vec<Member>,
    /// The box around every member's frustum.
    aabb: Aabb,
    /// The coarse group (3× the cell and the angle bins) that holds this one.
    coarse: usize,
    /// The newest member's time, read for every group the tree finds
    /// (kept here so that this reads no member).
    newest_time: u64,
}

impl Group {
    /// Widens the hull and the box to contain `f`.
    fn cover(&mut self, f: &Frustum) {
        self.hull.cover(f);
        self.aabb = Aabb { min: self.aabb.min.min(f.aabb().min), max: self.aabb.max.max(f.aabb().max) };
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
    groups: Vec<Group>,
    group_index: HashMap<[i64; 5], usize>,
    /// Hulls of the coarse groups, whose bound can reject many groups with one clip.
    coarse: Vec<Hull>,
    coarse_index: HashMap<[i64; 5], usize>,
    tree: RTree<GroupBox>,
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

    /// All frames, the most recent first (by time, then id).
    pub fn newest_first(&self) -> impl Iterator<Item = &MemoryFrame> {
        self.by_recency.iter().rev().map(|&s| &self.frames[s])
    }

    /// Adds a frame. Ids must be unique; times may arrive out of order.
    pub fn insert(&mut self, frame: MemoryFrame) -> Result<(), InputError> {
        if self.slot_of.contains_key(&frame.id) {
            return Err(InputError::invalid("id", format!("a frame with id {} is already stored", frame.id)));
        }
        let slot = self.frames.len();
        let key = (frame.time, frame.id);
        let frames = &self.frames;
        let newer_than = |s: &usize| (frames[*s].time, frames[*s].id) < key;
        // Appending is the common case; a late frame is placed by binary search.
        let pos = self.by_recency.partition_point(newer_than);
        self.by_recency.insert(pos, slot);
        let fine_key = group_key(&frame.frustum);
        let next_coarse = self.coarse.len();
        let c = *self.coarse_index.entry(fine_key.map(|k| k.div_euclid(COARSE_FACTOR))).or_insert(next_coarse);
        if c == next_coarse {
            self.coarse.push(Hull::new(&frame.frustum));
        }
        self.coarse[c].cover(&frame.frustum);
        let next_group = self.groups.len();
        let g = *self.group_index.entry(fine_key).or_insert(next_group);
        if g == next_group {
            self.groups.push(Group { hull: Hull::new(&frame.frustum), members: Vec::new(), aabb: *frame.frustum.aabb(), coarse: c, newest_time: frame.time });
        }
        let group = &mut self.groups[g];
        let before = (!group.members.is_empty()).then(|| GroupBox { group: g, envelope: envelope(&group.aabb) });
        group.cover(&frame.frustum);
        let pos = group.members.partition_point(|m| newer_than(&m.slot));
        group.newest_time = group.newest_time.max(frame.time);
        group.members.insert(pos, Member { slot, time: frame.time, aabb: *frame.frustum.aabb(), planes: *frame.frustum.planes(), scale: frame.frustum.scale() });
        let after = GroupBox { group: g, envelope: envelope(&group.aabb) };
        if before != Some(after) {
            if let Some(old) = before {
                self.tree.remove(&old);
            }
            self.tree.insert(after);
        }
        self.slot_of.insert(frame.id, slot);
        self.frames.push(frame);
        Ok(())
    }

    /// The plan for `target`, exactly as brute force would choose it.
    /// `previous` (the last plan for a nearby target) only speeds things up.
    pub fn select(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, SelectionStats) {
        Stack::of(self).select(policy, target, previous)
    }

    /// The newest frame's slot, by `(time, id)`.
    fn newest_slot(&self) -> Option<usize> {
        self.by_recency.last().copied()
    }
}

/// Frame memories read as one: layers whose frames together are the memory,
/// such as a fork's shared, frozen history and the frames written since.
/// Ids must be unique across the layers. Selection visits every layer
/// through its own R-tree and bounds with one shared top-`n`, so a stack
/// selects exactly what one `FrameMemory` of all its frames would (tested).
#[derive(Clone, Default)]
pub struct Stack<'a> {
    layers: Vec<&'a FrameMemory>,
}

impl<'a> From<&'a FrameMemory> for Stack<'a> {
    fn from(memory: &'a FrameMemory) -> Self {
        Stack::of(memory)
    }
}

impl<'a> From<&Stack<'a>> for Stack<'a> {
    fn from(stack: &Stack<'a>) -> Self {
        stack.clone()
    }
}

impl<'a> Stack<'a> {
    pub fn new(layers: Vec<&'a FrameMemory>) -> Self {
        Stack { layers }
    }

    pub fn of(memory: &'a FrameMemory) -> Self {
        Stack { layers: vec![memory] }
    }

    /// Adds a layer on top.
    pub fn push(&mut self, memory: &'a FrameMemory) {
        self.layers.push(memory);
    }

    pub fn len(&self) -> usize {
        self.layers.iter().map(|m| m.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.layers.iter().all(|m| m.is_empty())
    }

    pub fn get(&self, id: u64) -> Option<&'a MemoryFrame> {
        self.layers.iter().find_map(|m| m.get(id))
    }

    /// Every frame, layer by layer, each in insertion order.
    pub fn frames(&self) -> impl Iterator<Item = &'a MemoryFrame> + '_ {
        self.layers.iter().flat_map(|m| m.frames.iter())
    }

    /// All frames, the most recent first (by time, then id), merged across layers.
    pub fn newest_first(&self) -> impl Iterator<Item = &'a MemoryFrame> + '_ {
        let mut heads: Vec<_> = self.layers.iter().map(|m| m.newest_first().peekable()).collect();
        std::iter::from_fn(move || {
            let (best, _) = heads.iter_mut().enumerate().filter_map(|(i, h)| h.peek().map(|f| (i, (f.time, f.id)))).max_by_key(|&(_, key)| key)?;
            heads[best].next()
        })
    }

    /// The newest frame's (layer, slot).
    fn newest(&self) -> Option<(usize, usize)> {
        self.layers
            .iter()
            .enumerate()
            .filter_map(|(l, m)| m.newest_slot().map(|s| (l, s)))
            .max_by_key(|&(l, s)| (self.layers[l].frames[s].time, self.layers[l].frames[s].id))
    }

    fn frame(&self, (layer, slot): (usize, usize)) -> &'a MemoryFrame {
        &self.layers[layer].frames[slot]
    }

    /// The plan for `target`, exactly as brute force over every layer's frames would choose it.
    pub fn select(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, SelectionStats) {
        let n = policy.packing.slots();
        let newest = self.newest().map(|at| &self.frame(at).frustum);
        let target = policy.query_view(target, newest);
        match policy.ranking {
            Ranking::Score => self.select_by_score(policy, target, previous),
            Ranking::Recency => {
                // The newest n frames are all that recency can pick.
                let newest: Vec<&MemoryFrame> = self.newest_first().take(n).collect();
                let stats = SelectionStats { overlap_evaluations: newest.len(), ..SelectionStats::default() };
                (select_by_brute_force_among(policy, target, &newest), stats)
            }
            Ranking::GreedyCoverage => {
                // Coverage changes every round; scored by brute force.
                let all: Vec<&MemoryFrame> = self.frames().collect();
                let stats =
                    SelectionStats { box_candidates: all.len(), overlap_evaluations: all.len() * n, ..SelectionStats::default() };
                (select_by_brute_force_among(policy, target, &all), stats)
            }
        }
    }

    fn select_by_score(&self, policy: &Policy, target: &Frustum, previous: Option<&ContextPlan>) -> (ContextPlan, SelectionStats) {
        let mut stats = SelectionStats::default();
        let Some(newest) = self.newest() else {
            return (ContextPlan::from_ranked(&policy.packing, &[]), stats);
        };
        let t_now = self.frame(newest).time;
        let pinned = policy.keep_last.then_some(newest);
        let n = policy.packing.slots() - pinned.is_some() as usize;
        let samples = policy.estimator.samples(target);
        let overlap_of = |f: &MemoryFrame| match &samples {
            Some(s) => s.overlap(&f.frustum),
            None => crate::overlap::exact_overlap(target, &f.frustum),
        };
        let describe = |at: (usize, usize), overlap: f64| {
            let f = self.frame(at);
            SelectedFrame { id: f.id, time: f.time, overlap, score: policy.weights.score(overlap, age(f.time, t_now)) }
        };

        // WorldMem's angular test has no range: a box cannot rule a frame out.
        let ranged = !matches!(policy.estimator, Estimator::WorldMem(_));
        let meets_box = |aabb: &Aabb| !ranged || aabb.intersects(target.aabb());
        let meets = |at: (usize, usize)| meets_box(self.frame(at).frustum.aabb());
        // Group bounds hold for the exact overlap only (an estimate may
        // exceed them), and only rank correctly while the score grows with it.
        let use_bounds = matches!(policy.estimator, Estimator::Exact) && policy.weights.overlap > 0.0;
        let mut best = TopN::new(n);
        if n > 0 {
            // Warm start: last plan's frames that can still overlap.
            let mut warm: Vec<(usize, usize)> = Vec::new();
            for id in previous.iter().flat_map(|p| p.selected().map(|(_, f)| f.id)) {
                let Some(at) = self.layers.iter().enumerate().find_map(|(l, m)| m.slot_of.get(&id).map(|&s| (l, s))) else { continue };
                if Some(at) != pinned && meets(at) && !warm.contains(&at) {
                    warm.push(at);
                    stats.overlap_evaluations += 1;
                    best.push(describe(at, overlap_of(self.frame(at))));
                }
            }
            let mut groups: Vec<(usize, usize)> = Vec::new();
            for (l, m) in self.layers.iter().enumerate() {
                if ranged {
                    groups.extend(m.tree.locate_in_envelope_intersecting(envelope(target.aabb())).map(|b| (l, b.group)));
                } else {
                    groups.extend((0..m.groups.len()).map(|g| (l, g)));
                }
            }
            // Best first: a queue of each group's next step keyed by the best
            // score any of its remaining members could reach. A group enters
            // with its coarse group's bound; its own hull is clipped only when
            // it reaches the head of the queue: by then `s*` has often risen
            // past it and that clip is never spent.
            let upper = |bound: f64, time: u64| policy.weights.score(bound, age(time, t_now));
            let mut queue: BinaryHeap<Next> = BinaryHeap::with_capacity(groups.len());
            let mut coarse_bounds: Vec<Vec<f64>> = self.layers.iter().map(|m| vec![f64::NAN; m.coarse.len()]).collect();
            for (layer, g) in groups {
                let memory = self.layers[layer];
                let group = &memory.groups[g];
                stats.box_candidates += group.members.len();
                let newest = Stage::Member(group.members.len() - 1);
                if !use_bounds {
                    queue.push(Next { upper: upper(1.0, group.newest_time), bound: 1.0, layer, group: g, stage: newest });
                    continue;
                }
                if best.cannot_admit(upper(1.0, group.newest_time)) {
                    continue;
                }
                // Coarse bounds are few and shared by groups of every age, so
                // they are taken at once, clipped only as far as the newest
                // frame needs.
                let coarse = &mut coarse_bounds[layer][group.coarse];
                if coarse.is_nan() {
                    stats.group_bounds += 1;
                    *coarse = memory.coarse[group.coarse].overlap_bound(target, best.overlap_to_enter(&policy.weights, 0.0));
                }
                let bound = *coarse;
                if best.cannot_admit(upper(bound, group.newest_time)) {
                    continue;
                }
                let stage = if group.members.len() >= MIN_GROUP_FOR_BOUND { Stage::Group } else { newest };
                queue.push(Next { upper: upper(bound, group.newest_time), bound, layer, group: g, stage });
            }
            while let Some(next) = queue.pop() {
                if best.cannot_admit(next.upper) {
                    break; // everything still queued has a lower bound
                }
                let group = &self.layers[next.layer].groups[next.group];
                let index = match next.stage {
                    Stage::Group => {
                        stats.group_bounds += 1;
                        let floor = best.overlap_to_enter(&policy.weights, age(group.newest_time, t_now));
                        let bound = group.hull.overlap_bound(target, floor).min(next.bound);
                        queue.push(Next { upper: upper(bound, group.newest_time), bound, stage: Stage::Member(group.members.len() - 1), ..next });
                        continue;
                    }
                    Stage::Member(index) => index,
                };
                // Members newest first, staying in this group while its next
                // member still ranks at least as high as the queue's head (the
                // heap is touched once per switch of group, not per member).
                let members = &group.members;
                let mut index = index;
                loop {
                    let member = &members[index];
                    let at = (next.layer, member.slot);
                    if Some(at) != pinned && meets_box(&member.aabb) && !warm.contains(&at) {
                        stats.overlap_evaluations += 1;
                        if use_bounds {
                            // The clip stops once it proves this frame cannot enter.
                            let floor = best.overlap_to_enter(&policy.weights, age(member.time, t_now));
                            // Its box meets the target's (checked above): the planes beside it are all the clip needs.
                            match crate::overlap::overlap_within_unless_below(target, &member.planes, member.scale, floor) {
                                Some(o) => best.push(describe(at, o)),
                                None => stats.cut_short += 1,
                            }
                        } else {
                            best.push(describe(at, overlap_of(self.frame(at))));
                        }
                    }
                    if index == 0 {
                        break;
                    }
                    index -= 1;
                    let older = Next { upper: upper(next.bound, members[index].time), stage: Stage::Member(index), ..next };
                    if best.cannot_admit(older.upper) {
                        break; // older members score lower still
                    }
                    if queue.peek().is_some_and(|head| head.upper > older.upper) {
                        queue.push(older);
                        break;
                    }
                }
            }
            // Zero-overlap frames: scores need no geometry, newest is best (layer by layer).
            for (l, m) in self.layers.iter().enumerate() {
                for &slot in m.by_recency.iter().rev() {
                    let at = (l, slot);
                    if Some(at) == pinned || meets(at) {
                        continue;
                    }
                    let entry = describe(at, 0.0);
                    if best.cannot_admit(entry.score) {
                        break;
                    }
                    best.push(entry);
                }
            }
        }
        let mut ranked = best.into_sorted();
        if let Some(at) = pinned {
            stats.overlap_evaluations += 1;
            ranked.insert(0, describe(at, overlap_of(self.frame(at))));
        }
        (ContextPlan::from_ranked(&policy.packing, &ranked), stats)
    }
}

/// A group's next step and the best score any of its remaining members could reach.
#[derive(Clone, Copy)]
struct Next {
    upper: f64,
    /// The tightest bound on the group's overlaps found so far.
    bound: f64,
    /// The stack layer the group belongs to.
    layer: usize,
    group: usize,
    stage: Stage,
}

#[derive(Clone, Copy)]
enum Stage {
    /// Bound the group by its own hull.
    Group,
    /// Evaluate the member at this position in `members` (oldest first).
    Member(usize),
}

impl PartialEq for Next {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other).is_eq()
    }
}
impl Eq for Next {}
impl PartialOrd for Next {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Next {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.upper.total_cmp(&other.upper).then(other.layer.cmp(&self.layer)).then(other.group.cmp(&self.group))
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

    /// The least overlap a frame of this age needs to be admitted (−∞ while
    /// the heap is not full). Score-ranked with a positive overlap weight only.
    fn overlap_to_enter(&self, weights: &crate::policy::ScoreWeights, age: f64) -> f64 {
        match self.heap.peek() {
            Some(worst) if self.heap.len() == self.n => (worst.0.score + weights.recency * age) / weights.overlap,
            _ => f64::NEG_INFINITY,
        }
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
