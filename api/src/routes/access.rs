//! Reaching a session: its tenant, its lock (with a queue limit), catching up on
//! a shared store, the in-flight model-call limit, and work off the async workers.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::http::StatusCode;

use crate::state::{AppState, Slot};
use crate::auth::Caller;
use crate::error::ApiError;
use crate::session::Session;
use super::Res;

/// The session `id` if `caller` may see it; another tenant's session is as
/// missing as one that never existed.
pub(crate) fn slot(st: &AppState, id: u64, caller: &Caller) -> Res<Arc<Slot>> {
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
    // A fork another server made: the frames it shares are read once here
    // (shared in the store, not in this server's memory); its own, by `lock`.
    let shared = match record.fork {
        Some(f) => tokio::task::block_in_place(|| st.engine.store.frames_before(f.parent, f.frames))?,
        None => Vec::new(),
    };
    let session = Session::restore(id, record, shared, world)?;
    let slot = Arc::new(Slot::new(session));
    owned(st.sessions.write().unwrap().entry(id).or_insert(slot).clone())
}

/// Refuses a new session (created or forked) with 429 when the caller's
/// tenant has its limit of live sessions (forks count: each is a session).
pub(crate) fn within_session_limit(st: &AppState, caller: &Caller) -> Res<()> {
    let Some(tenant) = &caller.0 else { return Ok(()) };
    let limit = st.tokens.limits(tenant).sessions;
    let owned = st.sessions.read().unwrap().values().filter(|s| s.owner.as_deref() == Some(tenant)).count();
    if owned >= limit {
        return Err(ApiError::new(StatusCode::TOO_MANY_REQUESTS, "session", format!("tenant {tenant} has {owned} live sessions, its limit; delete one first")));
    }
    Ok(())
}

/// On a store other servers write too: indexes the frames stored since this
/// server last saw the session, or marks it deleted when it is gone.
pub(crate) fn catch_up(st: &AppState, s: &mut Session) -> Res<()> {
    if !st.engine.store.shared() {
        return Ok(());
    }
    let started = std::time::Instant::now();
    tokio::task::block_in_place(|| {
        if st.engine.store.session(s.id)?.is_none() {
            s.deleted = true;
            return Ok(());
        }
        let new = st.engine.store.frames_from(s.id, s.len())?;
        st.metrics.caught_up_frames.fetch_add(new.len() as u64, Ordering::Relaxed);
        s.append_stored(new)
    })?;
    st.metrics.catch_up_micros.fetch_add(started.elapsed().as_micros() as u64, Ordering::Relaxed);
    st.metrics.catch_ups.fetch_add(1, Ordering::Relaxed);
    Ok(())
}

/// Waits for the session, refusing with 429 when too many requests queue on it.
pub(crate) async fn lock(st: &AppState, slot: &Arc<Slot>) -> Res<tokio::sync::OwnedMutexGuard<Session>> {
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

pub(crate) fn permit(st: &AppState) -> Res<tokio::sync::SemaphorePermit<'_>> {
    st.inflight.try_acquire().map_err(|_| {
        ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "", format!("busy: {} model calls in flight; retry shortly", st.config.max_inflight))
    })
}

pub(crate) async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Res<T> + Send + 'static) -> Res<T> {
    tokio::task::spawn_blocking(f).await.map_err(ApiError::internal)?
}
