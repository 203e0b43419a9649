//! Tokens and tenants (docs/api.md#tokens-and-tenants): two tenants on two
//! replicas of one PostgreSQL, every route tried across tenants, requests
//! without a token or with a wrong one, per-tenant limits, and the refusal to
//! serve a non-loopback address openly.

mod support;

use std::process::{Command, Stdio};

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

const TOKENS: &str = "acme:acme-token-1,beta:beta-token-2";

fn call(method: &str, url: &str, token: Option<&str>, body: Option<&Value>) -> (u16, Value, Option<String>) {
    let mut r = HTTP.request(method, url);
    if let Some(t) = token {
        r = r.set("Authorization", &format!("Bearer {t}"));
    }
    let resp = match body {
        Some(b) => r.set("Content-Type", "application/json").send_string(&b.to_string()),
        None => r.call(),
    };
    let resp = match resp {
        Ok(r) => r,
        Err(ureq::Error::Status(_, r)) => r,
        Err(e) => panic!("transport error: {e}"),
    };
    let status = resp.status();
    let challenge = resp.header("WWW-Authenticate").map(str::to_string);
    let bytes = { let mut v = Vec::new(); std::io::Read::read_to_end(&mut resp.into_reader(), &mut v).unwrap(); v };
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null), challenge)
}

/// Every route that names a session, as (method, path, body).
fn routes_on(id: u64, image: &str, pose: &Value) -> Vec<(&'static str, String, Option<Value>)> {
    vec![
        ("GET", format!("/v1/sessions/{id}"), None),
        ("POST", format!("/v1/sessions/{id}/step"), Some(json!({ "action": { "forward": true } }))),
        ("POST", format!("/v1/sessions/{id}/observe"), Some(json!({ "image_png": image, "pose": pose }))),
        ("POST", format!("/v1/sessions/{id}/select"), Some(json!({ "pose": pose }))),
        ("POST", format!("/v1/sessions/{id}/fork"), None),
        ("POST", format!("/v1/sessions/{id}/imagine"), Some(json!({ "candidates": [{ "actions": [{ "forward": true }] }] }))),
        ("GET", format!("/v1/sessions/{id}/frames/0"), None),
        ("GET", format!("/v1/sessions/{id}/frames/0/image"), None),
        ("GET", format!("/v1/sessions/{id}/frames/0/depth"), None),
        ("GET", format!("/v1/sessions/{id}/frames/0/truth"), None),
        ("DELETE", format!("/v1/sessions/{id}"), None),
    ]
}

#[test]
fn two_tenants_on_two_replicas_cannot_touch_each_others_sessions() {
    let pg = PgCluster::start("tenants");
    let env = [("WORLDPACK_TOKENS", TOKENS)];
    let a = Server::start_with(&pg.url(), &[], Stdio::inherit(), &env);
    let b = Server::start_with(&pg.url(), &[], Stdio::inherit(), &env);
    let tenants = [("acme", "acme-token-1"), ("beta", "beta-token-2")];
    // Each tenant makes a session, acme on replica a, beta on replica b.
    let mut ids = Vec::new();
    for ((_, token), server) in tenants.iter().zip([&a, &b]) {
        let (code, r, _) = call("POST", &format!("{}/v1/sessions", server.url), Some(token), Some(&json!({ "synthetic": { "seed": 3 } })));
        assert_eq!(code, 201, "{r}");
        ids.push(r["session"].as_u64().unwrap());
    }
    for (mine, (name, token)) in tenants.iter().enumerate() {
        let theirs = ids[1 - mine];
        for server in [&a, &b] {
            let (code, r, _) = call("GET", &format!("{}/v1/sessions", server.url), Some(token), None);
            assert_eq!((code, r["sessions"].clone()), (200, json!([ids[mine]])), "{name} lists only its own session on {}", server.url);
            let (_, frame, _) = call("GET", &format!("{}/v1/sessions/{}/frames/0", server.url, ids[mine]), Some(token), None);
            let (_, img, _) = call("GET", &format!("{}/v1/sessions/{}", server.url, ids[mine]), Some(token), None);
            assert!(img["frames"].as_u64().unwrap() >= 1);
            let image = {
                let mut v = Vec::new();
                std::io::Read::read_to_end(&mut HTTP.get(&format!("{}/v1/sessions/{}/frames/0/image", server.url, ids[mine]))
                    .set("Authorization", &format!("Bearer {token}")).call().unwrap().into_reader(), &mut v).unwrap();
                B64.encode(v)
            };
            let pose = json!({ "c2w": frame["pose"] });
            for (method, path, body) in routes_on(theirs, &image, &pose) {
                let (code, r, _) = call(method, &format!("{}{path}", server.url), Some(token), body.as_ref());
                assert_eq!((code, r["error"]["field"].as_str()), (404, Some("session")), "{name}: {method} {path} on another tenant's session: {r}");
            }
        }
    }
    // The owners still have their sessions whole, and may use every route.
    for (mine, (_, token)) in tenants.iter().enumerate() {
        let id = ids[mine];
        let (code, r, _) = call("POST", &format!("{}/v1/sessions/{id}/step", b.url), Some(token), Some(&json!({ "action": { "forward": true } })));
        assert_eq!((code, r["index"].as_u64()), (200, Some(1)), "{r}");
        let (code, _, _) = call("DELETE", &format!("{}/v1/sessions/{id}", a.url), Some(token), None);
        assert_eq!(code, 204);
    }
    // No token, a malformed header or a wrong token: 401 with a Bearer challenge, on every /v1 route.
    for server in [&a, &b] {
        for token in [None, Some("not-a-token")] {
            for (method, path, body) in routes_on(ids[0], "", &json!({})).into_iter().chain([("GET", "/v1/sessions".to_string(), None), ("POST", "/v1/sessions".to_string(), Some(json!({ "synthetic": { "seed": 1 } })))]) {
                let (code, r, challenge) = call(method, &format!("{}{path}", server.url), token, body.as_ref());
                assert_eq!((code, r["error"]["field"].as_str()), (401, Some("authorization")), "{method} {path} with {token:?}: {r}");
                assert_eq!(challenge.as_deref(), Some("Bearer realm=\"worldpack\""));
            }
        }
        let r = HTTP.get(&format!("{}/v1/sessions", server.url)).set("Authorization", "Basic YWNtZTp4").call();
        assert!(matches!(r, Err(ureq::Error::Status(401, _))), "a Basic header is not a bearer token");
    }
}

