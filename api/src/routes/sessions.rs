//! `/v1/sessions` and `/v1/sessions/{id}`: create, list, describe, delete.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::http::{HeaderMap, StatusCode};
use memory::{Intrinsics, Policy};
use memory::input::{IntrinsicsInput, PoseInput};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;
use world::picture::encode_png;

use crate::{Slot, schemas};
use crate::auth::Caller;
use crate::engine::meta;
use crate::error::{ApiError, ErrorBody};
use crate::session::policy_of;
use crate::store::{FrameRecord, SessionRecord};
use super::request::{parse, session_id, check_id, decode_png, pose_from};
use super::access::{slot, lock, permit, blocking, within_session_limit};
use super::{Res, St};

/// A new session: a synthetic world (by seed), or real frames with their
/// poses and the camera's intrinsics; not both.
#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CreateRequest {
    #[serde(default)]
    #[schema(schema_with = schemas::optional_policy)]
    policy: Option<Value>,
    #[serde(default)]
    synthetic: Option<SyntheticStart>,
    #[serde(default)]
    #[schema(min_items = 1)]
    frames: Option<Vec<FrameInput>>,
    #[serde(default)]
    #[schema(schema_with = schemas::optional_intrinsics)]
    intrinsics: Option<IntrinsicsInput>,
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SyntheticStart {
    /// The world's seed.
    #[schema(maximum = 9223372036854775807_u64)]
    seed: u64,
    /// Start on this biome (the world must have it).
    #[serde(default)]
    #[schema(schema_with = schemas::optional_biome)]
    biome: Option<world::Biome>,
    /// The width of the session's frames in pixels (default: the model's);
    /// the height keeps the model's aspect. The model still sees its own
    /// size; steps answer at this one. At most the server's `--max-frame-side`.
    #[serde(default)]
    #[schema(minimum = 8)]
    size: Option<u32>,
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameInput {
    /// A PNG (RGB, RGBA, grey or palette; 16-bit channels are cut to 8), base64,
    /// of the intrinsics' size: the session's size, which steps answer at (at most the server's `--max-frame-side`).
    #[schema(content_encoding = "base64")]
    image_png: String,
    #[schema(schema_with = schemas::pose_ref)]
    pose: PoseInput,
}

#[utoipa::path(post, path = "/v1/sessions", summary = "Create a session (synthetic world or real frames); answered after the commit",
    request_body = CreateRequest,
    responses(
        (status = 201, body = Created),
        (status = 400, description = "a field is missing or wrong (the body names it)", body = ErrorBody),
        (status = 413, description = "the body is larger than the server's limit", body = ErrorBody),
        (status = 415, description = "the body is not application/json", body = ErrorBody),
        (status = 503, description = "too many model calls in flight, or a dependency (field `store` or `triton`) unreachable; retry", body = ErrorBody)))]
pub async fn create(State(st): St, caller: Caller, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<(StatusCode, Json<Created>)> {
    let req: CreateRequest = parse(&headers, body)?;
    if let Some(s) = &req.synthetic {
        check_id("synthetic.seed", s.seed)?;
    }
    let policy_spec = req.policy.unwrap_or_else(|| st.config.policy.clone());
    policy_of(&policy_spec)?;
    within_session_limit(&st, &caller)?;
    let tenant = caller.0.clone();
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let (id, frames) = blocking(move || {
        let e = &st2.engine;
        let session = match (req.synthetic, req.frames) {
            (Some(_), Some(_)) => return Err(ApiError::bad("frames", "give either synthetic or frames, not both")),
            (None, None) => return Err(ApiError::bad("frames", "give initial frames (with intrinsics) or a synthetic world seed")),
            (Some(s), None) => {
                if req.intrinsics.is_some() {
                    return Err(ApiError::bad("intrinsics", "a synthetic session uses the model's camera"));
                }
                e.create_synthetic(policy_spec, s.seed, s.biome, s.size, tenant)?
            }
            (None, Some(frames)) => {
                let k = req.intrinsics.ok_or_else(|| ApiError::bad("intrinsics", "required with frames"))?.resolve().map_err(|e| e.within("intrinsics"))?;
                e.check_frame_size("intrinsics.width", k.width, k.height)?;
                let mut records = Vec::new();
                for (i, f) in frames.iter().enumerate() {
                    let at = format!("frames[{i}]");
                    let pose = pose_from(&f.pose, &format!("{at}.pose"))?;
                    let (rgb, w, h) = decode_png(&format!("{at}.image_png"), &f.image_png)?;
                    let latent = e.latent_of(&rgb, w, h, &k, &format!("{at}.image_png"))?;
                    records.push(FrameRecord { meta: meta(&pose, i as u64, "observed", None, None), latent, png: encode_png(w, h, &rgb), depth_png16: Vec::new() });
                }
                e.create(SessionRecord { policy: policy_spec, intrinsics: k, world_seed: None, tenant, fork: None }, records, None)?
            }
        };
        let (id, n) = (session.id, session.len() as usize);
        st2.sessions.write().unwrap().insert(id, Arc::new(Slot::new(session)));
        Ok((id, n))
    })
    .await?;
    st.metrics.sessions_created.fetch_add(1, Ordering::Relaxed);
    Ok((StatusCode::CREATED, Json(Created { session: id, frames })))
}

#[utoipa::path(get, path = "/v1/sessions", summary = "The caller's sessions (with tokens: its tenant's), by id",
    responses((status = 200, body = SessionList)))]
