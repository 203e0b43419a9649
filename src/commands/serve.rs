//! `worldpack serve`: the REST API over a model and a store (`api::Server`).

use std::path::PathBuf;

use anyhow::{Result, bail};

use crate::cli::{parse_method, parse_provider};

#[derive(clap::Args)]
pub struct Args {
    /// Model folder (ONNX graphs + manifest.json); its manifest's `serving` block sets the
    /// sampler, steps, policy and selection it was measured with, unless the flags below say otherwise.
    #[arg(long, default_value = SERVED_MODEL)]
    pub model: PathBuf,
    /// Run without a model: observe and select work, step answers 409.
    #[arg(long, conflicts_with = "model")]
    pub memory_only: bool,
    /// Where the model's graphs run: in this process (default), or `triton://HOST:PORT`, a Triton
    /// Inference Server's HTTP port serving the model's graphs (serving/triton/host.py;
    /// docs/deployment.md). The manifest is still read from --model.
    #[arg(long, conflicts_with = "memory_only")]
    pub model_backend: Option<String>,
    /// The store: a redb file (created when missing), or a PostgreSQL database as
    /// postgres://USER[:PASSWORD]@HOST:PORT/DB (its schema is made and migrated on start).
    /// Either way the sessions in it are restored.
    #[arg(long, default_value = "data/worldpack.redb")]
    pub store: PathBuf,
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: std::net::SocketAddr,
    #[arg(long, default_value = "cpu", value_parser = parse_provider)]
    pub provider: model::Provider,
    /// Intra-op threads per model session.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Sampler steps per generated frame (a step request may override); default: the model's
    /// `serving` block, else 16.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=1000))]
    pub steps: Option<u64>,
    /// Sampler: ancestral, ddim or dpm2m (DPM-Solver++(2M): the 10-step DDIM's frames in about 8 calls);
    /// default: the model's `serving` block, else ancestral.
    #[arg(long, value_parser = parse_method)]
    pub method: Option<model::Method>,
    /// Policy of sessions that do not name one, by name (memory::variants): a preset, or an option such as
    /// worldpack_keep_last; default: the model's `serving` block, else worldpack.
    #[arg(long, value_parser = super::plan::parse_variant)]
    pub policy: Option<&'static memory::Variant>,
    /// Requests queued on one session before the next is refused with 429.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub max_queue: u64,
    /// Model calls in flight across sessions before the next is refused with 503.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    pub max_inflight: u64,
    /// Geometry models only: each generated frame keeps the warp of its sources wherever it
    /// lands, and the model fills only the holes (the composite; docs/geometry.md).
    #[arg(long)]
    pub overlay_warp: bool,
    /// Sessions that do not name a policy choose each step's plan and a geometry model's warp
    /// sources by co-visibility from the observed frames' depth instead of frustum overlap
    /// (their policy's `covisibility`, at its defaults; docs/geometry.md). `--covisible false`
    /// turns it off for a model whose `serving` block turns it on.
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub covisible: Option<bool>,
    /// Batching across sessions: gather concurrent steps' model calls for up to this many
    /// milliseconds into one call (0: off, each step calls alone).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=1000))]
    pub batch_window_ms: u64,
    /// The most steps one batched call serves.
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u64).range(1..=1024))]
    pub batch_max: u64,
    /// Retention: delete sessions that no frame was written to for this many seconds
    /// (swept every quarter of it, at most every minute; 0: keep them until deleted).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=10 * 365 * 86_400))]
    pub retain_idle_secs: u64,
    /// API tokens: a file of lines `TENANT sha256:HEX [sessions=N] [rate=R]` (the SHA-256 of each
    /// token, never the token). Tokens may also come from the environment, WORLDPACK_TOKENS=TENANT:TOKEN,...;
    /// with either, every /v1 route needs `Authorization: Bearer <token>` (docs/api.md).
    #[arg(long)]
    pub tokens_file: Option<PathBuf>,
    /// Live sessions a tenant may own at once, unless its line in the tokens file says otherwise.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub max_sessions_per_tenant: u64,
    /// Requests a second a tenant may make (bursts of twice that), unless its line says otherwise.
    #[arg(long, default_value_t = 50.0)]
    pub rate_per_tenant: f64,
    /// Serve a non-loopback --addr without tokens: anyone who reaches it may use every session.
    #[arg(long)]
    pub allow_unauthenticated: bool,
    /// Serve HTTPS: the certificate chain, a PEM file (with --tls-key; default: plain HTTP).
    #[arg(long, requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The certificate's private key, a PEM file (PKCS#8, PKCS#1 or SEC1).
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// A fusion-head model's memory keeps each frame's sampled latent instead of re-encoding the blended frame shown (one encoder call less a step).
    #[arg(long)]
    pub sampled_latents: bool,
    /// The most candidate futures (K) one `imagine` request may ask for.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub imagine_max_candidates: u64,
    /// The most steps (H) each imagined candidate may take.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub imagine_max_horizon: u64,
    /// The most MiB of imagined frames one `imagine` answer may carry (before base64).
    #[arg(long, default_value_t = 24, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub imagine_max_answer_mib: u64,
    /// The largest side, in pixels, of a session's frames: sessions keep their frames and answer
    /// steps at their own size up to it; larger ones are refused naming the field (docs/fullsize.md).
    #[arg(long, default_value_t = api::engine::MAX_FRAME_SIDE as u64, value_parser = clap::value_parser!(u64).range(256..=4096))]
    pub max_frame_side: u64,
}

