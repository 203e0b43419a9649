//! What the server keeps: acknowledged frames through SIGKILL on redb and
//! PostgreSQL, a stopped database, replicas on one database, retention.

mod support;

use std::path::Path;
use std::time::Duration;

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

#[test]
fn acknowledged_frames_survive_sigkill() {
    let store = temp_store("crash");
    acknowledged_writes_survive_sigkill(&store);
    let _ = std::fs::remove_dir_all(store.parent().unwrap());
}

/// The same crash test with the store on a real PostgreSQL cluster of the test's own.
#[test]
fn acknowledged_frames_survive_sigkill_on_postgres() {
    let pg = PgCluster::start("crash");
    acknowledged_writes_survive_sigkill(&pg.url());
}

/// Writes until the server is SIGKILLed, ten times over; every acknowledged frame is there after each restart.
fn acknowledged_writes_survive_sigkill(store: &Path) {
    let png = {
        let s = Server::start(&temp_store("crash-src"), &[]);
        let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 2 } }));
        B64.encode(s.bytes(&format!("/v1/sessions/{}/frames/0/image", c["session"])))
    };
    let intrinsics = json!({ "hfov_deg": 70, "width": 64, "height": 64 });
    let mut acknowledged: Vec<(u64, u64, f64)> = Vec::new(); // session, index, x
    for round in 0..10u64 {
        let s = Server::start(store, &["--memory-only"]);
        // Everything acknowledged before is there, bit for bit.
        for &(id, index, x) in &acknowledged {
            let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/{index}"));
            assert_eq!(code, 200, "round {round}: frame {id}/{index} lost: {r}");
            assert_eq!(r["pose"]["position"][0].as_f64(), Some(x), "round {round}: frame {id}/{index}");
        }
        let (_, c) = s.post("/v1/sessions", &json!({ "frames": [{ "image_png": png, "pose": c2w([0.0; 3]) }], "intrinsics": intrinsics }));
        let id = c["session"].as_u64().unwrap();
        acknowledged.push((id, 0, 0.0));
        let url = s.url.clone();
        let png = png.clone();
        let writer = std::thread::spawn(move || {
            let mut done = Vec::new();
            for k in 1..10_000u64 {
                let x = round as f64 * 1000.0 + k as f64;
                let body = json!({ "image_png": png.clone(), "pose": c2w([x, 0.0, 0.0]) }).to_string();
                match HTTP.post(&format!("{url}/v1/sessions/{id}/observe")).set("Content-Type", "application/json").send_string(&body) {
                    Ok(r) => {
                        let v: Value = r.into_json().unwrap();
                        done.push((id, v["index"].as_u64().unwrap(), x));
                    }
                    Err(_) => break, // the server died mid-request: not acknowledged
                }
            }
            done
        });
        std::thread::sleep(Duration::from_millis(300 + 97 * round));
        s.kill();
        let done = writer.join().unwrap();
        assert!(!done.is_empty(), "round {round}: some writes were acknowledged before the kill");
        acknowledged.extend(done);
    }
    let s = Server::start(store, &["--memory-only"]);
    for &(id, index, x) in &acknowledged {
        let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/{index}"));
        assert_eq!((code, r["pose"]["position"][0].as_f64()), (200, Some(x)), "frame {id}/{index}");
    }
}

