//! What `worldpack serve` can be told: the server's settings and their defaults.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use model::Method;

use crate::{auth, imagine};

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
    /// The largest side of a session's frames; sessions keep and answer
    /// frames at their own size up to it (`Engine::max_frame_side`).
    pub max_frame_side: u32,
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
            max_frame_side: crate::engine::MAX_FRAME_SIDE,
        }
    }
}
