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
use memory::{ContextPlan, Intrinsics, Policy, Pose};
use model::generate::{Conditioning, frame_to_tensor, tensor_to_frame};
use model::{Sampler, Tensor};
use serde::Deserialize;
use serde::de::DeserializeOwned;
use serde_json::{Value, json};
use world::agent::{Action, PlayerState};
use world::render::{RenderSettings, render};

use crate::error::ApiError;
use crate::session::{Session, player_to, policy_of};
use crate::store::{FrameMeta, FrameRecord, SessionRecord};
use crate::{AppState, Slot};

type Res<T> = Result<T, ApiError>;
type St = State<Arc<AppState>>;

pub fn router(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/v1/health", get(health))
        .route("/metrics", get(metrics))
        .route("/v1/sessions", post(create))
        .route("/v1/sessions/{id}", get(describe).delete(delete))
        .route("/v1/sessions/{id}/step", post(step))
        .route("/v1/sessions/{id}/observe", post(observe))
        .route("/v1/sessions/{id}/select", post(select))
        .route("/v1/sessions/{id}/frames/{index}", get(frame))
        .route("/v1/sessions/{id}/frames/{index}/image", get(frame_image))
        .fallback(|| async { ApiError::not_found("path", "no such endpoint; see docs/api.md") })
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

pub fn encode_png(rgb: &[u8], w: u32, h: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().and_then(|mut w| w.write_image_data(rgb)).expect("encoding a PNG into memory");
    out
}

/// The model's scaled latent of an RGB frame (empty without a model).
fn latent_of(st: &AppState, rgb: &[u8], w: u32, h: u32, k: &Intrinsics, field: &str) -> Res<Vec<f32>> {
    let Some(m) = &st.model else { return Ok(Vec::new()) };
    let img = &m.manifest().image;
    let (t, _) = frame_to_tensor(rgb, w, h, k, img.width as u32, img.height as u32).map_err(|e| match e {
        model::ModelError::Input { message, .. } => ApiError::bad(field, message),
        other => ApiError::internal(other),
    })?;
    Ok(m.encode(&t)?.data)
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
        "model": st.model.as_ref().map(|m| m.manifest().name.clone()),
        "provider": st.model.as_ref().map(|m| m.provider()),
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
        let st = st2;
        let (record, firsts, world) = match (req.synthetic, req.frames) {
            (Some(_), Some(_)) => return Err(ApiError::bad("frames", "give either synthetic or frames, not both")),
            (None, None) => return Err(ApiError::bad("frames", "give initial frames (with intrinsics) or a synthetic world seed")),
            (Some(s), None) => {
                if req.intrinsics.is_some() {
                    return Err(ApiError::bad("intrinsics", "a synthetic session uses the model's camera"));
                }
                let k = match &st.model {
                    Some(m) => m.manifest().intrinsics,
                    None => world::suite::default_intrinsics(64, 64)?,
                };
                let world = st.world(s.seed);
                let cell = world::agent::spawn_point(&world, s.biome)
                    .ok_or_else(|| ApiError::bad("synthetic.biome", "this world has no standable spawn in that biome"))?;
                let player = PlayerState::at_cell(cell, 0.0);
                let frame = render(&world, &player.camera(), &k, &RenderSettings::default());
                let latent = latent_of(&st, &frame.rgb, k.width, k.height, &k, "synthetic")?;
                let meta = meta(&player.camera(), 0, "observed", None, Some(&player));
                let rec = SessionRecord { policy: policy_spec, intrinsics: k, world_seed: Some(s.seed) };
                (rec, vec![FrameRecord { meta, latent, png: encode_png(&frame.rgb, k.width, k.height) }], Some(world))
            }
            (None, Some(frames)) => {
                let k = req.intrinsics.ok_or_else(|| ApiError::bad("intrinsics", "required with frames"))?.resolve().map_err(|e| e.within("intrinsics"))?;
                if frames.is_empty() {
                    return Err(ApiError::bad("frames", "give at least one frame"));
                }
                let mut out = Vec::new();
                for (i, f) in frames.iter().enumerate() {
                    let at = format!("frames[{i}]");
                    let pose = pose_from(&f.pose, &format!("{at}.pose"))?;
                    let (rgb, w, h) = decode_png(&format!("{at}.image_png"), &f.image_png)?;
                    let latent = latent_of(&st, &rgb, w, h, &k, &format!("{at}.image_png"))?;
                    out.push(FrameRecord { meta: meta(&pose, i as u64, "observed", None, None), latent, png: encode_png(&rgb, w, h) });
                }
                (SessionRecord { policy: policy_spec, intrinsics: k, world_seed: None }, out, None)
            }
        };
        let mut session = Session::restore(0, record.clone(), Vec::new(), world)?;
        let id = st.store.create_session(&record, &firsts[0])?;
        for (i, f) in firsts.iter().enumerate().skip(1) {
            st.store.put_frame(id, i as u64, f)?;
        }
        session.id = id;
        for f in firsts {
            session.push(f.meta.time, crate::session::pose_of(&f.meta)?, f.latent, f.meta.player.map(crate::session::player_from))?;
        }
        let n = session.frames.len();
        let slot = Slot { session: Arc::new(tokio::sync::Mutex::new(session)), waiting: AtomicUsize::new(0) };
        st.sessions.write().unwrap().insert(id, Arc::new(slot));
        Ok((id, n))
    })
    .await?;
    st.metrics.sessions_created.fetch_add(1, Ordering::Relaxed);
    Ok((StatusCode::CREATED, Json(json!({ "session": id, "frames": frames }))))
}

