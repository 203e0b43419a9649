//! Context policies: which past frames enter the model's context, and at
//! which compression rate (paper §3.2, Algorithm 1).
//!
//! A policy is a *ranking* of the stored frames plus a *packing* that gives
//! rank r its rate. The paper's four ablations and WorldMem's greedy
//! selection are presets of these two parts.

use serde::{Deserialize, Serialize};

use crate::error::InputError;
use crate::frustum::Frustum;
use crate::overlap::{Estimator, MonteCarlo, ViewSamples};

/// A stored frame as selection sees it.
#[derive(Clone, Debug)]
pub struct MemoryFrame {
    pub id: u64,
    /// Step index; larger is more recent.
    pub time: u64,
    pub frustum: Frustum,
}

/// `s_i = overlap·o_i − recency·Δt_i` (paper Eq. 7).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreWeights {
    pub overlap: f64,
    pub recency: f64,
}

impl Default for ScoreWeights {
    fn default() -> Self {
        ScoreWeights { overlap: 1.0, recency: 0.2 }
    }
}

impl ScoreWeights {
    pub fn validated(self) -> Result<Self, InputError> {
        crate::error::check_finite("weights.overlap", &[self.overlap])?;
        crate::error::check_finite("weights.recency", &[self.recency])?;
        if self.overlap <= 0.0 {
            return Err(InputError::NotPositive { field: "weights.overlap".into(), value: self.overlap });
        }
        if self.recency < 0.0 {
            return Err(InputError::invalid("weights.recency", format!("must be ≥ 0, got {}", self.recency)));
        }
        Ok(self)
    }

    pub fn score(&self, overlap: f64, age: f64) -> f64 {
        self.overlap * overlap - self.recency * age
    }
}

/// A group of context slots sharing one compression rate (token reduction factor).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tier {
    pub slots: usize,
    pub rate: u32,
}

/// Slots in rank order: the first tier's slots take ranks 1.., and so on.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Packing {
    tiers: Vec<Tier>,
}

impl Packing {
    /// Rates must be perfect squares (square kernels: rate 4 is 2× the patch
    /// per side, 16 is 4×) and at least one slot must exist.
    pub fn new(tiers: Vec<Tier>) -> Result<Packing, InputError> {
        for (i, t) in tiers.iter().enumerate() {
            if t.rate == 0 || side_factor(t.rate).is_none() {
                return Err(InputError::invalid(
                    &format!("tiers[{i}].rate"),
                    format!("must be a perfect square ≥ 1 (1, 4, 16, …) so kernels stay square, got {}", t.rate),
                ));
            }
        }
        if tiers.iter().map(|t| t.slots).sum::<usize>() == 0 {
            return Err(InputError::invalid("tiers", "at least one slot is required"));
        }
        Ok(Packing { tiers })
    }

    /// Rates `λ^d`: `groups` lists `(slots, d)` from the first tier on.
    pub fn geometric(lambda: u32, groups: &[(usize, u32)]) -> Result<Packing, InputError> {
        if lambda < 2 {
            return Err(InputError::invalid("lambda", format!("must be ≥ 2, got {lambda}")));
        }
        let tiers = groups
            .iter()
            .enumerate()
            .map(|(i, &(slots, d))| {
                lambda
                    .checked_pow(d)
                    .map(|rate| Tier { slots, rate })
                    .ok_or_else(|| InputError::invalid(&format!("tiers[{i}].d"), "λ^d overflows"))
            })
            .collect::<Result<_, _>>()?;
        Packing::new(tiers)
    }

    /// `slots` frames at full resolution (the Baseline and Memory Retrieval
    /// budget). Panics on 0 slots; user-given tiers go through [`Packing::new`].
    pub fn uncompressed(slots: usize) -> Packing {
        Packing::new(vec![Tier { slots, rate: 1 }]).expect("one tier at rate 1")
    }

