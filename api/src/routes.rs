//! The HTTP endpoints (all JSON, under `/v1`), each parsing its request into
//! typed input first so every bad field gets a 4xx naming it.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use memory::input::{IntrinsicsInput, PoseInput};
use memory::covisibility::{CoVisibility, CoVisibilityStats};
use memory::{ContextPlan, Intrinsics, Policy, Pose};
use model::Sampler;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;
use motion::Action;

use crate::auth::Caller;
use crate::error::{ApiError, ErrorBody};
use crate::schemas::{self, MAX_COORDINATE, MAX_ID, MAX_TURN_DEG};
use crate::session::{Session, policy_of};
use crate::engine::meta;
use world::picture::encode_png;
use crate::store::{FrameRecord, SessionRecord};
use crate::{AppState, Slot};

/// The web viewer (docs/viewer.md): one page, embedded, that drives the public API.
const VIEWER: &str = include_str!("viewer.html");

type Res<T> = Result<T, ApiError>;
type St = State<Arc<AppState>>;

pub fn router(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/", get(|| async { axum::response::Redirect::to("/viewer") }))
        .route("/viewer", get(|| async { axum::response::Html(VIEWER) }))
        .route("/v1/health", get(health))
        .route("/v1/ready", get(ready))
        .route("/metrics", get(metrics))
        .route("/v1/sessions", post(create).get(list))
        .route("/v1/sessions/{id}", get(describe).delete(delete))
        .route("/v1/sessions/{id}/step", post(step))
        .route("/v1/sessions/{id}/observe", post(observe))
        .route("/v1/sessions/{id}/select", post(select))
        .route("/v1/sessions/{id}/frames/{index}", get(frame))
        .route("/v1/sessions/{id}/frames/{index}/image", get(frame_image))
        .route("/v1/sessions/{id}/frames/{index}/depth", get(frame_depth))
        .route("/v1/sessions/{id}/frames/{index}/truth", get(frame_truth))
        .fallback(|| async { ApiError::not_found("path", "no such endpoint; see /docs or docs/api.md") })
        .with_state(state)
}

/// A JSON body into `T`: 415 for another content type, 413 when too large,
/// 400 naming the field (`frames[0].pose.c2w.rotation`) when it does not fit.
fn parse<T: DeserializeOwned>(headers: &HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<T> {
    let json = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).is_some_and(|v| v.starts_with("application/json"));
    if !json {
        return Err(ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, "content-type", "send the body as application/json"));
    }
    let bytes = body.map_err(|r| ApiError::new(r.status(), "body", r.body_text()))?;
    let de = &mut serde_json::Deserializer::from_slice(&bytes);
    let first = match serde_path_to_error::deserialize(de) {
        Ok(v) => return Ok(v),
        Err(e) => e,
    };
    // Once more with whole-valued floats as integers; the first error names the field if that fails too.
    let retried = serde_json::from_slice::<Value>(&bytes).ok().and_then(|mut v| {
        integral_floats_as_integers(&mut v);
        serde_json::from_value(v).ok()
    });
    retried.ok_or_else(|| {
        let path = first.path().to_string();
        ApiError::bad(if path == "." { "body".into() } else { path }, first.inner().to_string())
    })
}

/// JSON has one number type and JSON Schema calls 7.0 an integer, so a
/// whole-valued float is taken where an integer is expected (a seed of
/// 7.0); fields that take floats accept integers anyway.
fn integral_floats_as_integers(v: &mut Value) {
    match v {
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or(f64::NAN);
            if x.fract() == 0.0 && (0.0..1.8e19).contains(&x) {
                *v = Value::from(x as u64);
            } else if x.fract() == 0.0 && (-9.2e18..0.0).contains(&x) {
                *v = Value::from(x as i64);
            }
        }
        Value::Array(items) => items.iter_mut().for_each(integral_floats_as_integers),
        Value::Object(map) => map.values_mut().for_each(integral_floats_as_integers),
        _ => {}
    }
}

