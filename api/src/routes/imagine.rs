//! `POST /v1/sessions/{id}/imagine`: K candidate futures of H steps from the
//! session's present, answered and forgotten (`crate::imagine`).

use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::HeaderMap;
use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use memory::input::PoseInput;
use motion::Action;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use world::picture::encode_png;

use crate::auth::Caller;
use crate::error::{ApiError, ErrorBody};
use crate::imagine::{Candidate, Last, goal_score};
use crate::schemas;
use super::request::{parse, session_id, check_id, decode_png, pose_from, sampler, validate_action};
use super::access::{slot, lock, permit, blocking};
use super::answers::PoseAnswer;
use super::{Res, St};

/// Candidate futures to imagine from the session's present, and what to answer of them.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ImagineRequest {
    /// K candidates (1 to the server's limit, 64 by default), each H steps long (the same H for all, 1 to 64 by default).
    #[schema(min_items = 1)]
    candidates: Vec<CandidateInput>,
    /// Sampler steps (default: the server's --steps).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 1000)]
    steps: Option<usize>,
    /// Noise seed: step h of every candidate uses `seed + h`. Default: each frame's time, as a step's default.
    #[serde(default)]
    #[schema(maximum = 9223372036854775807_u64)]
    seed: Option<u64>,
    /// Which imagined frames the answer carries: `"last"` (the default), `"all"`, `"none"`, or `{"every": n}` (steps n, 2n, …).
    #[serde(default)]
    frames: FramesAsked,
    /// How they are carried: `"png"` (the default) or `"latent"` (the model's scaled latents, f32 little-endian, base64).
    #[serde(default)]
    format: FrameFormat,
    /// A goal image (base64 PNG at the model's image size): each candidate's last frame is scored against it.
    #[serde(default)]
    #[schema(content_encoding = "base64")]
    goal_png: Option<String>,
    /// How the goal is scored: `"both"` (the default: PSNR of the pictures and the latents' difference) or
    /// `"latent"` (the latents' only: unless its frame is answered, the last step is then not decoded).
    #[serde(default)]
    goal_score: GoalScoring,
}

#[derive(Deserialize, ToSchema, Clone, Copy, Debug, Default, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum GoalScoring {
    #[default]
    Both,
    Latent,
}

/// One candidate: an action per step, or a pose per step, or both (the same length).
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CandidateInput {
    /// The actions, one per step (without poses: the motion model moves by them, as a step does).
    #[serde(default)]
    #[schema(schema_with = schemas::optional_actions)]
    actions: Option<Vec<Action>>,
    /// The camera pose of each step (with actions: the model is told the actions, the poses are used as given).
    #[serde(default)]
    #[schema(schema_with = schemas::optional_poses)]
    poses: Option<Vec<PoseInput>>,
}

#[derive(Deserialize, ToSchema, Clone, Copy, Debug, Default, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum Which {
    #[default]
    Last,
    All,
    None,
}

#[derive(Deserialize, ToSchema, Clone, Copy, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Every {
    #[schema(minimum = 1)]
    every: usize,
}

#[derive(Deserialize, ToSchema, Clone, Copy, Debug, PartialEq)]
#[serde(untagged)]
pub enum FramesAsked {
    Which(Which),
    Every(Every),
}

impl Default for FramesAsked {
    fn default() -> Self {
        FramesAsked::Which(Which::Last)
    }
}

impl FramesAsked {
    /// The steps (0-based) whose frames the answer carries, of a horizon of `h`.
    fn steps(self, h: usize) -> Res<Vec<usize>> {
        Ok(match self {
            FramesAsked::Which(Which::Last) => vec![h - 1],
            FramesAsked::Which(Which::All) => (0..h).collect(),
            FramesAsked::Which(Which::None) => Vec::new(),
            FramesAsked::Every(Every { every: 0 }) => return Err(ApiError::bad("frames.every", "must be at least 1")),
            FramesAsked::Every(Every { every }) => (every - 1..h).step_by(every).collect(),
        })
    }
}

#[derive(Deserialize, ToSchema, Clone, Copy, Debug, Default, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum FrameFormat {
    #[default]
    Png,
    Latent,
}