pub fn run(a: Args) -> Result<()> {
    let Args { model, memory_only, model_backend, store, addr, provider, threads, steps, method, policy, max_queue, max_inflight, overlay_warp,
        covisible, batch_window_ms, batch_max, retain_idle_secs, tokens_file, max_sessions_per_tenant, rate_per_tenant, allow_unauthenticated,
        tls_cert, tls_key, sampled_latents, imagine_max_candidates, imagine_max_horizon, imagine_max_answer_mib, max_frame_side } = a;
    if !(rate_per_tenant.is_finite() && rate_per_tenant > 0.0) {
        bail!("--rate-per-tenant: must be a positive number, got {rate_per_tenant}");
    }
    // The model's `serving` block sets what the flags leave unsaid.
    let served = if memory_only { model::manifest::ServingSpec::default() } else { model::Manifest::load(&model)?.serving.unwrap_or_default() };
    let steps = steps.or(served.steps).unwrap_or(16);
    let method = match method {
        Some(m) => m,
        None => served.method.as_deref().unwrap_or("ancestral").parse().map_err(|e| anyhow::anyhow!("{}: serving.method: {e}", model.display()))?,
    };
    let policy = match policy {
        Some(p) => p,
        None => super::plan::parse_variant(served.policy.as_deref().unwrap_or("worldpack"))
            .map_err(|e| anyhow::anyhow!("{}: serving.policy: {e}", model.display()))?,
    };
    let covisible = covisible.or(served.covisible).unwrap_or(false);
    let limits = api::auth::Limits { sessions: max_sessions_per_tenant as usize, rate: rate_per_tenant };
    let env = std::env::var(api::auth::TOKENS_ENV).ok();
    let tokens = std::sync::Arc::new(api::auth::Tokens::load(tokens_file.as_deref(), env.as_deref(), &limits).map_err(anyhow::Error::msg)?);
    let config = api::Config {
        tokens,
        allow_unauthenticated,
        tls: tls_cert.zip(tls_key),
        sampled_latents,
        addr,
        store,
        model: (!memory_only).then_some(model),
        model_backend,
        runtime: model::RuntimeOptions { provider, threads },
        steps: steps as usize,
        method,
        policy: serde_json::json!({ "kind": policy.kind, "query": policy.query, "keep_last": policy.keep_last,
                                    "covisibility": covisible.then(memory::CoVisibility::default) }),
        max_queue_per_session: max_queue as usize,
        max_inflight: max_inflight as usize,
        overlay_warp,
        batch_window: (batch_window_ms > 0).then(|| std::time::Duration::from_millis(batch_window_ms)),
        batch_max: batch_max as usize,
        retain_idle: (retain_idle_secs > 0).then(|| std::time::Duration::from_secs(retain_idle_secs)),
        imagine: api::imagine::Limits {
            candidates: imagine_max_candidates as usize,
            horizon: imagine_max_horizon as usize,
            answer_bytes: (imagine_max_answer_mib as usize) << 20,
        },
        max_frame_side: max_frame_side as u32,
        ..api::Config::default()
    };
    serve(config)
}

/// The model served when `--model` is not given: the voxel world's 1-step student
/// (docs/models.md), whose manifest says how it is served.
pub const SERVED_MODEL: &str = "fixtures/variants/worldpack_geometry_fused_1step";

fn serve(config: api::Config) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async {
        let server = api::Server::bind(config).await.map_err(anyhow::Error::msg)?;
        println!("worldpack serve: {}", server.description);
        use std::io::Write;
        std::io::stdout().flush()?;
        server.run().await.map_err(anyhow::Error::msg)
    })
}