fn session_id(id: Result<Path<u64>, PathRejection>) -> Res<u64> {
    let id = id.map(|Path(id)| id).map_err(|_| ApiError::bad("session", format!("session ids are whole numbers from 0 to {MAX_ID}")))?;
    check_id("session", id)
}

/// Ids above [`MAX_ID`] are never handed out; the document's bound says so.
fn check_id(field: &str, id: u64) -> Res<u64> {
    if id > MAX_ID {
        return Err(ApiError::bad(field, format!("must be at most {MAX_ID}, got {id}")));
    }
    Ok(id)
}

/// The session `id` if `caller` may see it; another tenant's session is as
/// missing as one that never existed.
fn slot(st: &AppState, id: u64, caller: &Caller) -> Res<Arc<Slot>> {
    let missing = || ApiError::not_found("session", format!("no session {id}"));
    let owned = |slot: Arc<Slot>| if caller.owns(slot.owner.as_deref()) { Ok(slot) } else { Err(missing()) };
    if let Some(slot) = st.sessions.read().unwrap().get(&id).cloned() {
        return owned(slot);
    }
    if !st.engine.store.shared() {
        return Err(missing());
    }
    // Another server on the same database may have made it; its frames are read by `lock`.
    let record = tokio::task::block_in_place(|| st.engine.store.session(id))?.ok_or_else(missing)?;
    let world = record.world_seed.map(|seed| st.engine.world(seed));
    let session = Session::restore(id, record, Vec::new(), world)?;
    let slot = Arc::new(Slot::new(session));
    owned(st.sessions.write().unwrap().entry(id).or_insert(slot).clone())
}

/// On a store other servers write too: indexes the frames stored since this
/// server last saw the session, or marks it deleted when it is gone.
fn catch_up(st: &AppState, s: &mut Session) -> Res<()> {
    if !st.engine.store.shared() {
        return Ok(());
    }
    let started = std::time::Instant::now();
    tokio::task::block_in_place(|| {
        if st.engine.store.session(s.id)?.is_none() {
            s.deleted = true;
            return Ok(());
        }
        let new = st.engine.store.frames_from(s.id, s.frames.len() as u64)?;
        st.metrics.caught_up_frames.fetch_add(new.len() as u64, Ordering::Relaxed);
        s.append_stored(new)
    })?;
    st.metrics.catch_up_micros.fetch_add(started.elapsed().as_micros() as u64, Ordering::Relaxed);
    st.metrics.catch_ups.fetch_add(1, Ordering::Relaxed);
    Ok(())
}

/// Waits for the session, refusing with 429 when too many requests queue on it.
async fn lock(st: &AppState, slot: &Arc<Slot>) -> Res<tokio::sync::OwnedMutexGuard<Session>> {
    let queued = slot.waiting.fetch_add(1, Ordering::SeqCst);
    if queued >= st.config.max_queue_per_session {
        slot.waiting.fetch_sub(1, Ordering::SeqCst);
        return Err(ApiError::new(StatusCode::TOO_MANY_REQUESTS, "session", format!("{queued} requests already queued on this session")));
    }
    let mut guard = slot.session.clone().lock_owned().await;
    slot.waiting.fetch_sub(1, Ordering::SeqCst);
    if !guard.deleted {
        catch_up(st, &mut guard)?;
    }
    if guard.deleted {
        st.sessions.write().unwrap().remove(&guard.id);
        return Err(ApiError::not_found("session", format!("session {} was deleted", guard.id)));
    }
    Ok(guard)
}

fn permit(st: &AppState) -> Res<tokio::sync::SemaphorePermit<'_>> {
    st.inflight.try_acquire().map_err(|_| {
        ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "", format!("busy: {} model calls in flight; retry shortly", st.config.max_inflight))
    })
}

pub(crate) async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Res<T> + Send + 'static) -> Res<T> {
    tokio::task::spawn_blocking(f).await.map_err(ApiError::internal)?
}


