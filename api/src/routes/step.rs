//! `POST /v1/sessions/{id}/step`: select, generate, store, answer.

use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::{HeaderMap, StatusCode};
use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use memory::input::PoseInput;
use motion::Action;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::schemas;
use crate::auth::Caller;
use crate::engine::StepOptions;
use crate::error::{ApiError, ErrorBody};
use super::request::{parse, session_id, check_id, pose_from, sampler, validate_action};
use super::access::{slot, lock, permit, blocking};
use super::answers::{PoseAnswer, PlanAnswer};
use super::{Res, St};

/// One step of the world model.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StepRequest {
    #[schema(schema_with = schemas::action)]
    action: Action,
    /// The next camera pose, for sessions of real frames (the kinematic motion model is used without it).
    #[serde(default)]
    #[schema(schema_with = schemas::optional_pose)]
    pose: Option<PoseInput>,
    /// Sampler steps (default: the server's --steps).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 1000)]
    steps: Option<usize>,
    /// Noise seed (default: derived from the frame's time).
    #[serde(default)]
    #[schema(maximum = 9223372036854775807_u64)]
    seed: Option<u64>,
    /// The index the new frame must get: the step is refused with 409 when
    /// the session has moved on, so a client that lost an answer can send
    /// the step again without stepping twice.
    #[serde(default)]
    #[schema(maximum = 9223372036854775807_u64)]
    expected_index: Option<u64>,
    /// Synthetic sessions only: move by the action and record the world's
    /// true frame and depth there as an observed frame, instead of
    /// generating one (exploration, as a robot's camera would see it).
    #[serde(default)]
    observe: bool,
    /// Synthetic sessions: score the frame against the world's true frame
    /// (`truth` in the answer). `false` skips rendering it: at 224×224 that
    /// costs about as much as the model's step.
    #[serde(default = "yes")]
    truth: bool,
}

fn yes() -> bool {
    true
}

#[utoipa::path(post, path = "/v1/sessions/{id}/step", summary = "Select memories, generate the next frame, store it (durable before the answer)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    request_body = StepRequest,
    responses(
        (status = 200, body = StepAnswer),
        (status = 400, description = "a field is missing or wrong (the body names it)", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 409, description = "the server runs without a model (memory only), the session's next index is not `expected_index`, or another replica stored that index first", body = ErrorBody),
        (status = 413, description = "the body is larger than the server's limit", body = ErrorBody),
        (status = 415, description = "the body is not application/json", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session", body = ErrorBody),
        (status = 503, description = "too many model calls in flight, or a dependency (field `store` or `triton`) unreachable; retry", body = ErrorBody)))]
pub async fn step(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<StepAnswer>> {
    let started = Instant::now();
    let id = session_id(id)?;
    let req: StepRequest = parse(&headers, body)?;
    validate_action(&req.action, "action")?;
    let m = st.engine.model()?;
    let sampler = sampler(&st.config, m, req.steps)?;
    if let Some(seed) = req.seed {
        check_id("seed", seed)?;
    }
    let provider = Some(m.provider().to_string());
    let slot = slot(&st, id, &caller)?;
    let mut s = lock(&st, &slot).await?;
    if let Some(expected) = req.expected_index {
        let next = s.len();
        if expected != next {
            return Err(ApiError::new(StatusCode::CONFLICT, "expected_index", format!("the session's next frame is {next}, not {expected}")));
        }
    }
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let pose = req.pose.as_ref().map(|p| pose_from(p, "pose")).transpose()?;
        let o = if req.observe {
            if pose.is_some() {
                return Err(ApiError::bad("observe", "an observing step moves by the world's physics; leave out pose"));
            }
            st2.engine.step_observed(&mut s, &req.action)?
        } else {
            st2.engine.step(&mut s, &req.action, &sampler, &StepOptions { pose, seed: req.seed, truth: req.truth })?
        };
        let [select, warp, sample, decode, full_size, truth, store] = o.timings_ms;
        let k = s.intrinsics();
        Ok(StepAnswer {
            session: s.id,
            index: o.index,
            time: o.time,
            pose: PoseAnswer::of(&o.pose),
            source: if o.observed { crate::session::OBSERVED } else { crate::session::GENERATED }.into(),
            image_png: B64.encode(&o.png),
            width: k.width,
            height: k.height,
            steps: sampler.len(),
            provider,
            selection: Selection { plan: PlanAnswer::of(&s.policy, &o.plan), layout: o.layout, exact_evaluations: o.exact_evaluations, warp_frames: o.warp_frames },
            timings_ms: StepTimings { select, warp, sample, decode, full_size, truth, store, total: 0.0 },
            truth: o.truth.map(|t| TruthAnswer { psnr_db: t.psnr_db, ssim: t.ssim, image: format!("/v1/sessions/{}/frames/{}/truth", s.id, o.index) }),
        })
    })
    .await?;
    let micros = started.elapsed().as_micros() as u64;
    st.metrics.steps.fetch_add(1, Ordering::Relaxed);
    st.metrics.step_micros.fetch_add(micros, Ordering::Relaxed);
    let mut out = out;
    out.timings_ms.total = micros as f64 / 1e3;
    Ok(Json(out))
}

#[derive(Serialize, ToSchema)]
pub struct Selection {
    pub plan: PlanAnswer,
    /// The model's context layout the plan was packed into.
    pub layout: String,
    /// Exact frustum-overlap evaluations the selection needed.
    pub exact_evaluations: usize,
    /// The observed frames with depth a geometry model warped into the new
    /// view, best first (empty for other models, or when no frame with depth sees it).
    pub warp_frames: Vec<u64>,
}

#[derive(Serialize, ToSchema)]
pub struct StepTimings {
    pub select: f64,
    /// Warping and encoding a geometry model's warp input (0 for other models).
    pub warp: f64,
    pub sample: f64,
    pub decode: f64,
    /// Showing the model's frame at the session's size (`model::full_size`;
    /// 0 when the session is at the model's size).
    pub full_size: f64,
    /// Rendering a synthetic session's true frame and scoring against it (0 otherwise).
    pub truth: f64,
    pub store: f64,
    /// From the request's arrival to the answer.
    pub total: f64,
}

/// A synthetic session's generated frame against the world's true frame at its pose.
#[derive(Serialize, ToSchema)]
pub struct TruthAnswer {
    pub psnr_db: f64,
    pub ssim: f64,
    /// Path of the true frame's PNG.
    pub image: String,
}

#[derive(Serialize, ToSchema)]
pub struct StepAnswer {
    pub session: u64,
    /// The new frame's index in the session.
    pub index: u64,
    pub time: u64,
    pub pose: PoseAnswer,
    /// `generated`, or `observed` for an observing step.
    pub source: String,
    /// The generated frame, a base64 PNG at the session's size.
    #[schema(content_encoding = "base64")]
    pub image_png: String,
    /// The frame's size: the session's (its frames' size, or a synthetic
    /// session's `size`), not the model's. Where the session is larger than
    /// the model, stored frames are shown where they land in this view and
    /// agree with the model's frame; the model's frame, brought up, elsewhere.
    pub width: u32,
    pub height: u32,
    /// Sampler steps used.
    pub steps: usize,
    pub provider: Option<String>,
    pub selection: Selection,
    /// Milliseconds.
    pub timings_ms: StepTimings,
    /// Synthetic sessions only (null otherwise).
    pub truth: Option<TruthAnswer>,
}
