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