/// A PNG (base64) as RGB bytes, width, height.
fn decode_png(field: &str, b64: &str) -> Res<(Vec<u8>, u32, u32)> {
    let bytes = B64.decode(b64.trim()).map_err(|e| ApiError::bad(field, format!("not base64: {e}")))?;
    world::picture::decode_rgb(&bytes).map_err(|e| ApiError::bad(field, e))
}

fn pose_from(input: &PoseInput, field: &str) -> Res<Pose> {
    let pose = input.resolve().map_err(|e| e.within(field))?;
    if pose.position().abs().max_element() > MAX_COORDINATE {
        return Err(ApiError::bad(format!("{field}.position"), format!("must lie within ±{MAX_COORDINATE:e} world units")));
    }
    Ok(pose)
}

fn validate_action(a: &Action) -> Res<()> {
    for (field, v) in [("action.yaw_deg", a.yaw_deg), ("action.pitch_deg", a.pitch_deg)] {
        if !v.is_finite() || v.abs() > MAX_TURN_DEG {
            return Err(ApiError::bad(field, format!("must be a finite angle within ±{MAX_TURN_DEG} degrees, got {v}")));
        }
    }
    Ok(())
}

#[utoipa::path(get, path = "/v1/health", summary = "Liveness, the model served and the live sessions",
    responses((status = 200, body = Health)))]
pub async fn health(State(st): St) -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        model: st.engine.model.as_ref().map(|m| m.manifest().name.clone()),
        provider: st.engine.model.as_ref().map(|m| m.provider().to_string()),
        sessions: st.sessions.read().unwrap().len(),
    })
}

#[utoipa::path(get, path = "/v1/ready", summary = "Readiness: whether every dependency (the store, a remote model backend) answers now",
    responses((status = 200, body = Readiness), (status = 503, body = Readiness, description = "a dependency is down: each one is named with why",
        headers(("Retry-After" = String, description = "seconds before asking again")))))]
pub async fn ready(State(st): St) -> Response {
    let checked = st.clone();
    let (store, model) = tokio::task::spawn_blocking(move || {
        let store = checked.engine.store.ping().map_err(|e| e.to_string());
        let model = checked.engine.model.as_ref().map_or(Ok(()), |m| m.ready().map_err(|e| e.to_string()));
        (store, model)
    })
    .await
    .unwrap_or_else(|e| (Err(e.to_string()), Err("not checked".into())));
    let down: Vec<Dependency> = [("store", store), ("model", model)]
        .into_iter()
        .filter_map(|(name, r)| r.err().map(|message| Dependency { name: name.into(), message }))
        .collect();
    let body = Readiness { ready: down.is_empty(), down };
    if body.ready {
        return (StatusCode::OK, Json(body)).into_response();
    }
    (StatusCode::SERVICE_UNAVAILABLE, [(axum::http::header::RETRY_AFTER, crate::error::RETRY_AFTER_S)], Json(body)).into_response()
}

#[utoipa::path(get, path = "/metrics", summary = "Prometheus counters: steps, observes, selects, sessions, step seconds, shared-store catch-ups",
    responses((status = 200, description = "Prometheus text exposition format", body = String, content_type = "text/plain")))]