    /// The paper's packing: 2 at rate 1, 4 at 1/4, 16 at 1/16 (λ = 2, d ∈ {0, 2, 4}).
    pub fn worldpack() -> Packing {
        Packing::geometric(2, &[(2, 0), (4, 2), (16, 4)]).expect("valid constants")
    }

    pub fn tiers(&self) -> &[Tier] {
        &self.tiers
    }

    pub fn slots(&self) -> usize {
        self.tiers.iter().map(|t| t.slots).sum()
    }

    /// The rate of every slot, in rank order.
    pub fn rates(&self) -> impl Iterator<Item = u32> + '_ {
        self.tiers.iter().flat_map(|t| std::iter::repeat_n(t.rate, t.slots))
    }
}

/// `√rate` when the rate is a perfect square.
pub fn side_factor(rate: u32) -> Option<u32> {
    let s = (rate as f64).sqrt().round() as u64;
    (s * s == rate as u64).then_some(s as u32)
}

/// How frames are put in order before packing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ranking {
    /// Most recent first.
    Recency,
    /// By `s_i`, best first.
    Score,
    /// WorldMem: repeatedly take the best-scoring frame, then drop the part of
    /// the view it covers before scoring the rest.
    GreedyCoverage,
}

/// The named policies of the paper and of WorldMem.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PolicyKind {
    /// 4 most recent frames, uncompressed.
    Baseline,
    /// 22 most recent frames, packed 2/4/16 by recency.
    NearestFramePacking,
    /// 4 best-scoring frames, uncompressed.
    MemoryRetrieval,
    /// 22 best-scoring frames, packed 2/4/16 by rank.
    #[serde(rename = "worldpack")]
    WorldPack,
    /// WorldMem's greedy coverage, 4 frames uncompressed, its own estimator.
    #[serde(rename = "worldmem_greedy")]
    WorldMemGreedy,
}

/// Which view stored frames are scored against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Query {
    /// The current pose p_t, the newest stored frame's (the paper's Algorithm 1):
    /// that frame has overlap 1 and age 0, so it always ranks first.
    Current,
    /// The pose of the frame about to be generated, p_{t+1} (WorldMem's and
    /// LoopNav's choice): it sees where the camera is going, and may push
    /// the newest frame out of the full-rate slots.
    Target,
}

/// Co-visibility's settings (`crate::covisibility`): a policy that carries them
/// re-ranks its frustum candidates by what each frame saw of the target's surface.
/// Fields left out of a request take the defaults.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CoVisibility {
    /// Frames kept from the frustum stage.
    pub candidates: usize,
    /// Candidates whose depth makes the target's expected surface.
    pub sources: usize,
    /// Columns of the target's coarse grid.
    pub cells: u32,
    /// A surface point counts as seen when it lies at most this much deeper
    /// than the frame's recorded surface there, relative.
    pub tolerance: f64,
}

impl Default for CoVisibility {
    fn default() -> Self {
        CoVisibility { candidates: 32, sources: 3, cells: 16, tolerance: 0.1 }
    }
}

impl CoVisibility {
    /// The largest settings accepted: beyond them a selection's cost grows with no gain.
    pub const MAX_CANDIDATES: usize = 4096;
    pub const MAX_SOURCES: usize = 64;
    pub const MAX_CELLS: u32 = 256;
    pub const MAX_TOLERANCE: f64 = 10.0;

