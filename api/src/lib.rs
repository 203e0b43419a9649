//! The WorldPack REST server: sessions of frames with poses, a step endpoint
//! that generates the next frame from a packed memory context, and a durable
//! store underneath. See docs/api.md.

pub mod auth;
pub mod batch;
pub mod engine;
pub mod error;
pub mod history;
pub mod imagine;
pub mod openapi;
pub mod postgres_store;
pub mod postgres_tls;
mod records;
pub mod refusal;
mod schemas;
mod retention;
mod routes;
mod state;
pub mod session;
pub mod store;
pub mod tls;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, RwLock};
use std::time::Duration;

use axum::Router;
use axum::extract::DefaultBodyLimit;
use model::{Method, Model};
use tokio::sync::Semaphore;

pub use error::ApiError;
pub use refusal::EngineError;
use engine::Engine;
use state::{AppState, Metrics, Slot};
use store::Store;

/// Everything `worldpack serve` can be told.
#[derive(Clone, Debug)]
pub struct Config {
    pub addr: SocketAddr,
    pub store: PathBuf,
    /// `None`: memory-only (observe and select work, step does not).
    pub model: Option<PathBuf>,
    /// Where the model's graphs run: `None` in this process through ONNX
    /// Runtime; `triton://HOST:PORT` on a Triton server (the manifest is
    /// still read from `model`).
    pub model_backend: Option<String>,
    pub runtime: model::RuntimeOptions,
    /// Sampler steps when a step request does not say.
    pub steps: usize,
    pub method: Method,
    /// The policy of sessions that do not name one (a `memory::PolicySpec` as JSON).
    pub policy: serde_json::Value,
    pub max_body_bytes: usize,
    /// Step requests waiting on one session before the next gets 429.
    pub max_queue_per_session: usize,
    /// Model calls in flight across sessions before the next gets 503.
    pub max_inflight: usize,
    pub request_timeout: Duration,
    /// Geometry models: each generated frame shows the warp of its sources
    /// wherever it lands (the model fills only the holes), and is re-encoded.
    pub overlay_warp: bool,
    /// Batching across sessions: concurrent steps' model calls gathered for
    /// up to this long into one call of at most `batch_max` items; None: off.
    pub batch_window: Option<Duration>,
    pub batch_max: usize,
    /// Retention: sessions that no frame was written to for this long are
    /// deleted (`retention`); None: kept until deleted.
    pub retain_idle: Option<Duration>,
    /// API tokens and their tenants (`auth`); empty: every request is let in.
    pub tokens: Arc<auth::Tokens>,
    /// Serve a non-loopback address without tokens (otherwise refused).
    pub allow_unauthenticated: bool,
    /// HTTPS: the certificate chain and the private key, PEM files (`tls`); None: plain HTTP.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// A fusion-head model's memory keeps each frame's sampled latent instead
    /// of re-encoding the blended frame shown (one encoder call less a step).
    pub sampled_latents: bool,
    /// What one `imagine` request may ask for.
    pub imagine: imagine::Limits,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            addr: "127.0.0.1:8080".parse().unwrap(),
            store: PathBuf::from("data/worldpack.redb"),
            model: Some(PathBuf::from("fixtures/small")),
            model_backend: None,
            runtime: model::RuntimeOptions { provider: model::Provider::Cpu, threads: 1 },
            steps: 16,
            method: Method::Ancestral,
            policy: serde_json::json!({ "kind": "worldpack" }),
            max_body_bytes: 16 << 20,
            max_queue_per_session: 8,
            max_inflight: 64,
            request_timeout: Duration::from_secs(120),
            overlay_warp: false,
            batch_window: None,
            batch_max: 16,
            retain_idle: None,
            tokens: Arc::default(),
            allow_unauthenticated: false,
            tls: None,
            sampled_latents: false,
            imagine: imagine::Limits::default(),
        }
    }
}

/// The model in `dir`, its graphs run in this process (`backend` None) or on
/// the Triton server at `backend` (`triton://HOST:PORT`); errors name the flag.
pub fn load_model(dir: &std::path::Path, backend: Option<&str>, runtime: model::RuntimeOptions) -> Result<Model, String> {
    match backend {
        None => Model::load(dir, runtime).map_err(|e| format!("--model: {e}")),
        Some(url) => {
            let manifest = model::Manifest::load(dir).map_err(|e| format!("--model: {e}"))?;
            let graphs = kserve::KServeBackend::connect(url, &manifest).map_err(|e| format!("--model-backend: {e}"))?;
            Ok(Model::with_backend(dir, manifest, Box::new(graphs)))
        }
    }
}

/// A bound, not yet running server: its address is known (port 0 resolved).
pub struct Server {
    listener: tokio::net::TcpListener,
    router: Router,
    tls: Option<tokio_rustls::TlsAcceptor>,
    pub description: String,
}

