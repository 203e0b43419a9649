//! `POST /v1/sessions/{id}/select`: the context plan for a query pose, as a dry run.

use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::HeaderMap;
use memory::{CoVisibility, Policy};
use memory::covisibility::CoVisibilityStats;
use memory::input::PoseInput;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::schemas;
use crate::auth::Caller;
use crate::error::ErrorBody;
use super::request::{parse, session_id, pose_from};
use super::access::{slot, lock, blocking};
use super::answers::PlanAnswer;
use super::{Res, St};

/// A query pose for a dry run of the session's policy.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SelectRequest {
    #[schema(schema_with = schemas::pose_ref)]
    pose: PoseInput,
    /// Occlusion-aware selection for this query, in place of the policy's own
    /// setting (`{}` for the defaults); absent: as the session's policy says.
    #[schema(schema_with = schemas::optional_covisibility)]
    covisibility: Option<CoVisibility>,
}

#[utoipa::path(post, path = "/v1/sessions/{id}/select", summary = "The context plan the session's policy would choose for a query pose (dry run)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    request_body = SelectRequest,
    responses(
        (status = 200, body = Selected),
        (status = 400, description = "a field is missing or wrong (the body names it)", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 413, description = "the body is larger than the server's limit", body = ErrorBody),
        (status = 415, description = "the body is not application/json", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session", body = ErrorBody)))]
pub async fn select(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Selected>> {
    let id = session_id(id)?;
    let req: SelectRequest = parse(&headers, body)?;
    let pose = pose_from(&req.pose, "pose")?;
    let covisibility = req.covisibility.map(CoVisibility::validated).transpose()?;
    let slot = slot(&st, id, &caller)?;
    let s = lock(&st, &slot).await?;
    // Selection over a long history is CPU work: off the async workers.
    let out = blocking(move || {
        let t = Instant::now();
        let frustum = s.frustum(pose)?;
        let policy = Policy { covisibility: covisibility.or(s.policy.covisibility), ..s.policy.clone() };
        let selection = s.plan(&policy, &frustum, None)?;
        let plan = selection.plan;
        Ok(Selected {
            session: id,
            plan: PlanAnswer::of(&s.policy, &plan),
            exact_evaluations: selection.stats.overlap_evaluations,
            candidates: s.len() as usize,
            select_ms: t.elapsed().as_secs_f64() * 1e3,
            covisibility: selection.covisibility,
        })
    })
    .await?;
    st.metrics.selects.fetch_add(1, Ordering::Relaxed);
    Ok(Json(out))
}

#[derive(Serialize, ToSchema)]
pub struct Selected {
    pub session: u64,
    pub plan: PlanAnswer,
    /// Exact overlaps computed (0 with `covisibility`, which reports its own counts).
    pub exact_evaluations: usize,
    /// Stored frames the policy chose from.
    pub candidates: usize,
    pub select_ms: f64,
    /// With `covisibility`: the frustum stage's candidates, how many had depth, and the expected surface's points.
    #[schema(value_type = Option<Object>)]
    #[serde(skip_serializing_if = "Option::is_none")]
    pub covisibility: Option<CoVisibilityStats>,
}