/// PostgreSQL stopped under a running server: steps and observes answer 503
/// naming the store, nothing half-written shows, and service resumes when
/// the database is back.
#[test]
fn a_stopped_database_answers_503_and_service_resumes() {
    let pg = PgCluster::start("fault");
    let s = Server::start(&pg.url(), &[]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    let step = |s: &Server| s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!(step(&s).0, 200);
    pg.stop();
    let (code, r) = step(&s);
    assert_eq!((code, r["error"]["field"].as_str()), (503, Some("store")), "{r}");
    let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/1/image").replace("/image", ""));
    assert_eq!((code, r["error"]["field"].as_str()), (503, Some("store")), "{r}");
    pg.restart();
    let (code, r) = step(&s);
    assert_eq!((code, r["index"].as_u64()), (200, Some(2)), "the refused step left no frame behind: {r}");
    s.kill();
    let s = Server::start(&pg.url(), &[]);
    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((code, r["frames"].as_u64()), (200, Some(3)), "{r}");
}

/// Two replicas on one PostgreSQL, sharing nothing else: 16 sessions made on
/// either are stepped concurrently, each alternating between them; every
/// acknowledged frame reads back in order and byte for byte from both; a
/// retried step carrying its expected index makes no second frame; steps of
/// one session racing on both replicas each take a distinct index (the
/// database hands each out once: the loser gets 409); a deletion on one
/// replica is seen on the other.
#[test]
fn two_replicas_on_one_database_share_the_sessions() {
    let pg = PgCluster::start("replicas");
    replicas_share_the_sessions(&pg, &[]);
}

/// The replica test again, both replicas' model on one Triton server: Triton
/// sees every denoiser call and its dynamic batcher gathers some of them.
#[test]
fn two_replicas_on_one_database_and_one_triton_share_the_sessions() {
    let _alone = triton_alone();
    let pg = PgCluster::start("replicas-triton");
    let triton = TritonHost::start("fixtures/small", None);
    replicas_share_the_sessions(&pg, &["--model-backend", &triton.backend()]);
    let requests = triton.metric("nv_inference_request_success", "small-denoiser-worldpack");
    let executions = triton.metric("nv_inference_exec_count", "small-denoiser-worldpack");
    // 64 alternating steps, a retry and 8 racing steps, two sampler steps each.
    assert!(requests >= 2.0 * 64.0, "Triton saw {requests} denoiser calls");
    assert!(executions < requests, "Triton batched none of {requests} concurrent calls ({executions} executions)");
    eprintln!("Triton: {requests} denoiser calls in {executions} batched executions");
}

fn replicas_share_the_sessions(pg: &PgCluster, extra: &[&str]) {
    let (a, b) = (Server::start(&pg.url(), extra), Server::start(&pg.url(), extra));
    let replicas = [&a, &b];
    let ids: Vec<u64> = (0..16)
        .map(|n| {
            let (code, c) = replicas[n % 2].post("/v1/sessions", &json!({ "synthetic": { "seed": n } }));
            assert_eq!(code, 201, "{c}");
            c["session"].as_u64().unwrap()
        })
        .collect();
    std::thread::scope(|scope| {
        for (n, &id) in ids.iter().enumerate() {
            scope.spawn(move || {
                for k in 1..=4u64 {
                    let s = replicas[(n + k as usize) % 2];
                    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "expected_index": k }));
                    assert_eq!((code, r["index"].as_u64()), (200, Some(k)), "session {id}, step {k}: {r}");
                }
            });
        }
    });
    for &id in &ids {
        for s in replicas {
            assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64(), Some(5), "session {id} on {}", s.url);
        }
        for i in 0..5 {
            let (meta_a, meta_b) = (a.get(&format!("/v1/sessions/{id}/frames/{i}")).1, b.get(&format!("/v1/sessions/{id}/frames/{i}")).1);
            assert_eq!(meta_a, meta_b, "session {id} frame {i}");
            assert_eq!(meta_a["time"].as_u64(), Some(i), "in order: {meta_a}");
            assert_eq!(a.bytes(&format!("/v1/sessions/{id}/frames/{i}/image")), b.bytes(&format!("/v1/sessions/{id}/frames/{i}/image")));
        }
    }
    // A client that lost the answer to step 4 sends it again, to the other replica.
    let id = ids[0];
    let (code, r) = b.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "expected_index": 4 }));
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("expected_index")), "{r}");
    // Steps of one session racing on both replicas, without expected indices.
    let answers: Vec<(u16, Value)> = std::thread::scope(|scope| {
        let racers: Vec<_> = (0..8)
            .map(|n| scope.spawn(move || replicas[n % 2].post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "yaw_deg": 5 } }))))
            .collect();
        racers.into_iter().map(|r| r.join().unwrap()).collect()
    });
    let mut taken: Vec<u64> = Vec::new();
    for (code, r) in &answers {
        match code {
            200 => taken.push(r["index"].as_u64().unwrap()),
            409 => assert_eq!(r["error"]["field"].as_str(), Some("session"), "{r}"),
            _ => panic!("a racing step got {code}: {r}"),
        }
    }
    taken.sort();
    let codes: Vec<u16> = answers.iter().map(|(c, _)| *c).collect();
    assert_eq!(taken, (5..5 + taken.len() as u64).collect::<Vec<_>>(), "each acknowledged step its own index, none skipped (answers {codes:?})");
    for s in replicas {
        assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64(), Some(5 + taken.len() as u64));
    }
    let (code, _) = answer(HTTP.delete(&format!("{}/v1/sessions/{id}", a.url)).call());
    assert_eq!(code, 204);
    let (code, r) = b.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {} }));
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("session")), "deleted on the other replica: {r}");
    let metrics = String::from_utf8(a.bytes("/metrics")).unwrap();
    let caught_up = metrics.lines().find_map(|l| l.strip_prefix("worldpack_caught_up_frames_total ")).and_then(|v| v.parse::<u64>().ok());
    assert!(caught_up.is_some_and(|n| n > 0), "replica a read frames replica b wrote: {metrics}");
    // What a catch-up costs (reported, not asserted: a test is no benchmark).
    let value = |name: &str| metrics.lines().find_map(|l| l.strip_prefix(name)).and_then(|v| v.trim().parse::<f64>().ok()).unwrap_or(f64::NAN);
    let (count, seconds) = (value("worldpack_catch_ups_total "), value("worldpack_catch_up_seconds_sum "));
    eprintln!("replica a: {count} catch-ups, {:.2} ms each on average, {} frames read", 1e3 * seconds / count, caught_up.unwrap());
}

