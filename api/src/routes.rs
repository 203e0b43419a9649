//! The HTTP endpoints (all JSON, under `/v1`), each parsing its request into
//! typed input first so every bad field gets a 4xx naming it.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
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
use memory::{ContextPlan, Policy, Pose};
use model::Sampler;
use serde::Deserialize;
use serde::de::DeserializeOwned;
use serde_json::{Value, json};
use world::agent::Action;

use crate::error::ApiError;
use crate::session::{Session, policy_of};
use crate::engine::{encode_png, meta};
use crate::store::{FrameRecord, SessionRecord};
use crate::{AppState, Slot};

type Res<T> = Result<T, ApiError>;
type St = State<Arc<AppState>>;

/// The OpenAPI description, written by hand (docs/api.md says it in prose).
pub const OPENAPI: &str = include_str!("../openapi.json");

pub fn router(state: Arc<AppState>) -> Router {
    let doc: Value = serde_json::from_str(OPENAPI).expect("api/openapi.json is valid JSON (tested)");
    Router::new()
        .merge(utoipa_swagger_ui::SwaggerUi::new("/docs").external_url_unchecked("/openapi.json", doc))
        .route("/v1/health", get(health))
        .route("/metrics", get(metrics))
        .route("/v1/sessions", post(create))
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
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        ApiError::bad(if path == "." { "body".into() } else { path }, e.inner().to_string())
    })
}

fn session_id(id: Result<Path<u64>, PathRejection>) -> Res<u64> {
    id.map(|Path(id)| id).map_err(|_| ApiError::bad("session", "session ids are whole numbers"))
}

fn slot(st: &AppState, id: u64) -> Res<Arc<Slot>> {
    st.sessions.read().unwrap().get(&id).cloned().ok_or_else(|| ApiError::not_found("session", format!("no session {id}")))
}

/// Waits for the session, refusing with 429 when too many requests queue on it.
async fn lock(st: &AppState, slot: &Arc<Slot>) -> Res<tokio::sync::OwnedMutexGuard<Session>> {
    let queued = slot.waiting.fetch_add(1, Ordering::SeqCst);
    if queued >= st.config.max_queue_per_session {
        slot.waiting.fetch_sub(1, Ordering::SeqCst);
        return Err(ApiError::new(StatusCode::TOO_MANY_REQUESTS, "session", format!("{queued} requests already queued on this session")));
    }
    let guard = slot.session.clone().lock_owned().await;
    slot.waiting.fetch_sub(1, Ordering::SeqCst);
    if guard.deleted {
        return Err(ApiError::not_found("session", format!("session {} was deleted", guard.id)));
    }
    Ok(guard)
}

fn permit(st: &AppState) -> Res<tokio::sync::SemaphorePermit<'_>> {
    st.inflight.try_acquire().map_err(|_| {
        ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "", format!("busy: {} model calls in flight; retry shortly", st.config.max_inflight))
    })
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Res<T> + Send + 'static) -> Res<T> {
    tokio::task::spawn_blocking(f).await.map_err(ApiError::internal)?
}

fn pose_json(p: &Pose) -> Value {
    json!({ "rotation": p.rotation_rows(), "position": p.position().to_array() })
}

fn plan_json(policy: &Policy, plan: &ContextPlan) -> Value {
    let slots: Vec<Value> = plan
        .slots
        .iter()
        .enumerate()
        .map(|(i, s)| match s.frame {
            Some(f) => json!({ "slot": i, "rate": s.rate, "frame": f.id, "time": f.time, "overlap": f.overlap, "score": f.score }),
            None => json!({ "slot": i, "rate": s.rate, "frame": null }),
        })
        .collect();
    json!({ "policy": policy.kind, "slots": slots })
}

/// A PNG (base64) as RGB bytes, width, height.
fn decode_png(field: &str, b64: &str) -> Res<(Vec<u8>, u32, u32)> {
    let bytes = B64.decode(b64.trim()).map_err(|e| ApiError::bad(field, format!("not base64: {e}")))?;
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().map_err(|e| ApiError::bad(field, format!("not a PNG: {e}")))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| ApiError::bad(field, format!("broken PNG: {e}")))?;
    if info.bit_depth != png::BitDepth::Eight {
        return Err(ApiError::bad(field, "only 8-bit PNGs are accepted"));
    }
    let px = (info.width * info.height) as usize;
    let rgb = match info.color_type {
        png::ColorType::Rgb => buf[..px * 3].to_vec(),
        png::ColorType::Rgba => buf[..px * 4].chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => buf[..px].iter().flat_map(|&g| [g, g, g]).collect(),
        other => return Err(ApiError::bad(field, format!("unsupported PNG colour type {other:?}; use RGB or RGBA"))),
    };
    Ok((rgb, info.width, info.height))
}

