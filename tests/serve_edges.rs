//! The server's edges as an operator meets them: a clean stop on SIGTERM on
//! both stores with a step in flight, no database secret in any answer, log
//! line or metric, and readiness that reports a dependency that is down.

mod support;

use std::process::Stdio;
use std::time::Duration;

use serde_json::json;
use support::*;

/// SIGTERM while a step is being generated: the step is answered and stored,
/// the process exits 0, and a restarted server has the frame.
fn sigterm_finishes_the_step_in_flight(store: &std::path::Path) {
    let mut s = Server::start(store, &[]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    let url = s.url.clone();
    // Many sampler steps, so the request is still running when the signal comes.
    let step = std::thread::spawn(move || {
        answer(HTTP.post(&format!("{url}/v1/sessions/{id}/step")).set("Content-Type", "application/json")
            .send_string(&json!({ "action": { "forward": true }, "steps": 400 }).to_string()))
    });
    std::thread::sleep(Duration::from_millis(300));
    let status = s.terminate(Duration::from_secs(120)).expect("the server did not exit within 120 s of SIGTERM");
    let (code, r) = step.join().unwrap();
    assert_eq!((code, r["index"].as_u64()), (200, Some(1)), "the step in flight was not answered: {r}");
    assert!(status.success(), "the server did not exit cleanly on SIGTERM: {status:?}");
    let s = Server::start(store, &[]);
    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((code, r["frames"].as_u64()), (200, Some(2)), "the answered step's frame is not stored: {r}");
}

#[test]
fn sigterm_finishes_the_step_in_flight_and_exits_0_on_redb() {
    sigterm_finishes_the_step_in_flight(&temp_store("sigterm"));
}

#[test]
fn sigterm_finishes_the_step_in_flight_and_exits_0_on_postgres() {
    let pg = PgCluster::start("sigterm");
    sigterm_finishes_the_step_in_flight(&pg.url());
}

/// A connection string with a marker password: the database is stopped under
/// traffic, and the marker is in no answer body or header, no log line, no
/// metric and no startup line; readiness names the store while it is down.
#[test]
#[allow(clippy::result_large_err)] // `post` returns ureq's own Result
fn the_database_password_leaves_the_process_nowhere() {
    const MARKER: &str = "Sekr1tMarkerPw";
    let pg = PgCluster::start("secret");
    let url = std::path::PathBuf::from(format!("postgres://postgres:{MARKER}@127.0.0.1:{}/postgres", pg.port));
    let log = std::env::temp_dir().join(format!("worldpack-secret-{}.log", std::process::id()));
    let mut s = Server::start_with_stderr(&url, &[], Stdio::from(std::fs::File::create(&log).unwrap()));
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    let (code, r) = s.get("/v1/ready");
    assert_eq!((code, r["ready"].as_bool()), (200, Some(true)), "{r}");

    pg.stop();
    let seen = std::cell::RefCell::new(Vec::new());
    // Each answer whole (status, headers, body) into `seen`; its status back.
    let record = |resp: Result<ureq::Response, ureq::Error>| {
        let resp = match resp {
            Ok(r) => r,
            Err(ureq::Error::Status(_, r)) => r,
            Err(e) => panic!("transport error: {e}"),
        };
        let headers: Vec<String> = resp.headers_names().iter().map(|h| format!("{h}: {}", resp.header(h).unwrap_or(""))).collect();
        let status = resp.status();
        seen.borrow_mut().push(format!("{status} {} {}", headers.join("; "), resp.into_string().unwrap_or_default()));
        status
    };
    let post = |path: &str, body: serde_json::Value| HTTP.post(&format!("{}{path}", s.url)).set("Content-Type", "application/json").send_string(&body.to_string());
    for _ in 0..4 {
        assert_eq!(record(post(&format!("/v1/sessions/{id}/step"), json!({ "action": { "forward": true } }))), 503);
        record(post("/v1/sessions", json!({ "synthetic": { "seed": 4 } })));
        record(HTTP.get(&format!("{}/v1/sessions/{id}/frames/0", s.url)).call());
        record(HTTP.get(&format!("{}/v1/sessions/{id}", s.url)).call());
        record(HTTP.delete(&format!("{}/v1/sessions/{id}", s.url)).call());
    }
    assert_eq!(record(HTTP.get(&format!("{}/v1/ready", s.url)).call()), 503);
    let ready = seen.borrow().last().unwrap().clone();
    assert!(ready.contains("\"store\"") && ready.contains("retry-after"), "readiness does not name the store: {ready}");
    assert_eq!(record(HTTP.get(&format!("{}/v1/health", s.url)).call()), 200, "liveness stays up while the database is down");
    record(HTTP.get(&format!("{}/metrics", s.url)).call());
    let seen = seen.into_inner();
    assert!(seen.iter().any(|a| a.contains("store unavailable")), "no answer said the store was down: {seen:?}");

    pg.restart();
    let (code, _) = s.get("/v1/ready");
    assert_eq!(code, 200, "readiness comes back with the database");
    assert!(s.terminate(Duration::from_secs(60)).is_some_and(|st| st.success()));
    let stdout = s.rest_of_stdout();
    let stderr = std::fs::read_to_string(&log).unwrap();
    for (what, text) in seen.iter().map(|a| ("an answer", a.as_str())).chain([("stdout", stdout.as_str()), ("the log", stderr.as_str())]) {
        assert!(!text.contains(MARKER), "the password is in {what}: {text}");
    }
    let _ = std::fs::remove_file(&log);
}

#[test]
fn the_startup_line_names_the_database_without_its_password() {
    let pg = PgCluster::start("startup");
    let url = std::path::PathBuf::from(format!("postgres://postgres:Pw0rdMarker@127.0.0.1:{}/postgres", pg.port));
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_worldpack"))
        .args(["serve", "--memory-only", "--addr", "127.0.0.1:0", "--store", url.to_str().unwrap()])
        .stdout(Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().unwrap()), &mut line).unwrap();
    let _ = child.kill();
    let _ = child.wait();
    assert!(line.contains(&format!("postgres://postgres:***@127.0.0.1:{}/postgres", pg.port)), "{line}");
    assert!(!line.contains("Pw0rdMarker"), "{line}");
}