#[test]
fn a_tenant_over_its_session_limit_or_rate_gets_429_with_retry_after() {
    let env = [("WORLDPACK_TOKENS", TOKENS)];
    let s = Server::start_with(&temp_store("tenant-limits"), &["--memory-only", "--max-sessions-per-tenant", "2", "--rate-per-tenant", "5"], Stdio::inherit(), &env);
    let create = |token| call("POST", &format!("{}/v1/sessions", s.url), Some(token), Some(&json!({ "frames": [{ "image_png": png_1x1(), "pose": c2w([0.0, 0.0, 0.0]) }], "intrinsics": { "hfov_deg": 60, "width": 1, "height": 1 } })));
    let (code, first, _) = create("acme-token-1");
    assert_eq!(code, 201);
    // A fork is a live session of its tenant: it counts against the limit.
    let fork = || call("POST", &format!("{}/v1/sessions/{}/fork", s.url, first["session"]), Some("acme-token-1"), None);
    assert_eq!(fork().0, 201);
    let (code, r, _) = create("acme-token-1");
    assert_eq!((code, r["error"]["field"].as_str()), (429, Some("session")), "{r}");
    let (code, r, _) = fork();
    assert_eq!((code, r["error"]["field"].as_str()), (429, Some("session")), "a fork past the limit: {r}");
    assert_eq!(create("beta-token-2").0, 201, "another tenant has its own limit");
    // 5 requests a second, bursts of 10: a quick run of 30 is refused partway, with Retry-After.
    let mut refused = None;
    for _ in 0..30 {
        let resp = HTTP.get(&format!("{}/v1/sessions", s.url)).set("Authorization", "Bearer beta-token-2").call();
        if let Err(ureq::Error::Status(429, r)) = resp {
            refused = Some(r.header("Retry-After").map(str::to_string));
            break;
        }
    }
    let retry = refused.expect("30 quick requests at a rate of 5 a second were all let through");
    assert!(retry.and_then(|v| v.parse::<u64>().ok()).is_some_and(|v| v >= 1));
    assert_eq!(call("GET", &format!("{}/v1/sessions", s.url), Some("acme-token-1"), None).0, 200, "one tenant's rate does not hold up another");
}

fn png_1x1() -> String {
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, 1, 1);
    encoder.set_color(png::ColorType::Rgb);
    encoder.write_header().unwrap().write_image_data(&[128, 64, 32]).unwrap();
    B64.encode(bytes)
}

#[test]
fn a_non_loopback_address_needs_tokens_or_an_explicit_flag() {
    let store = temp_store("open-bind");
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack"))
        .args(["serve", "--memory-only", "--addr", "0.0.0.0:0", "--store", store.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--addr 0.0.0.0:0") && err.contains("--allow-unauthenticated"), "{err}");
    let open = Server::start(&store, &["--memory-only", "--addr", "0.0.0.0:0", "--allow-unauthenticated"]);
    open.kill();
    let with_tokens = Server::start_with(&store, &["--memory-only", "--addr", "0.0.0.0:0"], Stdio::inherit(), &[("WORLDPACK_TOKENS", TOKENS)]);
    with_tokens.kill();
}