/// Positions are capped at ±1e9 world units: beyond that the f64 geometry
/// has no centimetres left and any answer would be noise.
const MAX_COORDINATE: f64 = 1e9;

fn pose_from(input: &PoseInput, field: &str) -> Res<Pose> {
    let pose = input.resolve().map_err(|e| e.within(field))?;
    if pose.position().abs().max_element() > MAX_COORDINATE {
        return Err(ApiError::bad(format!("{field}.position"), format!("must lie within ±{MAX_COORDINATE:e} world units")));
    }
    Ok(pose)
}

fn validate_action(a: &Action) -> Res<()> {
    for (field, v) in [("action.yaw_deg", a.yaw_deg), ("action.pitch_deg", a.pitch_deg)] {
        if !v.is_finite() || v.abs() > 180.0 {
            return Err(ApiError::bad(field, format!("must be a finite angle within ±180 degrees, got {v}")));
        }
    }
    Ok(())
}

async fn health(State(st): St) -> Json<Value> {
    Json(json!({
        "status": "ok",
        "model": st.engine.model.as_ref().map(|m| m.manifest().name.clone()),
        "provider": st.engine.model.as_ref().map(|m| m.provider()),
        "sessions": st.sessions.read().unwrap().len(),
    }))
}

async fn metrics(State(st): St) -> Response {
    let m = &st.metrics;
    let g = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let text = format!(
        "# TYPE worldpack_steps_total counter\nworldpack_steps_total {}\n\
         # TYPE worldpack_observes_total counter\nworldpack_observes_total {}\n\
         # TYPE worldpack_selects_total counter\nworldpack_selects_total {}\n\
         # TYPE worldpack_sessions_created_total counter\nworldpack_sessions_created_total {}\n\
         # TYPE worldpack_step_seconds_sum counter\nworldpack_step_seconds_sum {}\n\
         # TYPE worldpack_sessions gauge\nworldpack_sessions {}\n",
        g(&m.steps),
        g(&m.observes),
        g(&m.selects),
        g(&m.sessions_created),
        g(&m.step_micros) as f64 / 1e6,
        st.sessions.read().unwrap().len()
    );
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CreateRequest {
    #[serde(default)]
    policy: Option<Value>,
    #[serde(default)]
    synthetic: Option<SyntheticStart>,
    #[serde(default)]
    frames: Option<Vec<FrameInput>>,
    #[serde(default)]
    intrinsics: Option<IntrinsicsInput>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SyntheticStart {
    seed: u64,
    #[serde(default)]
    biome: Option<world::Biome>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FrameInput {
    image_png: String,
    pose: PoseInput,
}

async fn create(State(st): St, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<(StatusCode, Json<Value>)> {
    let req: CreateRequest = parse(&headers, body)?;
    let policy_spec = req.policy.unwrap_or_else(|| st.config.policy.clone());
    policy_of(&policy_spec)?;
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
                e.create_synthetic(policy_spec, s.seed, s.biome)?
            }
            (None, Some(frames)) => {
                let k = req.intrinsics.ok_or_else(|| ApiError::bad("intrinsics", "required with frames"))?.resolve().map_err(|e| e.within("intrinsics"))?;
                let mut records = Vec::new();
                for (i, f) in frames.iter().enumerate() {
                    let at = format!("frames[{i}]");
                    let pose = pose_from(&f.pose, &format!("{at}.pose"))?;
                    let (rgb, w, h) = decode_png(&format!("{at}.image_png"), &f.image_png)?;
                    let latent = e.latent_of(&rgb, w, h, &k, &format!("{at}.image_png"))?;
                    records.push(FrameRecord { meta: meta(&pose, i as u64, "observed", None, None), latent, png: encode_png(&rgb, w, h), depth_png16: Vec::new() });
                }
                e.create(SessionRecord { policy: policy_spec, intrinsics: k, world_seed: None }, records, None)?
            }
        };
        let (id, n) = (session.id, session.frames.len());
        let slot = Slot { session: Arc::new(tokio::sync::Mutex::new(session)), waiting: AtomicUsize::new(0) };
        st2.sessions.write().unwrap().insert(id, Arc::new(slot));
        Ok((id, n))
    })
    .await?;
    st.metrics.sessions_created.fetch_add(1, Ordering::Relaxed);
    Ok((StatusCode::CREATED, Json(json!({ "session": id, "frames": frames }))))
}

