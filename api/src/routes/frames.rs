//! `/v1/sessions/{id}/frames/{index}`: a stored frame, its image, depth and the world's true frame.

use std::sync::Arc;

use axum::Json;
use axum::extract::{Path, State};
use axum::extract::rejection::PathRejection;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;
use world::picture::encode_png;

use crate::state::AppState;
use crate::auth::Caller;
use crate::error::{ApiError, ErrorBody};
use crate::schemas::MAX_ID;
use crate::store::FrameRecord;
use super::request::check_id;
use super::access::{slot, lock, blocking};
use super::answers::PoseAnswer;
use super::{Res, St};

fn frame_ids(p: Result<Path<(u64, u64)>, PathRejection>) -> Res<(u64, u64)> {
    let (id, index) = p.map(|Path(v)| v).map_err(|_| ApiError::bad("index", format!("session ids and frame indices are whole numbers from 0 to {MAX_ID}")))?;
    Ok((check_id("session", id)?, check_id("index", index)?))
}

/// A stored frame of a live session, read off the async workers; 404 naming what is missing.
async fn stored_frame(st: &Arc<AppState>, p: Result<Path<(u64, u64)>, PathRejection>, caller: &Caller) -> Res<(u64, u64, FrameRecord)> {
    let (id, index) = frame_ids(p)?;
    slot(st, id, caller)?;
    let st2 = st.clone();
    let f = blocking(move || st2.engine.store.frame(id, index).map_err(ApiError::from)).await?;
    let f = f.ok_or_else(|| ApiError::not_found("index", format!("session {id} has no frame {index}")))?;
    Ok((id, index, f))
}

#[utoipa::path(get, path = "/v1/sessions/{id}/frames/{index}", summary = "One stored frame: time, source (observed/generated), pose, action",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64),
           ("index" = u64, Path, description = "frame index in the session", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 200, body = FrameInfo), (status = 400, description = "the id or index is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session, frame (or depth, or true frame)", body = ErrorBody)))]
pub async fn frame(State(st): St, caller: Caller, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Json<FrameInfo>> {
    let (id, index, f) = stored_frame(&st, p, &caller).await?;
    let pose = crate::session::pose_of(&f.meta)?;
    Ok(Json(FrameInfo {
        session: id,
        index,
        time: f.meta.time,
        source: f.meta.source.clone(),
        pose: PoseAnswer::of(&pose),
        action: f.meta.action.clone(),
        has_latent: !f.latent.is_empty(),
        image: format!("/v1/sessions/{id}/frames/{index}/image"),
        depth: (!f.depth_png16.is_empty()).then(|| format!("/v1/sessions/{id}/frames/{index}/depth")),
    }))
}

#[utoipa::path(get, path = "/v1/sessions/{id}/frames/{index}/image", summary = "A stored frame's image (PNG)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64),
           ("index" = u64, Path, description = "frame index in the session", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 200, description = "the frame", content_type = "image/png", body = Vec<u8>), (status = 400, description = "the id or index is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session, frame (or depth, or true frame)", body = ErrorBody)))]
pub async fn frame_image(State(st): St, caller: Caller, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (_, _, f) = stored_frame(&st, p, &caller).await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], f.png).into_response())
}

#[utoipa::path(get, path = "/v1/sessions/{id}/frames/{index}/depth", summary = "A stored frame's depth: 16-bit grayscale PNG in millimetres (0 = unknown)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64),
           ("index" = u64, Path, description = "frame index in the session", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 200, description = "the depth", content_type = "image/png", body = Vec<u8>), (status = 400, description = "the id or index is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session, frame (or depth, or true frame)", body = ErrorBody)))]
pub async fn frame_depth(State(st): St, caller: Caller, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (id, index, f) = stored_frame(&st, p, &caller).await?;
    if f.depth_png16.is_empty() {
        return Err(ApiError::not_found("depth", format!("frame {index} of session {id} was stored without depth")));
    }
    Ok(([(header::CONTENT_TYPE, "image/png")], f.depth_png16).into_response())
}

/// The synthetic world's true frame at a stored frame's pose, so a user can
/// see how far generated frames drift; 404 for sessions of real frames.
#[utoipa::path(get, path = "/v1/sessions/{id}/frames/{index}/truth", summary = "A synthetic session's true frame at a stored frame's pose (PNG)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64),
           ("index" = u64, Path, description = "frame index in the session", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 200, description = "the world's frame", content_type = "image/png", body = Vec<u8>), (status = 400, description = "the id or index is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session, frame (or depth, or true frame)", body = ErrorBody)))]
pub async fn frame_truth(State(st): St, caller: Caller, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (id, _, f) = stored_frame(&st, p, &caller).await?;
    let pose = crate::session::pose_of(&f.meta)?;
    let slot = slot(&st, id, &caller)?;
    let s = lock(&st, &slot).await?;
    let st2 = st.clone();
    let png = blocking(move || {
        let rgb = st2.engine.truth_at(&s, &pose)?.ok_or_else(|| {
            ApiError::not_found("truth", format!("session {id} is not synthetic: only a synthetic world has a true frame"))
        })?;
        let k = s.intrinsics();
        Ok(encode_png(k.width, k.height, &rgb))
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}

#[derive(Serialize, ToSchema)]
pub struct FrameInfo {
    pub session: u64,
    pub index: u64,
    pub time: u64,
    /// `observed` (sent by a caller) or `generated` (made by the model).
    pub source: String,
    pub pose: PoseAnswer,
    /// The action that led to the frame: forward, back, left, right, jump (0/1), yaw and pitch deltas (degrees).
    pub action: Option<Vec<f32>>,
    pub has_latent: bool,
    /// Path of the frame's PNG.
    pub image: String,
    /// Path of its 16-bit depth PNG, when it was stored with depth.
    pub depth: Option<String>,
}
