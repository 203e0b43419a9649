//! What every request handler shares: the server's configuration, its engine,
//! the live sessions (each behind its own lock, with its queue) and counters.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize};
use std::sync::{Arc, RwLock};

use tokio::sync::Semaphore;

use crate::Config;
use crate::auth;
use crate::engine::Engine;
use crate::session::Session;

/// A session and the number of requests queued on it.
pub(crate) struct Slot {
    pub session: Arc<tokio::sync::Mutex<Session>>,
    pub waiting: AtomicUsize,
    /// The tenant that owns the session (`SessionRecord::tenant`), readable without its lock.
    pub owner: Option<String>,
}

impl Slot {
    pub fn new(session: Session) -> Slot {
        let owner = session.record.tenant.clone();
        Slot { session: Arc::new(tokio::sync::Mutex::new(session)), waiting: AtomicUsize::new(0), owner }
    }
}

#[derive(Default)]
pub(crate) struct Metrics {
    pub steps: AtomicU64,
    pub observes: AtomicU64,
    pub selects: AtomicU64,
    pub sessions_created: AtomicU64,
    pub forks: AtomicU64,
    /// Frames made by `imagine`, never stored.
    pub imagined_frames: AtomicU64,
    /// Sessions deleted by retention.
    pub sessions_expired: AtomicU64,
    pub step_micros: AtomicU64,
    /// Reads of a shared store's new frames before a request (see `routes::access::catch_up`).
    pub catch_ups: AtomicU64,
    pub catch_up_micros: AtomicU64,
    pub caught_up_frames: AtomicU64,
}

pub(crate) struct AppState {
    pub config: Config,
    pub tokens: Arc<auth::Tokens>,
    pub engine: Engine,
    pub sessions: RwLock<HashMap<u64, Arc<Slot>>>,
    pub inflight: Semaphore,
    pub metrics: Metrics,
}