pub async fn metrics(State(st): St) -> Response {
    let m = &st.metrics;
    let g = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let batched = st.engine.batcher.as_ref().map(|b| (g(&b.calls), g(&b.items))).unwrap_or((0, 0));
    let text = format!(
        "# TYPE worldpack_steps_total counter\nworldpack_steps_total {}\n\
         # TYPE worldpack_batched_calls_total counter\nworldpack_batched_calls_total {}\n\
         # TYPE worldpack_batched_items_total counter\nworldpack_batched_items_total {}\n\
         # TYPE worldpack_observes_total counter\nworldpack_observes_total {}\n\
         # TYPE worldpack_selects_total counter\nworldpack_selects_total {}\n\
         # TYPE worldpack_sessions_created_total counter\nworldpack_sessions_created_total {}\n\
         # TYPE worldpack_sessions_expired_total counter\nworldpack_sessions_expired_total {}\n\
         # TYPE worldpack_step_seconds_sum counter\nworldpack_step_seconds_sum {}\n\
         # TYPE worldpack_catch_ups_total counter\nworldpack_catch_ups_total {}\n\
         # TYPE worldpack_catch_up_seconds_sum counter\nworldpack_catch_up_seconds_sum {}\n\
         # TYPE worldpack_caught_up_frames_total counter\nworldpack_caught_up_frames_total {}\n\
         # TYPE worldpack_sessions gauge\nworldpack_sessions {}\n",
        g(&m.steps),
        batched.0,
        batched.1,
        g(&m.observes),
        g(&m.selects),
        g(&m.sessions_created),
        g(&m.sessions_expired),
        g(&m.step_micros) as f64 / 1e6,
        g(&m.catch_ups),
        g(&m.catch_up_micros) as f64 / 1e6,
        g(&m.caught_up_frames),
        st.sessions.read().unwrap().len()
    );
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

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
}

#[derive(Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameInput {
    /// A PNG (RGB, RGBA, grey or palette; 16-bit channels are cut to 8), base64, of the intrinsics' size.
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
    if let Some(tenant) = &caller.0 {
        let limit = st.tokens.limits(tenant).sessions;
        let owned = st.sessions.read().unwrap().values().filter(|s| s.owner.as_deref() == Some(tenant)).count();
        if owned >= limit {
            return Err(ApiError::new(StatusCode::TOO_MANY_REQUESTS, "session",
                format!("tenant {tenant} has {owned} live sessions, its limit; delete one first")));
        }
    }
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
                e.create_synthetic(policy_spec, s.seed, s.biome, tenant)?
            }
            (None, Some(frames)) => {
                let k = req.intrinsics.ok_or_else(|| ApiError::bad("intrinsics", "required with frames"))?.resolve().map_err(|e| e.within("intrinsics"))?;
                let mut records = Vec::new();
                for (i, f) in frames.iter().enumerate() {
                    let at = format!("frames[{i}]");
                    let pose = pose_from(&f.pose, &format!("{at}.pose"))?;
                    let (rgb, w, h) = decode_png(&format!("{at}.image_png"), &f.image_png)?;
                    let latent = e.latent_of(&rgb, w, h, &k, &format!("{at}.image_png"))?;
                    records.push(FrameRecord { meta: meta(&pose, i as u64, "observed", None, None), latent, png: encode_png(w, h, &rgb), depth_png16: Vec::new() });
                }
                e.create(SessionRecord { policy: policy_spec, intrinsics: k, world_seed: None, tenant }, records, None)?
            }
        };
        let (id, n) = (session.id, session.frames.len());
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
        frames: s.frames.len(),
        policy: s.policy.clone(),
        world_seed: s.record.world_seed,
        intrinsics: s.record.intrinsics,
        has_latents: s.frames.first().is_some_and(|f| !f.latent.is_empty()),
    }))
}