async fn describe(State(st): St, id: Result<Path<u64>, PathRejection>) -> Res<Json<Value>> {
    let id = session_id(id)?;
    let slot = slot(&st, id)?;
    let s = lock(&st, &slot).await?;
    Ok(Json(json!({
        "session": id,
        "frames": s.frames.len(),
        "policy": s.policy,
        "world_seed": s.record.world_seed,
        "intrinsics": s.record.intrinsics,
        "has_latents": s.frames.first().is_some_and(|f| !f.latent.is_empty()),
    })))
}

async fn delete(State(st): St, id: Result<Path<u64>, PathRejection>) -> Res<StatusCode> {
    let id = session_id(id)?;
    let slot = slot(&st, id)?;
    let mut guard = lock(&st, &slot).await?;
    let st2 = st.clone();
    blocking(move || Ok(st2.engine.store.delete_session(id)?)).await?;
    guard.deleted = true;
    st.sessions.write().unwrap().remove(&id);
    Ok(StatusCode::NO_CONTENT)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct StepRequest {
    action: Action,
    #[serde(default)]
    pose: Option<PoseInput>,
    #[serde(default)]
    steps: Option<usize>,
    #[serde(default)]
    seed: Option<u64>,
}

async fn step(State(st): St, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Value>> {
    let started = Instant::now();
    let id = session_id(id)?;
    let req: StepRequest = parse(&headers, body)?;
    validate_action(&req.action)?;
    let Some(m) = &st.engine.model else {
        return Err(ApiError::new(StatusCode::CONFLICT, "model", "this server runs without a model (memory only): use observe"));
    };
    let steps = req.steps.unwrap_or(st.config.steps);
    let sampler = Sampler::new(&m.manifest().diffusion, steps, st.config.method, 0.0)?;
    let slot = slot(&st, id)?;
    let mut s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let pose = req.pose.as_ref().map(|p| pose_from(p, "pose")).transpose()?;
        let o = st2.engine.step(&mut s, &req.action, pose, &sampler, req.seed)?;
        let [select, sample, decode, store] = o.timings_ms;
        Ok(json!({
            "session": s.id, "index": o.index, "time": o.time, "pose": pose_json(&o.pose), "source": crate::session::GENERATED,
            "image_png": B64.encode(&o.png), "steps": sampler.len(), "provider": st2.engine.model.as_ref().map(|m| m.provider()),
            "selection": { "plan": plan_json(&s.policy, &o.plan), "layout": o.layout, "exact_evaluations": o.exact_evaluations },
            "timings_ms": { "select": select, "sample": sample, "decode": decode, "store": store },
            "truth": o.truth.map(|t| json!({
                "psnr_db": t.psnr_db, "ssim": t.ssim, "image": format!("/v1/sessions/{}/frames/{}/truth", s.id, o.index),
            })),
        }))
    })
    .await?;
    let micros = started.elapsed().as_micros() as u64;
    st.metrics.steps.fetch_add(1, Ordering::Relaxed);
    st.metrics.step_micros.fetch_add(micros, Ordering::Relaxed);
    let mut out = out;
    out["timings_ms"]["total"] = json!(micros as f64 / 1e3);
    Ok(Json(out))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObserveRequest {
    image_png: String,
    pose: PoseInput,
    #[serde(default)]
    action: Option<Action>,
    /// Depth as a 16-bit grayscale PNG in millimetres (0 = unknown), the image's size.
    #[serde(default)]
    depth_png16: Option<String>,
}

/// Checks a depth PNG (16-bit grayscale, `w`×`h`) and returns its bytes as sent.
fn depth_png(b64: &str, w: u32, h: u32) -> Res<Vec<u8>> {
    let field = "depth_png16";
    let bytes = B64.decode(b64.trim()).map_err(|e| ApiError::bad(field, format!("not base64: {e}")))?;
    let reader = png::Decoder::new(std::io::Cursor::new(&bytes)).read_info().map_err(|e| ApiError::bad(field, format!("not a PNG: {e}")))?;
    let info = reader.info();
    if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
        return Err(ApiError::bad(field, format!("must be 16-bit grayscale (millimetres), got {:?} {:?}", info.color_type, info.bit_depth)));
    }
    if (info.width, info.height) != (w, h) {
        return Err(ApiError::bad(field, format!("is {}x{}, the image is {w}x{h}", info.width, info.height)));
    }
    Ok(bytes)
}

