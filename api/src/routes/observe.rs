//! `POST /v1/sessions/{id}/observe`: a real frame (and depth) with its pose.

use std::sync::atomic::Ordering;

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

use crate::schemas;
use crate::auth::Caller;
use crate::error::{ApiError, ErrorBody};
use super::request::{parse, session_id, decode_png, pose_from, validate_action};
use super::access::{slot, lock, permit, blocking};
use super::{Res, St};

/// A real frame with its pose.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ObserveRequest {
    /// A PNG (RGB, RGBA, grey or palette; 16-bit channels are cut to 8), base64, of the session's image size.
    #[schema(content_encoding = "base64")]
    image_png: String,
    #[schema(schema_with = schemas::pose_ref)]
    pose: PoseInput,
    /// The action that led here, when known.
    #[serde(default)]
    #[schema(schema_with = schemas::optional_action)]
    action: Option<Action>,
    /// Depth as a 16-bit grayscale PNG in millimetres (0 = unknown), the image's size, base64.
    #[serde(default)]
    #[schema(content_encoding = "base64")]
    depth_png16: Option<String>,
}

/// Checks a depth PNG (16-bit grayscale, `w`×`h`) and returns its bytes as sent.
fn depth_png(b64: &str, w: u32, h: u32) -> Res<Vec<u8>> {
    let field = "depth_png16";
    let bytes = B64.decode(b64.trim()).map_err(|e| ApiError::bad(field, format!("not base64: {e}")))?;
    let (_, dw, dh) = world::picture::decode_depth_png16(&bytes).map_err(|e| ApiError::bad(field, e))?;
    if (dw, dh) != (w, h) {
        return Err(ApiError::bad(field, format!("is {dw}x{dh}, the image is {w}x{h}")));
    }
    Ok(bytes)
}

#[utoipa::path(post, path = "/v1/sessions/{id}/observe", summary = "Append a real frame with its pose (encoded when a model is loaded); answered after the commit",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    request_body = ObserveRequest,
    responses(
        (status = 200, body = Observed),
        (status = 400, description = "a field is missing or wrong (the body names it)", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 409, description = "another replica stored that frame index first (a shared store): observe again", body = ErrorBody),
        (status = 413, description = "the body is larger than the server's limit", body = ErrorBody),
        (status = 415, description = "the body is not application/json", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session", body = ErrorBody),
        (status = 503, description = "too many model calls in flight, or a dependency (field `store` or `triton`) unreachable; retry", body = ErrorBody)))]
pub async fn observe(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Observed>> {
    let id = session_id(id)?;
    let req: ObserveRequest = parse(&headers, body)?;
    if let Some(a) = &req.action {
        validate_action(a, "action")?;
    }
    let pose = pose_from(&req.pose, "pose")?;
    let (rgb, w, h) = decode_png("image_png", &req.image_png)?;
    let depth = req.depth_png16.as_deref().map(|d| depth_png(d, w, h)).transpose()?.unwrap_or_default();
    let slot = slot(&st, id, &caller)?;
    let mut s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let (index, time) = st2.engine.observe(&mut s, &rgb, w, h, pose, req.action.as_ref(), depth)?;
        Ok(Observed { session: s.id, index, time, has_latent: st2.engine.model.is_some() })
    })
    .await?;
    st.metrics.observes.fetch_add(1, Ordering::Relaxed);
    Ok(Json(out))
}

#[derive(Serialize, ToSchema)]
pub struct Observed {
    pub session: u64,
    pub index: u64,
    pub time: u64,
    /// Whether the frame was encoded (a model is loaded).
    pub has_latent: bool,
}
