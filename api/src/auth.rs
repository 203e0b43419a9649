//! Tokens and tenants: who a request is, and how much it may do.
//!
//! With tokens configured, every `/v1` request carries `Authorization:
//! Bearer <token>`; the token's SHA-256 is compared in constant time with
//! every known hash, and the match names the tenant. A session belongs to
//! the tenant that created it; another tenant gets 404 for it, as for a
//! session that does not exist. Each tenant has a session limit and a
//! request rate (a token bucket); past either it gets 429 with `Retry-After`.
//! Tokens come from a file of hashes or an environment variable, never from
//! argv, and are never printed.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

use axum::extract::{FromRequestParts, Request, State};
use axum::http::request::Parts;
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};

use crate::error::ApiError;

/// The environment variable that may hold `tenant:token` pairs, comma-separated.
pub const TOKENS_ENV: &str = "WORLDPACK_TOKENS";

/// One tenant's allowance.
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Live sessions it may own at once (on this replica).
    pub sessions: usize,
    /// Requests a second, sustained; bursts of twice that pass.
    pub rate: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { sessions: 64, rate: 50.0 }
    }
}

#[derive(Clone, Debug)]
struct Entry {
    hash: [u8; 32],
    tenant: String,
    limits: Limits,
}

/// The tokens a server accepts (empty: no authentication).
#[derive(Debug, Default)]
pub struct Tokens {
    entries: Vec<Entry>,
    buckets: Mutex<HashMap<String, Bucket>>,
}

#[derive(Debug)]
struct Bucket {
    level: f64,
    at: Instant,
}

/// Who made a request: `None` when the server runs without tokens.
#[derive(Clone, Debug, PartialEq)]
pub struct Caller(pub Option<String>);

impl Caller {
    /// Whether this caller may see a session owned by `owner`.
    pub fn owns(&self, owner: Option<&str>) -> bool {
        match &self.0 {
            None => true,
            Some(me) => owner == Some(me.as_str()),
        }
    }
}

impl<S: Send + Sync> FromRequestParts<S> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, Self::Rejection> {
        Ok(parts.extensions.get::<Caller>().cloned().unwrap_or(Caller(None)))
    }
}

fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
}

fn parse_hex(field: &str, text: &str) -> Result<[u8; 32], String> {
    if text.len() != 64 {
        return Err(format!("{field}: a SHA-256 is 64 hex digits, got {}", text.len()));
    }
    let bytes: Vec<u8> = (0..text.len())
        .step_by(2)
        .map(|i| text.get(i..i + 2).and_then(|h| u8::from_str_radix(h, 16).ok()))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("{field}: not hexadecimal"))?;
    bytes.try_into().map_err(|_| format!("{field}: a SHA-256 is 64 hex digits"))
}

impl Tokens {
    /// Reads `--tokens-file` (lines `TENANT sha256:HEX [sessions=N] [rate=R]`,
    /// `#` comments) and the [`TOKENS_ENV`] variable (`TENANT:TOKEN,...`);
    /// `defaults` are the limits of entries that do not set their own.
    pub fn load(file: Option<&Path>, env: Option<&str>, defaults: &Limits) -> Result<Tokens, String> {
        let mut entries = Vec::new();
        if let Some(path) = file {
            let text = std::fs::read_to_string(path).map_err(|e| format!("--tokens-file {}: {e}", path.display()))?;
            for (n, line) in text.lines().enumerate() {
                let line = line.split('#').next().unwrap_or("").trim();
                if line.is_empty() {
                    continue;
                }
                let at = format!("--tokens-file {} line {}", path.display(), n + 1);
                let mut words = line.split_whitespace();
                let tenant = words.next().expect("a non-empty line has a word").to_string();
                let hash = words
                    .next()
                    .and_then(|w| w.strip_prefix("sha256:"))
                    .ok_or_else(|| format!("{at}: expected `TENANT sha256:HEX [sessions=N] [rate=R]`"))?;
                let mut limits = defaults.clone();
                for option in words {
                    match option.split_once('=') {
                        Some(("sessions", v)) => limits.sessions = v.parse().map_err(|_| format!("{at}: sessions={v} is not a whole number"))?,
                        Some(("rate", v)) => {
                            limits.rate = v.parse().ok().filter(|r: &f64| r.is_finite() && *r > 0.0).ok_or_else(|| format!("{at}: rate={v} is not a positive number"))?
                        }
                        _ => return Err(format!("{at}: unknown option {option:?} (sessions=N or rate=R)")),
                    }
                }
                entries.push(Entry { hash: parse_hex(&at, hash)?, tenant, limits });
            }
        }
        if let Some(list) = env {
            for (n, pair) in list.split(',').map(str::trim).filter(|p| !p.is_empty()).enumerate() {
                let (tenant, token) = pair
                    .split_once(':')
                    .filter(|(t, k)| !t.is_empty() && !k.is_empty())
                    .ok_or_else(|| format!("{TOKENS_ENV}: entry {} is not TENANT:TOKEN", n + 1))?;
                entries.push(Entry { hash: sha256(token.as_bytes()), tenant: tenant.to_string(), limits: defaults.clone() });
            }
        }
        let mut seen = std::collections::HashSet::new();
        if let Some(e) = entries.iter().find(|e| !seen.insert(e.hash)) {
            return Err(format!("the same token is given twice (tenant {})", e.tenant));
        }
        Ok(Tokens { entries, buckets: Mutex::default() })
    }