#[test]
fn readiness_names_a_store_that_cannot_be_reached_and_health_stays_live() {
    let pg = PgCluster::start("ready");
    let s = Server::start(&pg.url(), &["--memory-only"]);
    let (code, r) = s.get("/v1/ready");
    assert_eq!((code, r["ready"].as_bool(), r["down"].as_array().map(Vec::len)), (200, Some(true), Some(0)), "{r}");
    pg.stop();
    let (code, r) = s.get("/v1/ready");
    assert_eq!((code, r["down"][0]["name"].as_str()), (503, Some("store")), "{r}");
    assert_eq!(s.get("/v1/health").0, 200);
}

/// A self-signed certificate for 127.0.0.1 and its key, made by the openssl command line.
fn self_signed(dir: &std::path::Path, name: &str) -> (std::path::PathBuf, std::path::PathBuf) {
    let (cert, key) = (dir.join(format!("{name}.crt")), dir.join(format!("{name}.key")));
    let status = std::process::Command::new("openssl")
        .args(["req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2", "-subj", "/CN=127.0.0.1",
               "-addext", "subjectAltName=IP:127.0.0.1", "-keyout"])
        .arg(&key).arg("-out").arg(&cert).stderr(Stdio::null()).status().expect("openssl runs");
    assert!(status.success(), "openssl made no certificate");
    (cert, key)
}

/// `--tls-cert/--tls-key`: the server answers HTTPS that a client checking
/// the certificate accepts (curl), says https in its startup line, answers
/// no plain HTTP on that port, and stops on SIGTERM with exit 0; a missing
/// certificate or a key of another certificate is refused by flag.
#[test]
fn tls_serves_https_and_refuses_bad_files_by_flag() {
    let store = temp_store("tls");
    let dir = store.parent().unwrap().to_path_buf();
    std::fs::create_dir_all(&dir).unwrap();
    let (cert, key) = self_signed(&dir, "server");
    let mut s = Server::start(&store, &["--memory-only", "--tls-cert", cert.to_str().unwrap(), "--tls-key", key.to_str().unwrap()]);
    assert!(s.url.starts_with("https://127.0.0.1:"), "{}", s.url);
    let out = std::process::Command::new("curl")
        .args(["-s", "--cacert"]).arg(&cert).arg(format!("{}/v1/health", s.url)).output().expect("curl runs");
    let body: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|_| panic!("curl: {out:?}"));
    assert_eq!(body["status"], json!("ok"), "{body}");
    let plain = s.url.replace("https://", "http://");
    assert!(ureq::get(&format!("{plain}/v1/health")).timeout(Duration::from_secs(5)).call().is_err(), "plain HTTP was answered");
    assert_eq!(s.terminate(Duration::from_secs(10)).and_then(|st| st.code()), Some(0));

    let (other_cert, _) = self_signed(&dir, "other");
    let missing = dir.join("missing.crt");
    for (cert_arg, key_arg, flag) in [(&missing, &key, "--tls-cert"), (&other_cert, &key, "--tls-key")] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_worldpack"))
            .args(["serve", "--memory-only", "--addr", "127.0.0.1:0", "--store"]).arg(&store)
            .arg("--tls-cert").arg(cert_arg).arg("--tls-key").arg(key_arg).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{err}");
        assert!(err.contains(flag), "{flag}: {err}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