#[utoipa::path(delete, path = "/v1/sessions/{id}", summary = "Delete a session and its stored frames (durable before the answer)",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    responses((status = 204, description = "deleted"), (status = 400, description = "the id is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody), (status = 429, description = "too many requests queued on the session", body = ErrorBody)))]
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
    validate_action(&req.action)?;
    let Some(m) = &st.engine.model else {
        return Err(ApiError::new(StatusCode::CONFLICT, "model", "this server runs without a model (memory only): use observe"));
    };
    if req.steps.is_some_and(|n| !(1..=1000).contains(&n)) {
        return Err(ApiError::bad("steps", "must be from 1 to 1000"));
    }
    if let Some(seed) = req.seed {
        check_id("seed", seed)?;
    }
    let steps = req.steps.unwrap_or(st.config.steps);
    let sampler = Sampler::new(&m.manifest().diffusion, steps, st.config.method, 0.0)?;
    let slot = slot(&st, id, &caller)?;
    let mut s = lock(&st, &slot).await?;
    if let Some(expected) = req.expected_index {
        let next = s.frames.len() as u64;
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
            st2.engine.step(&mut s, &req.action, pose, &sampler, req.seed)?
        };
        let [select, warp, sample, decode, store] = o.timings_ms;
        Ok(StepAnswer {
            session: s.id,
            index: o.index,
            time: o.time,
            pose: PoseAnswer::of(&o.pose),
            source: if o.observed { crate::session::OBSERVED } else { crate::session::GENERATED }.into(),
            image_png: B64.encode(&o.png),
            steps: sampler.len(),
            provider: st2.engine.model.as_ref().map(|m| m.provider().to_string()),
            selection: Selection { plan: PlanAnswer::of(&s.policy, &o.plan), layout: o.layout, exact_evaluations: o.exact_evaluations, warp_frames: o.warp_frames },
            timings_ms: StepTimings { select, warp, sample, decode, store, total: 0.0 },
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
        validate_action(a)?;
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

// ---- answers -------------------------------------------------------------

#[derive(Serialize, ToSchema)]
pub struct Readiness {
    pub ready: bool,
    /// The dependencies that did not answer, each with why (empty when ready).
    pub down: Vec<Dependency>,
}

#[derive(Serialize, ToSchema)]
pub struct Dependency {
    /// `store` or `model`.
    #[schema(example = "store")]
    pub name: String,
    pub message: String,
}

#[derive(Serialize, ToSchema)]
pub struct Health {
    #[schema(example = "ok")]
    pub status: String,
    /// The model's name, or null for a memory-only server.
    pub model: Option<String>,
    /// The execution provider that runs the denoiser (cpu, cuda), or null.
    pub provider: Option<String>,
    /// Live sessions.
    pub sessions: usize,
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
}

/// A camera pose as the server answers it: OpenCV camera-to-world.
#[derive(Serialize, ToSchema)]
pub struct PoseAnswer {
    /// Row-major 3×3 rotation.
    pub rotation: [[f64; 3]; 3],
    /// The camera centre in world units.
    pub position: [f64; 3],
}

impl PoseAnswer {
    fn of(p: &Pose) -> PoseAnswer {
        PoseAnswer { rotation: p.rotation_rows(), position: p.position().to_array() }
    }
}

/// One context slot: its rate and the stored frame in it (null when empty).
#[derive(Serialize, ToSchema)]
pub struct SlotAnswer {
    pub slot: usize,
    /// Compression rate: 1, 4 or 16.
    pub rate: u32,
    pub frame: Option<u64>,
    pub time: Option<u64>,
    /// Share of the query view the frame's frustum covers.
    pub overlap: Option<f64>,
    pub score: Option<f64>,
}

#[derive(Serialize, ToSchema)]
pub struct PlanAnswer {
    #[schema(example = "worldpack")]
    pub policy: String,
    pub slots: Vec<SlotAnswer>,
}

impl PlanAnswer {
    fn of(policy: &Policy, plan: &ContextPlan) -> PlanAnswer {
        let slots = plan
            .slots
            .iter()
            .enumerate()
            .map(|(i, s)| SlotAnswer {
                slot: i,
                rate: s.rate,
                frame: s.frame.map(|f| f.id),
                time: s.frame.map(|f| f.time),
                overlap: s.frame.map(|f| f.overlap),
                score: s.frame.map(|f| f.score),
            })
            .collect();
        PlanAnswer { policy: policy.kind.name().to_string(), slots }
    }
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
    /// The generated frame, a base64 PNG.
    #[schema(content_encoding = "base64")]
    pub image_png: String,
    /// Sampler steps used.
    pub steps: usize,
    pub provider: Option<String>,
    pub selection: Selection,
    /// Milliseconds.
    pub timings_ms: StepTimings,
    /// Synthetic sessions only (null otherwise).
    pub truth: Option<TruthAnswer>,
}

#[derive(Serialize, ToSchema)]
pub struct Observed {
    pub session: u64,
    pub index: u64,
    pub time: u64,
    /// Whether the frame was encoded (a model is loaded).
    pub has_latent: bool,
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
