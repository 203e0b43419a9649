//! The HTTP endpoints (all JSON, under `/v1`), one module per resource. Each
//! handler parses its request into typed input first (`request`), so every bad
//! field gets a 4xx naming it, then reaches its session through `access`.

mod access;
mod answers;
mod fork;
mod frames;
mod health;
mod imagine;
mod observe;
mod request;
mod select;
mod sessions;
mod step;

use std::sync::Arc;

use axum::extract::State;
use axum::routing::{get, post};
use axum::Router;

use crate::state::AppState;
use crate::error::ApiError;

pub(crate) use access::blocking;
// The handlers by name, for the OpenAPI document's `paths`.
pub(crate) use fork::*;
pub(crate) use frames::*;
pub(crate) use health::*;
pub(crate) use imagine::*;
pub(crate) use observe::*;
pub(crate) use select::*;
pub(crate) use sessions::*;
pub(crate) use step::*;

/// The web viewer (docs/viewer.md): one page, embedded, that drives the public API.
const VIEWER: &str = include_str!("../viewer.html");

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
        .route("/v1/sessions/{id}/fork", post(fork))
        .route("/v1/sessions/{id}/step", post(step))
        .route("/v1/sessions/{id}/imagine", post(imagine))
        .route("/v1/sessions/{id}/observe", post(observe))
        .route("/v1/sessions/{id}/select", post(select))
        .route("/v1/sessions/{id}/frames/{index}", get(frame))
        .route("/v1/sessions/{id}/frames/{index}/image", get(frame_image))
        .route("/v1/sessions/{id}/frames/{index}/depth", get(frame_depth))
        .route("/v1/sessions/{id}/frames/{index}/truth", get(frame_truth))
        .fallback(|| async { ApiError::not_found("path", "no such endpoint; see /docs or docs/api.md") })
        .with_state(state)
}
