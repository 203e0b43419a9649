//! `POST /v1/sessions/{id}/fork`: a new session whose history is this one's up to now.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::extract::{Path, State};
use axum::extract::rejection::PathRejection;
use axum::http::StatusCode;
use serde::Serialize;
use utoipa::ToSchema;

use crate::Slot;
use crate::auth::Caller;
use crate::error::ErrorBody;
use super::request::session_id;
use super::access::{slot, lock, blocking, within_session_limit};
use super::{Res, St};

#[utoipa::path(post, path = "/v1/sessions/{id}/fork", summary = "Fork a session: a new session of the same tenant whose memory is this one's up to now, shared, not copied",
    description = "The fork starts with the session's frames (indices 0 to frames − 1), its policy, camera and world; its steps and observes \
                   are its own and never appear in the session, nor the session's in it. A session is not deleted while forks of it live \
                   (409 naming `session`). Forks count against the tenant's session limit. No body.",
    params(("id" = u64, Path, description = "session id", minimum = 0, maximum = 9223372036854775807_u64)),
    responses(
        (status = 201, body = Forked),
        (status = 400, description = "the id is not a whole number in range", body = ErrorBody),
        (status = 404, description = "no such session", body = ErrorBody),
        (status = 429, description = "too many requests queued on the session, or the tenant is at its session limit", body = ErrorBody),
        (status = 503, description = "the store (field `store`) is unreachable; retry", body = ErrorBody)))]
pub async fn fork(State(st): St, caller: Caller, id: Result<Path<u64>, PathRejection>) -> Res<(StatusCode, Json<Forked>)> {
    let id = session_id(id)?;
    let slot = slot(&st, id, &caller)?;
    within_session_limit(&st, &caller)?;
    let mut parent = lock(&st, &slot).await?;
    let st2 = st.clone();
    let forked = blocking(move || {
        let fork = st2.engine.fork(&mut parent)?;
        let answer = Forked { session: fork.id, parent: id, frames: fork.len() };
        st2.sessions.write().unwrap().insert(fork.id, Arc::new(Slot::new(fork)));
        Ok(answer)
    })
    .await?;
    st.metrics.forks.fetch_add(1, Ordering::Relaxed);
    Ok((StatusCode::CREATED, Json(forked)))
}

#[derive(Serialize, ToSchema)]
pub struct Forked {
    /// The fork's id.
    pub session: u64,
    /// The session it was forked from.
    pub parent: u64,
    /// Frames the fork shares with it: its next frame gets this index.
    pub frames: u64,
}