    pub fn enabled(&self) -> bool {
        !self.entries.is_empty()
    }

    /// The tenants, for the startup line (never the tokens).
    pub fn tenants(&self) -> Vec<&str> {
        let mut t: Vec<&str> = self.entries.iter().map(|e| e.tenant.as_str()).collect();
        t.sort_unstable();
        t.dedup();
        t
    }

    pub fn limits(&self, tenant: &str) -> Limits {
        self.entries.iter().find(|e| e.tenant == tenant).map(|e| e.limits.clone()).unwrap_or_default()
    }

    /// The tenant whose token this is. Every entry is compared, each in
    /// constant time, so the time taken says nothing about which matched.
    fn tenant_of(&self, token: &str) -> Option<&Entry> {
        let hash = sha256(token.as_bytes());
        let mut found = None;
        for e in &self.entries {
            let diff = e.hash.iter().zip(&hash).fold(0u8, |acc, (a, b)| acc | (a ^ b));
            if std::hint::black_box(diff) == 0 {
                found = Some(e);
            }
        }
        found
    }

    /// Takes one request from the tenant's bucket; the seconds to wait when it is empty.
    fn take(&self, e: &Entry) -> Result<(), f64> {
        let mut buckets = self.buckets.lock().unwrap();
        let now = Instant::now();
        let burst = 2.0 * e.limits.rate;
        let b = buckets.entry(e.tenant.clone()).or_insert(Bucket { level: burst, at: now });
        b.level = (b.level + now.duration_since(b.at).as_secs_f64() * e.limits.rate).min(burst);
        b.at = now;
        if b.level >= 1.0 {
            b.level -= 1.0;
            Ok(())
        } else {
            Err((1.0 - b.level) / e.limits.rate)
        }
    }
}

fn unauthorized(message: &str) -> Response {
    let mut r = ApiError::new(StatusCode::UNAUTHORIZED, "authorization", message).into_response();
    r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"worldpack\""));
    r
}

/// The middleware in front of every `/v1` route: with tokens configured, a
/// request without a known bearer token is refused with 401, one over its
/// tenant's rate with 429; the tenant rides on as a [`Caller`].
pub async fn authenticate(State(tokens): State<std::sync::Arc<Tokens>>, mut request: Request, next: Next) -> Response {
    if !tokens.enabled() || !request.uri().path().starts_with("/v1/") {
        return next.run(request).await;
    }
    let Some(value) = request.headers().get(header::AUTHORIZATION) else {
        return unauthorized("this server needs `Authorization: Bearer <token>`");
    };
    let Some(token) = value.to_str().ok().and_then(|v| v.strip_prefix("Bearer ")).map(str::trim) else {
        return unauthorized("the Authorization header must be `Bearer <token>`");
    };
    let Some(entry) = tokens.tenant_of(token) else {
        return unauthorized("unknown token");
    };
    if let Err(wait) = tokens.take(entry) {
        let mut r = ApiError::new(StatusCode::TOO_MANY_REQUESTS, "authorization", format!("tenant {} is over its rate of {} requests a second", entry.tenant, entry.limits.rate)).into_response();
        r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(wait.ceil().max(1.0) as u64));
        return r;
    }
    request.extensions_mut().insert(Caller(Some(entry.tenant.clone())));
    next.run(request).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(h: [u8; 32]) -> String {
        h.iter().map(|b| format!("{b:02x}")).collect()
    }

    #[test]
    fn a_file_of_hashes_and_the_environment_name_their_tenants() {
        let dir = std::env::temp_dir().join(format!("worldpack-tokens-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("tokens");
        std::fs::write(&file, format!("# tenants\nacme sha256:{} sessions=2 rate=5\n", hex(sha256(b"secret-a")))).unwrap();
        let t = Tokens::load(Some(&file), Some("beta:secret-b"), &Limits::default()).unwrap();
        assert_eq!(t.tenant_of("secret-a").map(|e| e.tenant.as_str()), Some("acme"));
        assert_eq!(t.tenant_of("secret-b").map(|e| e.tenant.as_str()), Some("beta"));
        assert!(t.tenant_of("secret-c").is_none());
        assert_eq!(t.limits("acme"), Limits { sessions: 2, rate: 5.0 });
        std::fs::write(&file, "acme sha256:abc\n").unwrap();
        let e = Tokens::load(Some(&file), None, &Limits::default()).unwrap_err();
        assert!(e.contains("line 1") && e.contains("64 hex digits"), "{e}");
        assert!(Tokens::load(None, Some("no-colon"), &Limits::default()).unwrap_err().contains(TOKENS_ENV));
    }

    #[test]
    fn a_tenant_over_its_rate_waits() {
        let t = Tokens::load(None, Some("a:x"), &Limits { sessions: 1, rate: 2.0 }).unwrap();
        let e = t.entries[0].clone();
        let passed = (0..10).filter(|_| t.take(&e).is_ok()).count();
        assert_eq!(passed, 4, "a burst of twice the rate passes, then nothing");
        assert!(t.take(&e).unwrap_err() > 0.0);
    }
}