/// A replica SIGKILLed while its steps are in flight: the other replica
/// serves the session on, every step acknowledged before the kill reads back
/// intact, and the session's indices stay contiguous (a step the dead replica
/// committed but never answered is there once; one it did not commit is not).
#[test]
fn a_replica_killed_mid_step_loses_nothing_acknowledged() {
    let pg = PgCluster::start("replica-kill");
    let (a, b) = (Server::start(&pg.url(), &[]), Server::start(&pg.url(), &[]));
    let (_, c) = a.post("/v1/sessions", &json!({ "synthetic": { "seed": 4 } }));
    let id = c["session"].as_u64().unwrap();
    let url = a.url.clone();
    // Steps on replica a, one after another, until it dies under them.
    let stepper = std::thread::spawn(move || {
        let mut acknowledged = Vec::new();
        for _ in 0..200 {
            let r = HTTP.post(&format!("{url}/v1/sessions/{id}/step")).set("Content-Type", "application/json").send_string(&json!({ "action": { "forward": true } }).to_string());
            match r {
                Ok(resp) => acknowledged.push(resp.into_json::<Value>().unwrap()["index"].as_u64().unwrap()),
                Err(_) => break,
            }
        }
        acknowledged
    });
    std::thread::sleep(Duration::from_millis(600));
    a.kill();
    let acknowledged = stepper.join().unwrap();
    assert!(!acknowledged.is_empty() && acknowledged.len() < 200, "the kill came mid-run ({} steps answered)", acknowledged.len());
    let frames = b.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64().unwrap();
    let last = *acknowledged.last().unwrap();
    assert!(frames == last + 1 || frames == last + 2, "{frames} frames after {last} acknowledged: at most the step in flight is extra");
    eprintln!("killed after {} acknowledged steps; the store holds {frames} frames", acknowledged.len());
    for i in 0..frames {
        let (code, meta) = b.get(&format!("/v1/sessions/{id}/frames/{i}"));
        assert_eq!((code, meta["time"].as_u64()), (200, Some(i)), "{meta}");
        assert!(world::picture::decode_rgb(&b.bytes(&format!("/v1/sessions/{id}/frames/{i}/image"))).is_ok(), "frame {i} is a whole PNG");
    }
    let (code, r) = b.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(frames)), "{r}");
}

/// A synthetic session's generated and observed frames (latents, images,
/// depth, poses) on PostgreSQL, back after a SIGKILL and a restart.
#[test]
fn a_session_on_postgres_comes_back_whole() {
    let pg = PgCluster::start("session");
    let store = pg.url();
    let s = Server::start(&store, &[]);
    let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    assert_eq!(code, 201, "{c}");
    let id = c["session"].as_u64().unwrap();
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!(code, 200, "{r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "observe": true }));
    assert_eq!((code, r["source"].as_str()), (200, Some("observed")), "{r}");
    let before: Vec<(Value, Vec<u8>)> = (0..3).map(|i| (s.get(&format!("/v1/sessions/{id}/frames/{i}")).1, s.bytes(&format!("/v1/sessions/{id}/frames/{i}/image")))).collect();
    let depth = s.bytes(&format!("/v1/sessions/{id}/frames/2/depth"));
    s.kill();
    let s = Server::start(&store, &[]);
    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((code, r["frames"].as_u64(), r["has_latents"].as_bool()), (200, Some(3), Some(true)), "{r}");
    for (i, (meta, png)) in before.iter().enumerate() {
        assert_eq!(&s.get(&format!("/v1/sessions/{id}/frames/{i}")).1, meta, "frame {i}");
        assert_eq!(&s.bytes(&format!("/v1/sessions/{id}/frames/{i}/image")), png, "frame {i}");
    }
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/2/depth")), depth);
    // The restored session steps on from its stored latents.
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {} }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(3)), "{r}");
    let (code, _) = answer(HTTP.delete(&format!("{}/v1/sessions/{id}", s.url)).call());
    assert_eq!(code, 204);
    s.kill();
    let s = Server::start(&store, &[]);
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).0, 404, "a deleted session stays deleted");
}

#[test]
fn idle_sessions_expire_and_active_ones_stay_on_redb() {
    idle_sessions_expire(&temp_store("retention"));
}

#[test]
fn idle_sessions_expire_and_active_ones_stay_on_postgres() {
    let pg = PgCluster::start("retention");
    idle_sessions_expire(&pg.url());
}