async fn observe(State(st): St, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Value>> {
    let id = session_id(id)?;
    let req: ObserveRequest = parse(&headers, body)?;
    if let Some(a) = &req.action {
        validate_action(a)?;
    }
    let pose = pose_from(&req.pose, "pose")?;
    let (rgb, w, h) = decode_png("image_png", &req.image_png)?;
    let depth = req.depth_png16.as_deref().map(|d| depth_png(d, w, h)).transpose()?.unwrap_or_default();
    let slot = slot(&st, id)?;
    let mut s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let (index, time) = st2.engine.observe(&mut s, &rgb, w, h, pose, req.action.as_ref(), depth)?;
        Ok(json!({ "session": s.id, "index": index, "time": time, "has_latent": st2.engine.model.is_some() }))
    })
    .await?;
    st.metrics.observes.fetch_add(1, Ordering::Relaxed);
    Ok(Json(out))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SelectRequest {
    pose: PoseInput,
}

async fn select(State(st): St, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Value>> {
    let id = session_id(id)?;
    let req: SelectRequest = parse(&headers, body)?;
    let pose = pose_from(&req.pose, "pose")?;
    let slot = slot(&st, id)?;
    let s = lock(&st, &slot).await?;
    // Selection over a long history is CPU work: off the async workers.
    let out = blocking(move || {
        let t = Instant::now();
        let frustum = s.frustum(pose)?;
        let (plan, stats) = s.memory.select(&s.policy, &frustum, None);
        Ok(json!({
            "session": id, "plan": plan_json(&s.policy, &plan), "exact_evaluations": stats.overlap_evaluations,
            "candidates": s.frames.len(), "select_ms": t.elapsed().as_secs_f64() * 1e3,
        }))
    })
    .await?;
    st.metrics.selects.fetch_add(1, Ordering::Relaxed);
    Ok(Json(out))
}

fn frame_ids(p: Result<Path<(u64, u64)>, PathRejection>) -> Res<(u64, u64)> {
    p.map(|Path(v)| v).map_err(|_| ApiError::bad("index", "session ids and frame indices are whole numbers"))
}

/// A stored frame of a live session, read off the async workers; 404 naming what is missing.
async fn stored_frame(st: &Arc<AppState>, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<(u64, u64, FrameRecord)> {
    let (id, index) = frame_ids(p)?;
    slot(st, id)?;
    let st2 = st.clone();
    let f = blocking(move || st2.engine.store.frame(id, index).map_err(ApiError::from)).await?;
    let f = f.ok_or_else(|| ApiError::not_found("index", format!("session {id} has no frame {index}")))?;
    Ok((id, index, f))
}

async fn frame(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Json<Value>> {
    let (id, index, f) = stored_frame(&st, p).await?;
    let pose = crate::session::pose_of(&f.meta)?;
    Ok(Json(json!({
        "session": id, "index": index, "time": f.meta.time, "source": f.meta.source, "pose": pose_json(&pose),
        "action": f.meta.action, "has_latent": !f.latent.is_empty(), "image": format!("/v1/sessions/{id}/frames/{index}/image"),
        "depth": (!f.depth_png16.is_empty()).then(|| format!("/v1/sessions/{id}/frames/{index}/depth")),
    })))
}

async fn frame_image(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (_, _, f) = stored_frame(&st, p).await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], f.png).into_response())
}

async fn frame_depth(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (id, index, f) = stored_frame(&st, p).await?;
    if f.depth_png16.is_empty() {
        return Err(ApiError::not_found("depth", format!("frame {index} of session {id} was stored without depth")));
    }
    Ok(([(header::CONTENT_TYPE, "image/png")], f.depth_png16).into_response())
}

/// The synthetic world's true frame at a stored frame's pose, so a user can
/// see how far generated frames drift; 404 for sessions of real frames.
async fn frame_truth(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (id, _, f) = stored_frame(&st, p).await?;
    let pose = crate::session::pose_of(&f.meta)?;
    let slot = slot(&st, id)?;
    let s = lock(&st, &slot).await?;
    let st2 = st.clone();
    let png = blocking(move || {
        let rgb = st2.engine.truth_at(&s, &pose)?.ok_or_else(|| {
            ApiError::not_found("truth", format!("session {id} is not synthetic: only a synthetic world has a true frame"))
        })?;
        let k = s.intrinsics();
        Ok(crate::engine::encode_png(&rgb, k.width, k.height))
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_openapi_document_is_json_with_every_endpoint() {
        let doc: serde_json::Value = serde_json::from_str(super::OPENAPI).unwrap();
        assert_eq!(doc["openapi"], "3.1.0");
        assert_eq!(doc["paths"].as_object().unwrap().len(), 11);
    }
}