/// The candidates as the engine takes them, checked against `limits`, with every fault named by its path.
fn candidates(input: &[CandidateInput], limits: &crate::imagine::Limits) -> Res<Vec<Candidate>> {
    if input.is_empty() || input.len() > limits.candidates {
        return Err(ApiError::bad("candidates", format!("give 1 to {} candidates, got {}", limits.candidates, input.len())));
    }
    let mut horizon = None;
    input
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let at = format!("candidates[{k}]");
            let n = match (&c.actions, &c.poses) {
                (None, None) => return Err(ApiError::bad(format!("{at}.actions"), "give actions, poses, or both")),
                (Some(a), Some(p)) if a.len() != p.len() => {
                    return Err(ApiError::bad(format!("{at}.poses"), format!("{} poses for {} actions: give one of each per step", p.len(), a.len())));
                }
                (Some(a), _) => (a.len(), "actions"),
                (None, Some(p)) => (p.len(), "poses"),
            };
            let field = format!("{at}.{}", n.1);
            if n.0 == 0 || n.0 > limits.horizon {
                return Err(ApiError::bad(field, format!("give 1 to {} steps, got {}", limits.horizon, n.0)));
            }
            if *horizon.get_or_insert(n.0) != n.0 {
                return Err(ApiError::bad(field, format!("{} steps, but candidates[0] has {}: every candidate has the same horizon", n.0, horizon.unwrap_or(0))));
            }
            let actions = c.actions.clone().unwrap_or_else(|| vec![Action::default(); n.0]);
            for (h, a) in actions.iter().enumerate() {
                validate_action(a, &format!("{at}.actions[{h}]"))?;
            }
            let poses = c.poses.as_ref().map(|p| p.iter().enumerate().map(|(h, p)| pose_from(p, &format!("{at}.poses[{h}]"))).collect::<Res<Vec<_>>>()).transpose()?;
            Ok(Candidate { actions, poses })
        })
        .collect()
}

#[utoipa::path(post, path = "/v1/sessions/{id}/imagine", summary = "Imagine K candidate futures of H steps from the session's present, without writing to it",
    description = "Each candidate reads the session's memory and its own earlier imagined frames, as a fork stepped H times would; step h of \
                   every candidate runs in one batched model call. Every candidate has the same number of steps, within the server's limits on \
                   candidates, steps and the bytes of frames answered (400 naming the field beyond them). The session, its memory and the \
                   store are left as they were. With a \
                   goal image, each candidate's last frame is scored against it: PSNR of the pictures (dB, higher is closer) and the mean \
                   squared difference of the model's latents (lower is closer); scored by latents alone, a last step whose frame is not \
                   answered is not decoded.",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    request_body = ImagineRequest,
    responses(
        (status = 200, body = ImagineAnswer),
        (status = 400, description = "a field is missing or wrong, or beyond the limits on candidates, horizon or answer size (the body names it)", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 409, description = "the server runs without a model (memory only)", body = ErrorBody),
        (status = 413, description = "the body is larger than the server's limit", body = ErrorBody),
        (status = 415, description = "the body is not application/json", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session", body = ErrorBody),
        (status = 503, description = "too many model calls in flight, or a dependency (field `store` or `triton`) unreachable; retry", body = ErrorBody)))]