pub async fn list(State(st): St, caller: Caller) -> Res<Json<SessionList>> {
    let mut sessions: Vec<u64> = if st.engine.store.shared() {
        // Replicas share the database: the store knows sessions this one has not seen.
        let st2 = st.clone();
        let all = blocking(move || Ok(st2.engine.store.sessions()?)).await?;
        all.into_iter().filter(|(_, r)| caller.owns(r.tenant.as_deref())).map(|(id, _)| id).collect()
    } else {
        st.sessions.read().unwrap().iter().filter(|(_, s)| caller.owns(s.owner.as_deref())).map(|(id, _)| *id).collect()
    };
    sessions.sort_unstable();
    Ok(Json(SessionList { sessions }))
}

#[derive(Serialize, ToSchema)]
pub struct SessionList {
    pub sessions: Vec<u64>,
}

#[utoipa::path(get, path = "/v1/sessions/{id}", summary = "A session: frames, resolved policy, world seed, intrinsics",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 200, body = SessionInfo), (status = 400, description = "the id is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody), (status = 429, description = "too many requests queued on the session", body = ErrorBody)))]
pub async fn describe(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>) -> Res<Json<SessionInfo>> {
    let id = session_id(id)?;
    let slot = slot(&st, id, &caller)?;
    let s = lock(&st, &slot).await?;
    Ok(Json(SessionInfo {
        session: id,
        frames: s.len() as usize,
        policy: s.policy.clone(),
        world_seed: s.record.world_seed,
        intrinsics: s.record.intrinsics,
        has_latents: s.history().first().is_some_and(|f| !f.latent.is_empty()),
        parent: s.record.fork.map(|f| f.parent),
        forked_at: s.record.fork.map(|f| f.frames),
    }))
}

#[utoipa::path(delete, path = "/v1/sessions/{id}", summary = "Delete a session and its stored frames (durable before the answer)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 204, description = "deleted"), (status = 400, description = "the id is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 409, description = "forks of the session live (field `session`, the message lists them): delete them first", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session", body = ErrorBody)))]
pub async fn delete(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>) -> Res<StatusCode> {
    let id = session_id(id)?;
    let slot = slot(&st, id, &caller)?;
    let mut guard = lock(&st, &slot).await?;
    let st2 = st.clone();
    blocking(move || Ok(st2.engine.store.delete_session(id)?)).await?;
    guard.deleted = true;
    st.sessions.write().unwrap().remove(&id);
    Ok(StatusCode::NO_CONTENT)
}

#[derive(Serialize, ToSchema)]
pub struct Created {
    pub session: u64,
    /// Frames stored with the session.
    pub frames: usize,
}

#[derive(Serialize, ToSchema)]
pub struct SessionInfo {
    pub session: u64,
    pub frames: usize,
    #[schema(schema_with = schemas::resolved_policy_ref)]
    pub policy: Policy,
    /// The synthetic world's seed; null for a session of real frames.
    pub world_seed: Option<u64>,
    #[schema(schema_with = schemas::camera_ref)]
    pub intrinsics: Intrinsics,
    /// Whether stored frames carry latents (a model was loaded when they came).
    pub has_latents: bool,
    /// A fork's session it was forked from (null otherwise).
    pub parent: Option<u64>,
    /// A fork's frames shared with that session (indices below this are its frames).
    pub forked_at: Option<u64>,
}