fn meta(pose: &Pose, time: u64, source: &str, action: Option<&Action>, player: Option<&PlayerState>) -> FrameMeta {
    FrameMeta {
        c2w: pose.matrix_rows(),
        time,
        source: source.into(),
        action: action.map(|a| a.to_vector().to_vec()),
        player: player.map(player_to),
    }
}

async fn describe(State(st): St, id: Result<Path<u64>, PathRejection>) -> Res<Json<Value>> {
    let id = session_id(id)?;
    let slot = slot(&st, id)?;
    let s = slot.session.lock().await;
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
    let _guard = lock(&st, &slot).await?;
    let st2 = st.clone();
    blocking(move || Ok(st2.store.delete_session(id)?)).await?;
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
    let Some(m) = &st.model else {
        return Err(ApiError::new(StatusCode::CONFLICT, "model", "this server runs without a model (memory only): use observe"));
    };
    let steps = req.steps.unwrap_or(st.config.steps);
    let sampler = Sampler::new(&m.manifest().diffusion, steps, st.config.method, 0.0)?;
    let slot = slot(&st, id)?;
    let mut s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let st = st2;
        let m = st.model.as_ref().expect("checked above");
        let t0 = Instant::now();
        let (pose, player) = match &req.pose {
            Some(p) => (pose_from(p, "pose")?, None),
            None => s.motion(&req.action)?,
        };
        let time = s.next_time();
        let frustum = s.frustum(pose)?;
        let (plan, stats) = s.memory.select(&s.policy, &frustum, s.last_plan.as_ref());
        let select_ms = t0.elapsed().as_secs_f64() * 1e3;
        let layout = layout_for(m, &s.policy)?;
        let spec = m.manifest().layout(&layout).expect("layout_for returns a layout of the manifest");
        let latent_spec = &m.manifest().autoencoder.latent;
        let packed = model::pack::pack(spec, latent_spec, &plan, time, &pose, |fid| {
            s.frames.get(fid as usize).map(|f| model::pack::ContextFrame { latent: &f.latent, time: f.time, pose: &f.pose })
        })?;
        let action = Tensor::new(vec![1, 7], req.action.to_vector().to_vec());
        let rel_time = Tensor::new(vec![1], vec![packed.rel_time]);
        let t1 = Instant::now();
        let cond = Conditioning { context: &packed.tensors, action: &action, rel_time: &rel_time };
        let latent = m.sample(&layout, &cond, &sampler, req.seed.unwrap_or(time))?;
        let sample_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = Instant::now();
        let image = m.decode(&latent)?;
        let rgb = tensor_to_frame(&image, 0)?;
        let img = &m.manifest().image;
        let png = encode_png(&rgb, img.width as u32, img.height as u32);
        let decode_ms = t2.elapsed().as_secs_f64() * 1e3;
        let t3 = Instant::now();
        let index = s.frames.len() as u64;
        let record = FrameRecord { meta: meta(&pose, time, "generated", Some(&req.action), player.as_ref()), latent: latent.data, png };
        st.store.put_frame(s.id, index, &record)?;
        let store_ms = t3.elapsed().as_secs_f64() * 1e3;
        s.push(time, pose, record.latent, player)?;
        let selection = json!({ "plan": plan_json(&s.policy, &plan), "layout": layout, "exact_evaluations": stats.overlap_evaluations });
        s.last_plan = Some(plan);
        Ok(json!({
            "session": s.id, "index": index, "time": time, "pose": pose_json(&pose), "source": "generated",
            "image_png": B64.encode(&record.png), "selection": selection, "steps": steps, "provider": m.provider(),
            "timings_ms": { "select": select_ms, "sample": sample_ms, "decode": decode_ms, "store": store_ms },
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

/// The denoiser layout whose slots are the policy's packing, tier by tier.
fn layout_for(m: &model::Model, policy: &Policy) -> Res<String> {
    let want: Vec<(u32, usize)> = policy.packing.tiers().iter().map(|t| (t.rate, t.slots)).collect();
    m.manifest()
        .denoiser
        .layouts
        .iter()
        .find(|l| l.slots.iter().map(|s| (s.rate, s.count)).collect::<Vec<_>>() == want)
        .map(|l| l.name.clone())
        .ok_or_else(|| ApiError::bad("policy", format!("the model has no context layout with slots {want:?} (rate, count); its layouts fit baseline (4x1) and worldpack (2x1, 4x4, 16x16) packings")))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObserveRequest {
    image_png: String,
    pose: PoseInput,
    #[serde(default)]
    action: Option<Action>,
}

async fn observe(State(st): St, id: Result<Path<u64>, PathRejection>, headers: HeaderMap, body: Result<Bytes, BytesRejection>) -> Res<Json<Value>> {
    let id = session_id(id)?;
    let req: ObserveRequest = parse(&headers, body)?;
    if let Some(a) = &req.action {
        validate_action(a)?;
    }
    let pose = pose_from(&req.pose, "pose")?;
    let (rgb, w, h) = decode_png("image_png", &req.image_png)?;
    let slot = slot(&st, id)?;
    let mut s = lock(&st, &slot).await?;
    let _permit = permit(&st)?;
    let st2 = st.clone();
    let out = blocking(move || {
        let st = st2;
        let k = *s.intrinsics();
        let latent = latent_of(&st, &rgb, w, h, &k, "image_png")?;
        s.frustum(pose)?;
        let time = s.next_time();
        let index = s.frames.len() as u64;
        let record = FrameRecord { meta: meta(&pose, time, "observed", req.action.as_ref(), None), latent, png: encode_png(&rgb, w, h) };
        st.store.put_frame(s.id, index, &record)?;
        s.push(time, pose, record.latent, None)?;
        Ok(json!({ "session": s.id, "index": index, "time": time, "has_latent": st.model.is_some() }))
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
    let s = slot.session.lock().await;
    let t = Instant::now();
    let frustum = s.frustum(pose)?;
    let (plan, stats) = s.memory.select(&s.policy, &frustum, None);
    st.metrics.selects.fetch_add(1, Ordering::Relaxed);
    Ok(Json(json!({
        "session": id, "plan": plan_json(&s.policy, &plan), "exact_evaluations": stats.overlap_evaluations,
        "candidates": s.frames.len(), "select_ms": t.elapsed().as_secs_f64() * 1e3,
    })))
}

fn frame_ids(p: Result<Path<(u64, u64)>, PathRejection>) -> Res<(u64, u64)> {
    p.map(|Path(v)| v).map_err(|_| ApiError::bad("index", "session ids and frame indices are whole numbers"))
}

async fn frame(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Json<Value>> {
    let (id, index) = frame_ids(p)?;
    slot(&st, id)?;
    let st2 = st.clone();
    let f = blocking(move || st2.store.frame(id, index).map_err(ApiError::from)).await?;
    let f = f.ok_or_else(|| ApiError::not_found("index", format!("session {id} has no frame {index}")))?;
    let pose = crate::session::pose_of(&f.meta)?;
    Ok(Json(json!({
        "session": id, "index": index, "time": f.meta.time, "source": f.meta.source, "pose": pose_json(&pose),
        "action": f.meta.action, "has_latent": !f.latent.is_empty(), "image": format!("/v1/sessions/{id}/frames/{index}/image"),
    })))
}

async fn frame_image(State(st): St, p: Result<Path<(u64, u64)>, PathRejection>) -> Res<Response> {
    let (id, index) = frame_ids(p)?;
    slot(&st, id)?;
    let st2 = st.clone();
    let f = blocking(move || st2.store.frame(id, index).map_err(ApiError::from)).await?;
    let f = f.ok_or_else(|| ApiError::not_found("index", format!("session {id} has no frame {index}")))?;
    Ok(([(header::CONTENT_TYPE, "image/png")], f.png).into_response())
}
