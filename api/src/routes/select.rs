//! `POST /v1/sessions/{id}/select`: the context plan for a query pose, as a dry run.

use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::HeaderMap;
use memory::covisibility::{CoVisibility, CoVisibilityStats};
use memory::input::PoseInput;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use crate::schemas;
use crate::auth::Caller;
use crate::error::{ApiError, ErrorBody};
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
    /// Occlusion-aware selection: rank the policy's frustum candidates by the
    /// share of the query view's expected surface each saw unoccluded, from
    /// the depth of the session's observed frames (`{}` for the defaults).
    covisibility: Option<CoVisibilityInput>,
}

/// Settings of occlusion-aware selection (memory::covisibility); each defaults when left out.
#[derive(Deserialize, ToSchema, Default)]
#[serde(deny_unknown_fields)]
pub struct CoVisibilityInput {
    /// Frames kept from the frustum stage (default 32).
    #[schema(minimum = 1, maximum = 4096)]
    candidates: Option<usize>,
    /// Frames with depth whose surfaces make the query view's expected surface (default 3).
    #[schema(minimum = 1, maximum = 64)]
    sources: Option<usize>,
    /// Columns of the coarse depth grid (default 16).
    #[schema(minimum = 1, maximum = 256)]
    cells: Option<u32>,
    /// How much deeper than a frame's recorded surface a point may lie and still count as seen, relative (default 0.1).
    #[schema(minimum = 0.0, maximum = 10.0)]
    tolerance: Option<f64>,
}

impl CoVisibilityInput {
    fn settings(&self) -> Result<CoVisibility, ApiError> {
        let d = CoVisibility::default();
        let limit = |field: &str, v: usize, max: usize| {
            if (1..=max).contains(&v) { Ok(v) } else { Err(ApiError::bad(format!("covisibility.{field}"), format!("must be from 1 to {max}, got {v}"))) }
        };
        let tolerance = self.tolerance.unwrap_or(d.tolerance);
        if !(0.0..=10.0).contains(&tolerance) {
            return Err(ApiError::bad("covisibility.tolerance", format!("must be from 0 to 10, got {tolerance}")));
        }
        Ok(CoVisibility {
            candidates: limit("candidates", self.candidates.unwrap_or(d.candidates), 4096)?,
            sources: limit("sources", self.sources.unwrap_or(d.sources), 64)?,
            cells: limit("cells", self.cells.unwrap_or(d.cells) as usize, 256)? as u32,
            tolerance,
        })
    }
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
    let covisibility = req.covisibility.as_ref().map(CoVisibilityInput::settings).transpose()?;
    let slot = slot(&st, id, &caller)?;
    let s = lock(&st, &slot).await?;
    // Selection over a long history is CPU work: off the async workers.
    let out = blocking(move || {
        let t = Instant::now();
        let frustum = s.frustum(pose)?;
        let (plan, exact_evaluations, covisibility) = match covisibility {
            None => {
                let (plan, stats) = s.memory.select(&s.policy, &frustum, None);
                (plan, stats.overlap_evaluations, None)
            }
            Some(c) => {
                let grids = s.depth_grids(c.cells)?;
                let (plan, stats) = memory::covisibility::select(&s.memory, &s.policy, &frustum, &c, None, |id| grids.get(&id))?;
                (plan, 0, Some(stats))
            }
        };
        Ok(Selected {
            session: id,
            plan: PlanAnswer::of(&s.policy, &plan),
            exact_evaluations,
            candidates: s.frames.len(),
            select_ms: t.elapsed().as_secs_f64() * 1e3,
            covisibility,
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
