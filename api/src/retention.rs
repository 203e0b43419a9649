//! Retention (`serve --retain-idle-secs N`): sessions that no frame was
//! written to for N seconds are deleted, frames and all, as `DELETE
//! /v1/sessions/{id}` deletes them. Each is deleted under its session's
//! lock, so a step in flight on it finishes first, and only if the store
//! still finds it idle then, so a frame written meanwhile (by this server or
//! a replica on the same database) keeps it.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use crate::state::AppState;
use crate::error::ApiError;
use crate::routes::blocking;

/// Sweeps every quarter of the idle time (between 0.2 s and a minute), for ever.
pub(crate) async fn expire_idle_sessions(state: Arc<AppState>, idle: Duration) {
    let mut tick = tokio::time::interval((idle / 4).clamp(Duration::from_millis(200), Duration::from_secs(60)));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let st = state.clone();
        let ids = match blocking(move || Ok(st.engine.store.idle_sessions(idle)?)).await {
            Ok(ids) => ids,
            Err(e) => {
                eprintln!("retention: {}", e.message); // the store is down: the next sweep tries again
                continue;
            }
        };
        for id in ids {
            if let Err(e) = expire(&state, id, idle).await {
                eprintln!("retention: session {id}: {}", e.message);
            }
        }
    }
}

async fn expire(state: &Arc<AppState>, id: u64, idle: Duration) -> Result<(), ApiError> {
    let slot = state.sessions.read().unwrap().get(&id).cloned();
    // A session this server never loaded (a replica's) has nothing here to lock.
    let mut guard = match &slot {
        Some(slot) => Some(slot.session.lock().await),
        None => None,
    };
    let st = state.clone();
    if blocking(move || Ok(st.engine.store.delete_if_idle(id, idle)?)).await? {
        if let Some(guard) = guard.as_mut() {
            guard.deleted = true;
        }
        state.sessions.write().unwrap().remove(&id);
        state.metrics.sessions_expired.fetch_add(1, Ordering::Relaxed);
    }
    Ok(())
}
