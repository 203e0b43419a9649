//! Imagined rollouts: K candidate futures of H steps from a session's
//! present, none written to the session or the store. Each candidate reads
//! the session's history with its own earlier imagined frames on top, as a
//! fork stepped H times would (the same `engine::prepare` and model call), and
//! step h of every candidate runs in one model call. Candidates that agree up
//! to a step (a planner's often share their first actions) are one future so
//! far: its frames are made once and shared.

use std::time::Instant;

use memory::{ContextPlan, Pose};
use model::Sampler;
use motion::Action;

use crate::batch::{self, Item};
use crate::engine::{Engine, Next, ms, prepare};
use crate::refusal::EngineError;
use crate::session::{Frame, Segment, Session};

/// What one imagine request may ask for; beyond it the request is refused with 400 naming the field.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Candidates (K).
    pub candidates: usize,
    /// Steps per candidate (H).
    pub horizon: usize,
    /// Bytes of imagined frames the answer may carry (PNG bounded by its raw size, latents as f32; before base64).
    pub answer_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { candidates: 64, horizon: 64, answer_bytes: 24 << 20 }
    }
}

/// One candidate future: an action per step, and optionally the pose of
/// each step (else the motion model moves by the action, as a step does).
pub struct Candidate {
    pub actions: Vec<Action>,
    pub poses: Option<Vec<Pose>>,
}

/// An imagined frame: where it was seen from, its latent and its decoded picture.
#[derive(Clone)]
pub struct Imagined {
    pub pose: Pose,
    pub time: u64,
    pub latent: Vec<f32>,
    pub rgb: Vec<u8>,
}

/// Every candidate's H frames, and what making them cost.
pub struct Imagination {
    pub rollouts: Vec<Vec<Imagined>>,
    /// Model calls made: one per step of the horizon.
    pub calls: usize,
    /// Frames the model made: K × H less those shared by candidates with the same prefix.
    pub made: usize,
    /// Milliseconds, summed over the horizon: choosing poses and plans, the warp, sampling, decoding.
    pub select_ms: f64,
    pub warp_ms: f64,
    pub sample_ms: f64,
    pub decode_ms: f64,
}

/// What an imagined rollout's last step must give: the frame (decoded, with
/// the heads, as a step's), or only the sampled latent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Last {
    Frame,
    Latent,
}

/// A frame against a goal image: PSNR of the pictures (dB, higher is
/// closer) and the mean squared difference of the model's latents (lower is closer).
#[derive(Clone, Copy, Debug)]
pub struct GoalScore {
    /// None for a frame not decoded, or when the picture is not scored.
    pub psnr_db: Option<f64>,
    pub latent_mse: f64,
}

impl Engine {
    /// Rolls every candidate out from `s`'s present (candidates of one
    /// horizon; the caller checks the lengths). The noise seed of step h is
    /// `seed + h`, or, without a seed, the frame's time, as a step's is: a
    /// candidate imagined alone equals a fork stepped with those seeds.
    /// `last` says what the last step needs: nothing reads its frame again, so
    /// when only its latent is wanted it is not decoded (`rgb` empty).
    pub fn imagine(&self, s: &Session, candidates: &[Candidate], sampler: &Sampler, seed: Option<u64>, last: Last) -> Result<Imagination, EngineError> {
        let m = self.model()?;
        let horizon = candidates.first().map_or(0, |c| c.actions.len());
        let base = s.timeline();
        let mut own: Vec<Segment> = candidates.iter().map(|_| Segment::starting_at(s.len())).collect();
        let mut previous: Vec<Option<ContextPlan>> = vec![s.last_plan.clone(); candidates.len()];
        let mut out = Imagination { rollouts: candidates.iter().map(|_| Vec::with_capacity(horizon)).collect(), calls: 0, made: 0, select_ms: 0.0, warp_ms: 0.0, sample_ms: 0.0, decode_ms: 0.0 };
        let mut same = vec![0; candidates.len()];
        for h in 0..horizon {
            let t0 = Instant::now();
            same = same_prefix(candidates, &same, h);
            // Only the first candidate of each prefix is imagined; the seed is per step, not per
            // candidate, so the others would have been given the same inputs and made the same frame.
            let firsts: Vec<usize> = (0..candidates.len()).filter(|&k| same[k] == k).collect();
            let nexts = firsts
                .iter()
                .map(|&k| {
                    let c = &candidates[k];
                    let pose = c.poses.as_ref().map(|p| p[h]);
                    prepare(m, &base.with(&own[k]), &c.actions[h], pose, seed.map(|s| s + h as u64), previous[k].as_ref())
                })
                .collect::<Result<Vec<Next>, _>>()?;
            out.select_ms += ms(t0);
            let items: Vec<&Item> = nexts.iter().map(|n| &n.item).collect();
            let outcomes = if h + 1 == horizon && last == Last::Latent {
                batch::call_latents(m, &s.policy.packing, sampler, &items)?
            } else {
                batch::call(m, &s.policy.packing, sampler, &items)?
            };
            out.calls += 1;
            out.made += firsts.len();
            if let Some(o) = outcomes.first() {
                out.warp_ms += o.warp_ms;
                out.sample_ms += o.sample_ms;
                out.decode_ms += o.decode_ms;
            }
            let made = nexts
                .into_iter()
                .zip(outcomes)
                .map(|(next, outcome)| {
                    let f = outcome.frame;
                    let imagined = Imagined { pose: next.pose, time: next.time, latent: f.latent, rgb: f.rgb };
                    Ok((s.frustum(next.pose)?, next, imagined))
                })
                .collect::<Result<Vec<_>, EngineError>>()?;
            for k in 0..candidates.len() {
                let (frustum, next, imagined) = &made[firsts.partition_point(|&j| j < same[k])];
                own[k].push(frustum.clone(), Frame { pose: next.pose, time: next.time, latent: imagined.latent.clone(), player: next.player, generated: true })?;
                previous[k] = Some(next.plan.clone());
                out.rollouts[k].push(imagined.clone());
            }
        }
        Ok(out)
    }
}

/// For step h, each candidate's first candidate with the same actions and poses
/// through h, given the same through h − 1 (`before`).
fn same_prefix(candidates: &[Candidate], before: &[usize], h: usize) -> Vec<usize> {
    let step = |k: usize| (&candidates[k].actions[h], candidates[k].poses.as_ref().map(|p| &p[h]));
    (0..candidates.len()).map(|k| (0..=k).find(|&j| before[j] == before[k] && step(j) == step(k)).unwrap_or(k)).collect()
}

/// How close `frame` is to the goal: its latent, and its picture when `goal_rgb` (at the
/// model's size) is given and the frame was decoded.
pub fn goal_score(frame: &Imagined, goal_rgb: Option<&[u8]>, goal_latent: &[f32]) -> GoalScore {
    let n = goal_latent.len().min(frame.latent.len()).max(1);
    let latent_mse = frame.latent.iter().zip(goal_latent).map(|(a, b)| f64::from(a - b).powi(2)).sum::<f64>() / n as f64;
    // A frame not decoded (`Last::Latent`) has no picture; the route checks the goal's size.
    let psnr_db = goal_rgb.filter(|g| !frame.rgb.is_empty() && frame.rgb.len() == g.len()).map(|g| eval::metrics::psnr(&frame.rgb, g));
    GoalScore { psnr_db, latent_mse }
}