    pub fn validated(self) -> Result<Self, InputError> {
        let count = |field: &str, v: usize, max: usize| {
            if (1..=max).contains(&v) {
                Ok(())
            } else {
                Err(InputError::invalid(&format!("covisibility.{field}"), format!("must be from 1 to {max}, got {v}")))
            }
        };
        count("candidates", self.candidates, Self::MAX_CANDIDATES)?;
        count("sources", self.sources, Self::MAX_SOURCES)?;
        count("cells", self.cells as usize, Self::MAX_CELLS as usize)?;
        if !(0.0..=Self::MAX_TOLERANCE).contains(&self.tolerance) {
            return Err(InputError::invalid("covisibility.tolerance", format!("must be from 0 to {}, got {}", Self::MAX_TOLERANCE, self.tolerance)));
        }
        Ok(self)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Policy {
    pub kind: PolicyKind,
    pub ranking: Ranking,
    pub packing: Packing,
    pub estimator: Estimator,
    pub weights: ScoreWeights,
    /// Always put the most recent frame in the first slot.
    pub keep_last: bool,
    pub query: Query,
    /// Re-rank the frustum stage's candidates by co-visibility from depth
    /// (`crate::covisibility`); None: frustum overlap alone.
    pub covisibility: Option<CoVisibility>,
}

impl Policy {
    pub fn preset(kind: PolicyKind) -> Policy {
        let (ranking, packing, estimator) = match kind {
            PolicyKind::Baseline => (Ranking::Recency, Packing::uncompressed(4), Estimator::Exact),
            PolicyKind::NearestFramePacking => (Ranking::Recency, Packing::worldpack(), Estimator::Exact),
            PolicyKind::MemoryRetrieval => (Ranking::Score, Packing::uncompressed(4), Estimator::Exact),
            PolicyKind::WorldPack => (Ranking::Score, Packing::worldpack(), Estimator::Exact),
            PolicyKind::WorldMemGreedy => {
                (Ranking::GreedyCoverage, Packing::uncompressed(4), Estimator::WorldMem(Default::default()))
            }
        };
        // The paper's scored policies follow Algorithm 1; recency needs no query, and WorldMem looks ahead.
        let query = match kind {
            PolicyKind::MemoryRetrieval | PolicyKind::WorldPack => Query::Current,
            PolicyKind::Baseline | PolicyKind::NearestFramePacking | PolicyKind::WorldMemGreedy => Query::Target,
        };
        Policy { kind, ranking, packing, estimator, weights: ScoreWeights::default(), keep_last: false, query, covisibility: None }
    }

    /// Only overlap with the target view counts, one frame: the frame the
    /// non-learned references copy or warp, and a geometry model's warp source.
    pub fn best_overlap() -> Policy {
        Policy::best_overlap_frames(1)
    }

    /// The `frames` stored frames that overlap the target view most, best first.
    pub fn best_overlap_frames(frames: usize) -> Policy {
        Policy {
            kind: PolicyKind::MemoryRetrieval,
            ranking: Ranking::Score,
            packing: Packing::uncompressed(frames),
            estimator: Estimator::Exact,
            weights: ScoreWeights { overlap: 1.0, recency: 0.0 },
            keep_last: false,
            query: Query::Target,
            covisibility: None,
        }
    }

    /// This policy, re-ranked by co-visibility at the default settings.
    pub fn covisible(self) -> Policy {
        Policy { covisibility: Some(CoVisibility::default()), ..self }
    }

    /// The view to score against: `target`, or the newest stored frame's
    /// frustum for [`Query::Current`] (the target when nothing is stored).
    pub fn query_view<'a>(&self, target: &'a Frustum, newest: Option<&'a Frustum>) -> &'a Frustum {
        match (self.query, newest) {
            (Query::Current, Some(f)) => f,
            _ => target,
        }
    }
}

/// A policy as users write it: a preset plus optional overrides.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicySpec {
    pub kind: PolicyKind,
    #[serde(default)]
    pub keep_last: Option<bool>,
    #[serde(default)]
    pub estimator: Option<Estimator>,
    #[serde(default)]
    pub weights: Option<ScoreWeights>,
    #[serde(default)]
    pub tiers: Option<Vec<Tier>>,
    #[serde(default)]
    pub query: Option<Query>,
    #[serde(default)]
    pub covisibility: Option<CoVisibility>,
}

impl PolicySpec {
    pub fn into_policy(self) -> Result<Policy, InputError> {
        let mut p = Policy::preset(self.kind);
        if let Some(k) = self.keep_last {
            p.keep_last = k;
        }
        if let Some(e) = self.estimator {
            p.estimator = e.validated()?;
        }
        if let Some(w) = self.weights {
            p.weights = w.validated()?;
        }
        if let Some(t) = self.tiers {
            p.packing = Packing::new(t)?;
        }
        if let Some(q) = self.query {
            p.query = q;
        }
        if let Some(c) = self.covisibility {
            p.covisibility = Some(c.validated()?);
        }
        Ok(p)
    }
}

/// One selected frame and why.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SelectedFrame {
    pub id: u64,
    pub time: u64,
    /// Overlap with the target view. For greedy coverage: the share of the
    /// view not yet covered by earlier picks that this frame covers.
    pub overlap: f64,
    pub score: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Slot {
    pub rate: u32,
    /// `None`: an empty slot, masked out of the model's attention.
    pub frame: Option<SelectedFrame>,
}

/// The context for one prediction: slots in rank order.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ContextPlan {
    pub slots: Vec<Slot>,
}