pub async fn imagine(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<ImagineAnswer>> {
    let started = Instant::now();
    let id = session_id(id)?;
    let req: ImagineRequest = parse(&headers, body)?;
    let limits = st.config.imagine;
    let candidates = candidates(&req.candidates, &limits)?;
    let horizon = candidates[0].actions.len();
    let steps = req.frames.steps(horizon)?;
    if let Some(seed) = req.seed {
        check_id("seed", seed)?;
    }
    let m = st.engine.model()?;
    let sampler = sampler(&st.config, m, req.steps)?;
    let (img, latent) = (&m.manifest().image, &m.manifest().autoencoder.latent);
    let (width, height) = (img.width, img.height);
    let latent_shape = [latent.channels, latent.height, latent.width];
    let per_frame = match req.format {
        FrameFormat::Png => img.width * img.height * img.channels + img.height + 1024,
        FrameFormat::Latent => latent.len() * 4,
    };
    let answer_bytes = per_frame * steps.len() * candidates.len();
    if answer_bytes > limits.answer_bytes {
        return Err(ApiError::bad("frames", format!(
            "{} frames of up to {per_frame} bytes would answer about {answer_bytes} bytes, over the limit of {}: ask for fewer (\"last\", {{\"every\": n}}), latents, or fewer candidates",
            steps.len() * candidates.len(), limits.answer_bytes)));
    }
    let goal = match &req.goal_png {
        Some(b64) => {
            let (rgb, w, h) = decode_png("goal_png", b64)?;
            if (w as usize, h as usize) != (img.width, img.height) {
                return Err(ApiError::bad("goal_png", format!("is {w}×{h}; the model's frames are {}×{}", img.width, img.height)));
            }
            Some((rgb, w, h))
        }
        None => None,
    };
    // The last step's frame is decoded only when someone looks at it: answered, or scored as a picture.
    let pictured = steps.last() == Some(&(horizon - 1)) || (goal.is_some() && req.goal_score == GoalScoring::Both);
    let last = if pictured { Last::Frame } else { Last::Latent };
    let slot = slot(&st, id, &caller)?;
    let s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let (format, scoring) = (req.format, req.goal_score);
    let mut out = blocking(move || {
        let e = &st2.engine;
        let goal = goal
            .map(|(rgb, w, h)| {
                let latent = e.latent_of(&rgb, w, h, &e.model()?.manifest().intrinsics, "goal_png")?;
                Ok::<_, ApiError>((rgb, latent))
            })
            .transpose()?;
        let imagined = e.imagine(&s, &candidates, &sampler, req.seed, last)?;
        let t = Instant::now();
        let answers = imagined
            .rollouts
            .iter()
            .map(|rollout| CandidateAnswer {
                poses: rollout.iter().map(|f| PoseAnswer::of(&f.pose)).collect(),
                frames: steps
                    .iter()
                    .map(|&h| {
                        let f = &rollout[h];
                        let (image_png, latent) = match format {
                            FrameFormat::Png => (Some(B64.encode(encode_png(width as u32, height as u32, &f.rgb))), None),
                            FrameFormat::Latent => (None, Some(B64.encode(f.latent.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>()))),
                        };
                        ImaginedFrame { step: h, index: s.len() + h as u64, time: f.time, image_png, latent }
                    })
                    .collect(),
                goal: goal
                    .as_ref()
                    .and_then(|(rgb, lat)| rollout.last().map(|f| goal_score(f, (scoring == GoalScoring::Both).then_some(rgb.as_slice()), lat)))
                    .map(|g| GoalAnswer { psnr_db: g.psnr_db, latent_mse: g.latent_mse }),
            })
            .collect();
        Ok(ImagineAnswer {
            session: s.id,
            from: s.len(),
            horizon,
            candidates: answers,
            latent_shape: (format == FrameFormat::Latent).then_some(latent_shape),
            steps: sampler.len(),
            model_calls: imagined.calls,
            frames_made: imagined.made,
            timings_ms: ImagineTimings {
                select: imagined.select_ms,
                warp: imagined.warp_ms,
                sample: imagined.sample_ms,
                decode: imagined.decode_ms,
                encode: t.elapsed().as_secs_f64() * 1e3,
                total: 0.0,
            },
        })
    })
    .await?;
    let frames = (out.horizon * out.candidates.len()) as u64;
    st.metrics.imagined_frames.fetch_add(frames, Ordering::Relaxed);
    out.timings_ms.total = started.elapsed().as_secs_f64() * 1e3;
    Ok(Json(out))
}

#[derive(Serialize, ToSchema)]
pub struct ImagineAnswer {
    pub session: u64,
    /// The session's frame count, unchanged: step h of a candidate would have been frame `from + h`.
    pub from: u64,
    /// Steps per candidate (H).
    pub horizon: usize,
    /// One per candidate, in the request's order.
    pub candidates: Vec<CandidateAnswer>,
    /// The shape of each latent (channels, height, width) when the format is `latent`.
    pub latent_shape: Option<[usize; 3]>,
    /// Sampler steps per frame.
    pub steps: usize,
    /// Model calls made: one per step, every candidate in it.
    pub model_calls: usize,
    /// Frames the model made, at most K × H: candidates whose actions (and poses) agree up to a
    /// step share the frames made so far, since the noise seed is per step, not per candidate.
    pub frames_made: usize,
    /// Milliseconds.
    pub timings_ms: ImagineTimings,
}

#[derive(Serialize, ToSchema)]
pub struct CandidateAnswer {
    /// The camera pose of every imagined step.
    pub poses: Vec<PoseAnswer>,
    /// The frames asked for.
    pub frames: Vec<ImaginedFrame>,
    /// With a goal image: the last frame scored against it.
    pub goal: Option<GoalAnswer>,
}

#[derive(Serialize, ToSchema)]
pub struct ImaginedFrame {
    /// The step of the horizon (0-based).
    pub step: usize,
    /// The index it would have had in the session.
    pub index: u64,
    pub time: u64,
    /// The frame, a base64 PNG (format `png`).
    #[schema(content_encoding = "base64")]
    pub image_png: Option<String>,
    /// The model's scaled latent, f32 little-endian, base64 (format `latent`; shape in `latent_shape`).
    #[schema(content_encoding = "base64")]
    pub latent: Option<String>,
}

/// A frame against the goal image.
#[derive(Serialize, ToSchema)]
pub struct GoalAnswer {
    /// PSNR of the pictures, dB (higher is closer; 100 when equal); null with `goal_score` `"latent"`.
    pub psnr_db: Option<f64>,
    /// Mean squared difference of the model's latents (lower is closer).
    pub latent_mse: f64,
}

#[derive(Serialize, ToSchema)]
pub struct ImagineTimings {
    /// Poses, plans and warp sources, over every candidate and step.
    pub select: f64,
    pub warp: f64,
    pub sample: f64,
    pub decode: f64,
    /// Encoding the frames answered (PNG or base64).
    pub encode: f64,
    pub total: f64,
}
