//! Imagined rollouts: K candidate futures of H steps from a session's
//! present, none written to the session or the store. Each candidate reads
//! the session's history with its own earlier imagined frames on top, as a
//! fork stepped H times would (the same `engine::prepare` and model call), and
//! step h of every candidate runs in one model call.

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
        let mut out = Imagination { rollouts: candidates.iter().map(|_| Vec::with_capacity(horizon)).collect(), calls: 0, select_ms: 0.0, warp_ms: 0.0, sample_ms: 0.0, decode_ms: 0.0 };
        for h in 0..horizon {
            let t0 = Instant::now();
            let nexts = candidates
                .iter()
                .zip(&own)
                .zip(&previous)
                .map(|((c, mine), prev)| {
                    let pose = c.poses.as_ref().map(|p| p[h]);
                    prepare(m, &base.with(mine), &c.actions[h], pose, seed.map(|s| s + h as u64), prev.as_ref())
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
            if let Some(o) = outcomes.first() {
                out.warp_ms += o.warp_ms;
                out.sample_ms += o.sample_ms;
                out.decode_ms += o.decode_ms;
            }
            for (k, (next, outcome)) in nexts.into_iter().zip(outcomes).enumerate() {
                let Next { pose, player, time, plan, .. } = next;
                let frame = outcome.frame;
                own[k].push(s.frustum(pose)?, Frame { pose, time, latent: frame.latent.clone(), player, generated: true })?;
                previous[k] = Some(plan);
                out.rollouts[k].push(Imagined { pose, time, latent: frame.latent, rgb: frame.rgb });
            }
        }
        Ok(out)
    }
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