/// With `--retain-idle-secs 2`, a session left alone is deleted, frames and
/// all, while one stepped every ~0.3 s stays whole; both stay so after a restart.
fn idle_sessions_expire(store: &Path) {
    let s = Server::start(store, &["--retain-idle-secs", "2"]);
    let create = || {
        let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
        assert_eq!(code, 201, "{c}");
        c["session"].as_u64().unwrap()
    };
    let (active, idle) = (create(), create());
    let start = std::time::Instant::now();
    let mut steps = 0;
    let expired_after = loop {
        let (code, r) = s.post(&format!("/v1/sessions/{active}/step"), &json!({ "action": { "forward": true } }));
        assert_eq!(code, 200, "the active session is never expired: {r}");
        steps += 1;
        let (code, r) = s.get(&format!("/v1/sessions/{idle}"));
        if code == 404 {
            assert_eq!(r["error"]["field"], "session", "{r}");
            break start.elapsed();
        }
        assert!(start.elapsed() < Duration::from_secs(15), "the idle session was not expired: {r}");
        std::thread::sleep(Duration::from_millis(300));
    };
    assert!(expired_after >= Duration::from_secs(2), "expired after {expired_after:?}, before its 2 s were up");
    let (code, _) = s.post(&format!("/v1/sessions/{idle}/step"), &json!({ "action": {} }));
    assert_eq!(code, 404, "an expired session takes no more steps");
    let metrics = String::from_utf8(s.bytes("/metrics")).unwrap();
    assert!(metrics.contains("worldpack_sessions_expired_total 1\n"), "{metrics}");
    s.kill();
    // Without retention the survivor is whole and the expired one stays gone.
    let s = Server::start(store, &[]);
    let (code, r) = s.get(&format!("/v1/sessions/{active}"));
    assert_eq!((code, r["frames"].as_u64()), (200, Some(steps + 1)), "{r}");
    assert_eq!(s.get(&format!("/v1/sessions/{idle}")).0, 404);
}

/// The link to PostgreSQL is TLS when the URL asks for it. A database that
/// takes TLS connections only serves a server that connects with
/// `sslmode=verify-full` (a session made and stepped over it) and refuses
/// one without TLS; `verify-full` refuses a database whose certificate names
/// another host, which `verify-ca` (the chain only) and `require` take.
#[test]
fn the_database_link_is_tls_when_the_url_asks_and_checks_the_name() {
    let url = |pg: &PgCluster, mode: &str| {
        std::path::PathBuf::from(format!("postgres://postgres@127.0.0.1:{}/postgres?sslmode={mode}&sslrootcert={}", pg.port, pg.ca().display()))
    };
    let pg = PgCluster::start_tls("tls", "IP:127.0.0.1,DNS:localhost");
    let s = Server::start(&url(&pg, "verify-full"), &[]);
    let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    assert_eq!(code, 201, "{c}");
    let (code, r) = s.post(&format!("/v1/sessions/{}/step", c["session"]), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(1)), "{r}");
    s.kill();
    let plain = api::store::Store::open(&pg.url()).err().expect("a TLS-only database took a plain connection");
    assert!(plain.to_string().contains("no encryption"), "{plain}");

    let other = PgCluster::start_tls("tls-other", "DNS:db.elsewhere.example");
    let refused = api::store::Store::open(&url(&other, "verify-full")).err().expect("verify-full took a certificate for another name");
    assert!(refused.to_string().contains("certificate not valid for name"), "{refused}");
    for mode in ["verify-ca", "require"] {
        api::store::Store::open(&url(&other, mode)).unwrap_or_else(|e| panic!("{mode}: {e}"));
    }
}

/// A database an earlier release made (the same tables with a session in
/// them, its own `schema_version` table, no refinery history) is adopted by
/// the refinery migrations as it is: the session stays and steps on.
#[test]
fn a_database_made_before_refinery_is_adopted_as_it_is() {
    let pg = PgCluster::start("adopt");
    let s = Server::start(&pg.url(), &[]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    s.kill();
    let mut psql = PgCluster::as_owner(PgCluster::bin("psql"));
    psql.args(["-h", "127.0.0.1", "-p", &pg.port.to_string(), "-U", "postgres", "-v", "ON_ERROR_STOP=1", "-c"]).arg(
        "DROP TABLE refinery_schema_history; CREATE TABLE schema_version (version INT NOT NULL); INSERT INTO schema_version VALUES (1), (2);",
    );
    PgCluster::run(psql, "psql");
    let s = Server::start(&pg.url(), &[]);
    let (code, r) = s.post(&format!("/v1/sessions/{}/step", c["session"]), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(1)), "{r}");
}
