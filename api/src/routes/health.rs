//! Liveness, readiness and the Prometheus counters.

use std::sync::atomic::Ordering;

use axum::Json;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

use super::St;

#[utoipa::path(get, path = "/v1/health", summary = "Liveness, the model served and the live sessions",
    responses((status = 200, body = Health)))]
pub async fn health(State(st): St) -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        model: st.engine.model.as_ref().map(|m| m.manifest().name.clone()),
        model_version: st.engine.model.as_ref().and_then(|m| m.manifest().version.clone()),
        model_digest: st.engine.model.as_ref().map(|m| m.manifest().digest.clone()),
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

#[utoipa::path(get, path = "/metrics", summary = "Prometheus counters: steps, observes, selects, sessions, forks, step seconds, shared-store catch-ups",
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
         # TYPE worldpack_forks_total counter\nworldpack_forks_total {}\n\
         # TYPE worldpack_imagined_frames_total counter\nworldpack_imagined_frames_total {}\n\
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
        g(&m.forks),
        g(&m.imagined_frames),
        g(&m.sessions_expired),
        g(&m.step_micros) as f64 / 1e6,
        g(&m.catch_ups),
        g(&m.catch_up_micros) as f64 / 1e6,
        g(&m.caught_up_frames),
        st.sessions.read().unwrap().len()
    );
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

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
    /// The model's version as its trainer wrote it, or null (older folders, memory-only).
    pub model_version: Option<String>,
    /// The first 16 hex digits of the SHA-256 of the model's manifest, graphs and weights.
    #[schema(example = "3f9a0c41d2b7e855")]
    pub model_digest: Option<String>,
    /// The execution provider that runs the denoiser (cpu, cuda), or null.
    pub provider: Option<String>,
    /// Live sessions.
    pub sessions: usize,
}