impl Server {
    /// Opens the store (restoring every session), loads the model, binds.
    pub async fn bind(config: Config) -> Result<Server, String> {
        // A PostgreSQL client blocks on a runtime of its own: never on an async worker.
        let store = tokio::task::block_in_place(|| Store::open(&config.store)).map_err(|e| e.to_string())?;
        let model = match &config.model {
            Some(dir) => {
                let mut m = tokio::task::block_in_place(|| load_model(dir, config.model_backend.as_deref(), config.runtime))?;
                m.keep_sampled_latents(config.sampled_latents);
                m.overlay_warp(config.overlay_warp).map_err(|e| match e {
                    model::ModelError::Input { message, .. } => format!("--overlay-warp: {message}"),
                    other => format!("--overlay-warp: {other}"),
                })?;
                Some(m)
            }
            None if config.model_backend.is_some() => return Err("--model-backend: a memory-only server runs no model".into()),
            None => None,
        };
        session::policy_of(&config.policy).map_err(|e| format!("--policy: {}", e.message))?;
        if config.overlay_warp && model.is_none() {
            return Err("--overlay-warp: a memory-only server runs no model".into());
        }
        let mut engine = Engine::new(store, model);
        engine.batcher = config.batch_window.map(|w| batch::Batcher::new(w, config.batch_max));
        if !config.addr.ip().is_loopback() && !config.tokens.enabled() && !config.allow_unauthenticated {
            return Err(format!(
                "--addr {}: anyone who can reach this address could read, step and delete every session; give tokens \
                 (--tokens-file, or {} in the environment) or pass --allow-unauthenticated",
                config.addr,
                auth::TOKENS_ENV
            ));
        }
        let state = Arc::new(AppState {
            tokens: config.tokens.clone(),
            inflight: Semaphore::new(config.max_inflight),
            engine,
            sessions: RwLock::new(HashMap::new()),
            metrics: Metrics::default(),
            config: config.clone(),
        });
        let engine = &state.engine;
        let sessions = tokio::task::block_in_place(|| {
            let records = engine.store.sessions()?;
            session::restore_all(records, |id, start| Ok(engine.store.frames_from(id, start)?), |seed| engine.world(seed))
        })
        .map_err(|e| e.message)?;
        let restored = sessions.len();
        for s in sessions {
            state.sessions.write().unwrap().insert(s.id, Arc::new(Slot::new(s)));
        }
        if let Some(idle) = config.retain_idle {
            tokio::spawn(retention::expire_idle_sessions(state.clone(), idle));
        }
        let router = routes::router(state.clone())
            .merge(utoipa_swagger_ui::SwaggerUi::new("/docs").external_url_unchecked("/openapi.json", openapi::document()))
            .layer(axum::middleware::from_fn_with_state(config.tokens.clone(), auth::authenticate))
            .layer(DefaultBodyLimit::max(config.max_body_bytes))
            .layer(tower_http::timeout::TimeoutLayer::with_status_code(axum::http::StatusCode::REQUEST_TIMEOUT, config.request_timeout));
        let tls = config.tls.as_ref().map(|(cert, key)| tls::acceptor(cert, key)).transpose()?;
        let listener = tokio::net::TcpListener::bind(config.addr).await.map_err(|e| format!("--addr {}: {e}", config.addr))?;
        let addr = listener.local_addr().map_err(|e| e.to_string())?;
        let scheme = if tls.is_some() { "https" } else { "http" };
        let description = format!(
            "listening on {scheme}://{addr} (model: {}, provider: {}{}, store: {}, {restored} sessions restored, {})",
            config.model.as_ref().map_or("none (memory only)".into(), |p| p.display().to_string()),
            state.engine.model.as_ref().map_or("-", |m| m.provider()),
            config.model_backend.as_ref().map_or(String::new(), |url| format!(" at {url}")),
            Store::describe(&config.store),
            if config.tokens.enabled() { format!("tokens for tenants {}", config.tokens.tenants().join(", ")) } else { "no tokens: open".into() }
        );
        Ok(Server { listener, router, tls, description })
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.listener.local_addr().expect("bound listener has an address")
    }

    /// Serves until Ctrl-C or SIGTERM, finishing requests in flight.
    pub async fn run(self) -> Result<(), String> {
        match self.tls {
            Some(acceptor) => {
                let listener = tls::TlsListener::new(self.listener, acceptor).map_err(|e| e.to_string())?;
                axum::serve(listener, self.router).with_graceful_shutdown(shutdown()).await.map_err(|e| e.to_string())
            }
            None => axum::serve(self.listener, self.router).with_graceful_shutdown(shutdown()).await.map_err(|e| e.to_string()),
        }
    }
}

async fn shutdown() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
}