impl ContextPlan {
    pub(crate) fn from_ranked(packing: &Packing, ranked: &[SelectedFrame]) -> ContextPlan {
        let slots = packing.rates().enumerate().map(|(i, rate)| Slot { rate, frame: ranked.get(i).copied() }).collect();
        ContextPlan { slots }
    }

    /// True when no slot holds a frame; the model cannot run on such a plan.
    pub fn is_empty(&self) -> bool {
        self.slots.iter().all(|s| s.frame.is_none())
    }

    pub fn selected(&self) -> impl Iterator<Item = (u32, &SelectedFrame)> {
        self.slots.iter().filter_map(|s| s.frame.as_ref().map(|f| (s.rate, f)))
    }

    /// Context tokens for a latent grid: `(used by filled slots, capacity)`.
    pub fn tokens(&self, grid: &LatentGrid) -> (u64, u64) {
        let mut used = 0;
        let mut capacity = 0;
        for s in &self.slots {
            let n = grid.tokens_at_rate(s.rate);
            capacity += n;
            if s.frame.is_some() {
                used += n;
            }
        }
        (used, capacity)
    }
}

/// A latent frame's spatial size and the model's patch size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LatentGrid {
    pub height: u32,
    pub width: u32,
    pub patch: u32,
}

impl LatentGrid {
    pub fn validated(self) -> Result<Self, InputError> {
        for (field, v) in [("latent.height", self.height), ("latent.width", self.width), ("latent.patch", self.patch)] {
            if v == 0 {
                return Err(InputError::NotPositive { field: field.into(), value: 0.0 });
            }
        }
        Ok(self)
    }

    /// Tokens of one frame at `rate`: kernel `patch·√rate` per side, the
    /// latent replicate-padded up to a multiple of the kernel.
    pub fn tokens_at_rate(&self, rate: u32) -> u64 {
        let k = self.patch as u64 * side_factor(rate).unwrap_or(1) as u64;
        (self.height as u64).div_ceil(k) * (self.width as u64).div_ceil(k)
    }
}

/// Selects by brute force: every stored frame is considered. The target is
/// the frustum of the frame being generated; the policy's [`Query`] decides
/// whether frames are scored against it or against the newest stored frame.
/// This is the reference that the indexed selection in [`crate::index`] must match.
/// It ranks by frustum overlap alone (a policy's `covisibility` is [`FrameMemory::plan`]'s).
///
/// [`FrameMemory::plan`]: crate::FrameMemory::plan
pub fn select_by_brute_force(policy: &Policy, target: &Frustum, frames: &[MemoryFrame]) -> ContextPlan {
    let refs: Vec<&MemoryFrame> = frames.iter().collect();
    select_by_brute_force_among(policy, target, &refs)
}

