//! The WorldPack REST server: sessions of frames with poses, a step endpoint
//! that generates the next frame from a packed memory context, and a durable
//! store underneath. See docs/api.md.

pub mod auth;
pub mod batch;
mod config;
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
use std::sync::{Arc, RwLock};

use axum::Router;
use axum::extract::DefaultBodyLimit;
use model::Model;
use tokio::sync::Semaphore;

pub use config::Config;
pub use error::ApiError;
pub use refusal::EngineError;
use engine::Engine;
use state::{AppState, Metrics, Slot};
use store::Store;

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
        engine.max_frame_side = config.max_frame_side;
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