/// [`select_by_brute_force`] over borrowed frames.
pub fn select_by_brute_force_among(policy: &Policy, target: &Frustum, frames: &[&MemoryFrame]) -> ContextPlan {
    let Some(t_now) = frames.iter().map(|f| f.time).max() else {
        return ContextPlan::from_ranked(&policy.packing, &[]);
    };
    let newest = frames.iter().max_by_key(|f| (f.time, f.id)).map(|f| &f.frustum);
    let target = policy.query_view(target, newest);
    let age_of = |f: &MemoryFrame| age(f.time, t_now);
    let n = policy.packing.slots();
    let by_recency = |a: &&MemoryFrame, b: &&MemoryFrame| b.time.cmp(&a.time).then(b.id.cmp(&a.id));
    let pinned: Option<&MemoryFrame> = if policy.keep_last { frames.iter().copied().min_by(by_recency) } else { None };
    let rest = frames.iter().copied().filter(|f| pinned.is_none_or(|p| !std::ptr::eq(*f, p)));
    let describe = |f: &MemoryFrame, overlap: f64| SelectedFrame {
        id: f.id,
        time: f.time,
        overlap,
        score: policy.weights.score(overlap, age_of(f)),
    };

    let mut ranked: Vec<SelectedFrame> = Vec::with_capacity(n);
    match policy.ranking {
        Ranking::Recency | Ranking::Score => {
            let chosen: Vec<(&MemoryFrame, f64)> = if policy.ranking == Ranking::Recency {
                let mut by_time: Vec<&MemoryFrame> = pinned.into_iter().chain(rest).collect();
                by_time.sort_by(by_recency);
                by_time.truncate(n);
                // Overlaps only for the chosen few, to explain the plan.
                let o = policy.estimator.overlaps(target, by_time.iter().map(|f| &f.frustum));
                by_time.into_iter().zip(o).collect()
            } else {
                let rest: Vec<&MemoryFrame> = rest.collect();
                let o = policy.estimator.overlaps(target, pinned.iter().chain(&rest).map(|f| &f.frustum));
                let mut scored: Vec<(&MemoryFrame, f64)> = pinned.iter().chain(&rest).copied().zip(o).collect();
                let pinned_entry = pinned.map(|_| scored.remove(0));
                scored.sort_by(|a, b| rank_order(&describe(a.0, a.1), &describe(b.0, b.1)));
                pinned_entry.into_iter().chain(scored).take(n).collect()
            };
            ranked.extend(chosen.into_iter().map(|(f, o)| describe(f, o)));
        }
        Ranking::GreedyCoverage => {
            let mut samples = policy
                .estimator
                .samples(target)
                .unwrap_or_else(|| ViewSamples::monte_carlo(target, &MonteCarlo::default()));
            let mut pool: Vec<&MemoryFrame> = rest.collect();
            if let Some(p) = pinned {
                ranked.push(describe(p, samples.overlap(&p.frustum)));
                samples.remove_seen_by(&p.frustum);
            }
            while ranked.len() < n && !pool.is_empty() {
                let (best_index, best) = pool
                    .iter()
                    .enumerate()
                    .map(|(i, f)| (i, describe(f, samples.overlap(&f.frustum))))
                    .min_by(|a, b| rank_order(&a.1, &b.1))
                    .expect("pool is not empty");
                samples.remove_seen_by(&pool[best_index].frustum);
                pool.swap_remove(best_index);
                ranked.push(best);
            }
        }
    }
    ContextPlan::from_ranked(&policy.packing, &ranked)
}

/// `Δt_i = (t − time_i)/t`, 0 when `t = 0` (paper Eq. 7).
pub fn age(time: u64, t_now: u64) -> f64 {
    if t_now == 0 { 0.0 } else { t_now.saturating_sub(time) as f64 / t_now as f64 }
}

/// Best first: higher score, then more recent, then larger id. Total, so
/// every tie is broken the same way everywhere.
pub fn rank_order(a: &SelectedFrame, b: &SelectedFrame) -> std::cmp::Ordering {
    b.score.total_cmp(&a.score).then(b.time.cmp(&a.time)).then(b.id.cmp(&a.id))
}
