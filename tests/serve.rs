//! The REST server as users meet it: the real `worldpack serve` process on
//! loopback, real HTTP, a real store on disk, SIGKILL and restart.

mod support;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use base64::Engine;
use base64::engine::general_purpose::STANDARD as B64;
use serde_json::{Value, json};
use support::*;

#[test]
fn a_synthetic_session_steps_observes_selects_and_reads_back() {
    let store = temp_store("flow");
    let s = Server::start(&store, &[]);
    let (code, health) = s.get("/v1/health");
    assert_eq!((code, health["provider"].as_str()), (200, Some("cpu")));

    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    let mut last_pose = Value::Null;
    for i in 1..=20u64 {
        let turn = if i % 5 == 0 { 12.0 } else { 0.0 };
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": turn } }));
        assert_eq!(code, 200, "{r}");
        assert_eq!(r["index"].as_u64(), Some(i));
        let png = B64.decode(r["image_png"].as_str().unwrap()).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let plan = r["selection"]["plan"]["slots"].as_array().unwrap();
        assert_eq!(plan.len(), 22, "worldpack packs 22 slots");
        let used: Vec<u64> = plan.iter().filter_map(|s| s["frame"].as_u64()).collect();
        assert_eq!(used.len() as u64, i.min(22), "every earlier frame fits until there are 22");
        assert!(used.iter().all(|&f| f < i), "only earlier frames are context");
        assert_ne!(r["pose"], last_pose, "the motion model moved the camera");
        last_pose = r["pose"].clone();
        let psnr = r["truth"]["psnr_db"].as_f64().unwrap();
        assert!(psnr.is_finite() && psnr > 5.0, "a synthetic step scores itself against the world: {}", r["truth"]);
        assert_eq!(r["truth"]["image"], format!("/v1/sessions/{id}/frames/{i}/truth"));
        assert!(r["selection"]["warp_frames"] == json!([]) && r["timings_ms"]["warp"] == 0.0, "this model takes no warp: {r}");
    }
    // The first frame is the world's own render, so its truth is the same picture.
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/0/truth")), s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    assert_ne!(s.bytes(&format!("/v1/sessions/{id}/frames/7/truth")), s.bytes(&format!("/v1/sessions/{id}/frames/7/image")));
    // Observe a real frame (the first one again), then ask what a pose would use.
    let image = B64.encode(s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    let (code, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    assert_eq!(code, 200);
    let pose = json!({ "c2w": frame0["pose"] });
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": image, "pose": pose }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(21)), "{r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/select"), &json!({ "pose": pose }));
    assert_eq!(code, 200, "{r}");
    let best = &r["plan"]["slots"][0];
    assert!(best["frame"] == 0 || best["frame"] == 21, "the frames taken from this very pose rank first: {best}");
    assert!((best["overlap"].as_f64().unwrap() - 1.0).abs() < 1e-9);

    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!((code, r["frames"].as_u64()), (200, Some(22)));
    let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/7"));
    assert_eq!((code, r["source"].as_str()), (200, Some("generated")));
    let (code, _) = answer(HTTP.delete(&format!("{}/v1/sessions/{id}", s.url)).call());
    assert_eq!(code, 204);
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).0, 404);
    let text = HTTP.get(&format!("{}/metrics", s.url)).call().unwrap().into_string().unwrap();
    assert!(text.contains("worldpack_steps_total 20") && text.contains("worldpack_observes_total 1"), "{text}");
}

#[test]
fn without_a_model_the_server_is_a_memory_store() {
    let store = temp_store("memory");
    let with_model = Server::start(&temp_store("memory-src"), &[]);
    let (_, created) = with_model.post("/v1/sessions", &json!({ "synthetic": { "seed": 5 } }));
    let png = B64.encode(with_model.bytes(&format!("/v1/sessions/{}/frames/0/image", created["session"])));
    drop(with_model);

    let s = Server::start(&store, &["--memory-only"]);
    let intrinsics = json!({ "hfov_deg": 70, "width": 64, "height": 64 });
    let (code, r) = s.post("/v1/sessions", &json!({ "frames": [{ "image_png": png, "pose": c2w([0.0, 0.0, 0.0]) }], "intrinsics": intrinsics }));
    assert_eq!(code, 201, "{r}");
    let id = r["session"].as_u64().unwrap();
    for x in 1..5 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([x as f64 * 5.0, 0.0, 0.0]) }));
        assert_eq!((code, r["has_latent"].as_bool()), (200, Some(false)), "{r}");
    }
    let (code, r) = s.post(&format!("/v1/sessions/{id}/select"), &json!({ "pose": c2w([20.0, 0.0, 1.0]) }));
    assert_eq!(code, 200);
    assert_eq!(r["plan"]["slots"][0]["frame"], 4, "the nearest view ranks first: {r}");
    assert_eq!(r["plan"]["slots"][1]["frame"], 3, "then the one five units back: {r}");
    // Depth rides along as a 16-bit PNG (millimetres) and comes back byte for byte.
    let depth = {
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 64, 64);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mm: Vec<u8> = (0..64 * 64u32).flat_map(|i| ((1000 + i) as u16).to_be_bytes()).collect();
        enc.write_header().unwrap().write_image_data(&mm).unwrap();
        out
    };
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([21.0, 0.0, 0.0]), "depth_png16": B64.encode(&depth) }));
    assert_eq!(code, 200, "{r}");
    let index = r["index"].as_u64().unwrap();
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/{index}/depth")), depth);
    assert_eq!(s.get(&format!("/v1/sessions/{id}/frames/1/depth")).1["error"]["field"], "depth");
    let (code, r) = s.get(&format!("/v1/sessions/{id}/frames/1/truth"));
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("truth")), "real frames have no truth here: {r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": png, "pose": c2w([0.0; 3]), "depth_png16": png }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("depth_png16")), "an RGB image is not a depth map: {r}");
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("model")));
}

#[test]
fn bad_requests_get_4xx_json_naming_the_field() {
    let s = Server::start(&temp_store("bad"), &[]);
    let (_, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = created["session"].as_u64().unwrap();
    let step = format!("/v1/sessions/{id}/step");
    let small_png = {
        // A 32x32 frame: the session camera says 64x64.
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, 32, 32);
        enc.set_color(png::ColorType::Rgb);
        enc.write_header().unwrap().write_image_data(&[90u8; 32 * 32 * 3]).unwrap();
        B64.encode(out)
    };
    let cases: Vec<(&str, String, Value, u16, &str)> = vec![
        ("unknown session", "/v1/sessions/999/step".into(), json!({ "action": {} }), 404, "session"),
        ("bad session id", "/v1/sessions/abc/step".into(), json!({ "action": {} }), 400, "session"),
        ("turn too large", step.clone(), json!({ "action": { "yaw_deg": 1000 } }), 400, "action.yaw_deg"),
        ("key not a bool", step.clone(), json!({ "action": { "jump": "yes" } }), 400, "action.jump"),
        ("no action", step.clone(), json!({}), 400, "body"),
        ("unknown field", step.clone(), json!({ "action": {}, "speed": 2 }), 400, "speed"),
        ("far-away pose", step.clone(), json!({ "action": {}, "pose": c2w([0.0, 1e308, 0.0]) }), 400, "pose.position"),
        ("not a rotation", step.clone(), json!({ "action": {}, "pose": { "c2w": { "rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 0, 0] } } }), 400, "pose.rotation"),
        ("zero steps", step.clone(), json!({ "action": {}, "steps": 0 }), 400, "steps"),
        ("unknown policy", "/v1/sessions".into(), json!({ "synthetic": { "seed": 1 }, "policy": { "kind": "magic" } }), 400, "policy.kind"),
        ("both starts", "/v1/sessions".into(), json!({ "synthetic": { "seed": 1 }, "frames": [] }), 400, "frames"),
        ("no intrinsics", "/v1/sessions".into(), json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }] }), 400, "intrinsics"),
        ("wrong image size", "/v1/sessions".into(),
            json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }], "intrinsics": { "hfov_deg": 70, "width": 64, "height": 64 } }), 400, "frames[0].image_png"),
        ("not a png", format!("/v1/sessions/{id}/observe"), json!({ "image_png": "aGVsbG8=", "pose": c2w([0.0; 3]) }), 400, "image_png"),
        ("bad fov", "/v1/sessions".into(), json!({ "frames": [{ "image_png": small_png, "pose": c2w([0.0; 3]) }], "intrinsics": { "hfov_deg": 200, "width": 32, "height": 32 } }), 400, "intrinsics.hfov_deg"),
    ];
    for (what, path, body, status, field) in cases {
        let (code, r) = s.post(&path, &body);
        assert_eq!(code, status, "{what}: {r}");
        assert_eq!(r["error"]["field"].as_str(), Some(field), "{what}: {r}");
        assert!(!r["error"]["message"].as_str().unwrap().is_empty(), "{what}");
    }
    // JSON has no NaN; an overflowing number is the closest a client can send.
    let (code, r) = answer(HTTP.post(&format!("{}{step}", s.url)).set("Content-Type", "application/json")
        .send_string(r#"{"action": {}, "pose": {"c2w": {"rotation": [[1,0,0],[0,1,0],[0,0,1]], "position": [0, 1e999, 0]}}}"#));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("pose.c2w.position[1]")), "{r}");
    let (code, r) = answer(HTTP.post(&format!("{}{step}", s.url)).set("Content-Type", "text/plain").send_string("{}"));
    assert_eq!((code, r["error"]["field"].as_str()), (415, Some("content-type")));
    // A body over the limit is refused once the server has read past it. Sent by hand: a
    // client still writing when the server answers and closes sees a broken pipe, and the
    // answer is already waiting in the socket.
    let (code, r) = oversized_post(&s.url, &step, 17 << 20);
    assert_eq!((code, r["error"]["field"].as_str()), (413, Some("body")), "{r}");
    let (code, r) = s.get("/v1/nowhere");
    assert_eq!((code, r["error"]["field"].as_str()), (404, Some("path")));
    // The session is untouched by all of it.
    let (_, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!(r["frames"], 1);
}

#[test]
fn sixteen_sessions_step_concurrently() {
    let s = Server::start(&temp_store("concurrent"), &[]);
    let ids: Vec<u64> = (0..16).map(|i| s.post("/v1/sessions", &json!({ "synthetic": { "seed": i % 4 } })).1["session"].as_u64().unwrap()).collect();
    std::thread::scope(|scope| {
        for &id in &ids {
            let s = &s;
            scope.spawn(move || {
                for i in 1..=3u64 {
                    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
                    assert_eq!(code, 200, "session {id}: {r}");
                    assert_eq!(r["index"].as_u64(), Some(i), "steps within a session are ordered");
                }
            });
        }
    });
    for id in ids {
        assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"], 4);
    }
}

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

/// A throwaway PostgreSQL 15 cluster on a loopback port (initdb refuses to
/// run as root, so as root it runs as the `postgres` user), removed on drop.
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

#[test]
fn the_openapi_document_describes_the_routes_and_docs_are_served_offline() {
    let s = Server::start(&temp_store("openapi"), &["--memory-only"]);
    let (code, doc) = s.get("/openapi.json");
    assert_eq!(code, 200);
    let paths = doc["paths"].as_object().unwrap();
    assert!(paths.len() >= 9);
    for (path, item) in paths {
        let concrete = path.replace("{id}", "999999").replace("{index}", "0");
        for method in item.as_object().unwrap().keys().filter(|m| ["get", "post", "delete"].contains(&m.as_str())) {
            let url = format!("{}{concrete}", s.url);
            let resp = match method.as_str() {
                "get" => HTTP.get(&url).call(),
                "delete" => HTTP.delete(&url).call(),
                _ => HTTP.post(&url).set("Content-Type", "application/json").send_string("{}"),
            };
            let (code, body) = answer(resp);
            assert_ne!(body["error"]["field"], "path", "{method} {path} is documented but not routed ({code})");
        }
    }
    let html = HTTP.get(&format!("{}/docs/", s.url)).call().unwrap().into_string().unwrap();
    assert!(html.contains("swagger-ui"), "the docs page is Swagger UI, served from the binary");
}

#[test]
fn full_queues_answer_429_and_503_and_lose_nothing() {
    let s = Server::start(&temp_store("queues"), &["--max-queue", "1", "--max-inflight", "1"]);
    let ids: Vec<u64> = (0..2).map(|_| s.post("/v1/sessions", &json!({ "synthetic": { "seed": 1 } })).1["session"].as_u64().unwrap()).collect();
    // Many slow steps at once: on one session they queue (429 past one waiting),
    // across sessions they compete for the one model slot (503).
    let codes: Vec<u16> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..8)
            .map(|i| {
                let (s, id) = (&s, ids[i % 2]);
                scope.spawn(move || s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true }, "steps": 40 })))
            })
            .collect();
        workers.into_iter().map(|w| w.join().unwrap()).map(|(code, r)| {
            if code != 200 {
                assert!(r["error"]["message"].as_str().is_some(), "{r}");
            }
            code
        }).collect()
    });
    assert!(codes.iter().all(|c| [200, 429, 503].contains(c)), "{codes:?}");
    assert!(codes.contains(&200), "{codes:?}");
    assert!(codes.iter().any(|&c| c == 429 || c == 503), "8 concurrent slow steps against queue 1 / in-flight 1: {codes:?}");
    // Exactly the accepted steps were stored.
    let stored: u64 = ids.iter().map(|id| s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64().unwrap() - 1).sum();
    assert_eq!(stored, codes.iter().filter(|&&c| c == 200).count() as u64);
}

#[test]
fn a_geometry_model_warps_the_best_observed_frame_with_depth_across_restarts() {
    let store = temp_store("geometry");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry");
    let s = Server::start(&store, &["--model", model]);
    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    let step = |body: Value| s.post(&format!("/v1/sessions/{id}/step"), &body);
    // A synthetic session's first frame comes with the world's depth, as a depth camera's would.
    let depth = s.bytes(&format!("/v1/sessions/{id}/frames/0/depth"));
    assert_eq!(&depth[1..4], b"PNG");
    for i in 1..=3u64 {
        let (code, r) = step(json!({ "action": { "forward": true } }));
        assert_eq!(code, 200, "{r}");
        assert_eq!(r["selection"]["warp_frames"][0].as_u64(), Some(0), "step {i}: only frame 0 has depth: {r}");
        assert!(r["timings_ms"]["warp"].as_f64().unwrap() > 0.0, "{r}");
    }
    // An observing step records the world's frame and depth: the next step warps it first.
    let (code, r) = step(json!({ "action": { "forward": true }, "observe": true }));
    assert_eq!((code, r["source"].as_str(), r["index"].as_u64()), (200, Some("observed"), Some(4)), "{r}");
    assert!(r["truth"].is_null(), "an observed frame is the truth: {r}");
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/4/depth"))[1..4], *b"PNG");
    let (code, r) = step(json!({ "action": {} }));
    assert_eq!((code, r["selection"]["warp_frames"][0].as_u64()), (200, Some(4)), "{r}");
    // A frame observed through the API with depth joins the warp sources too.
    let (_, frame3) = s.get(&format!("/v1/sessions/{id}/frames/3"));
    let pose3 = json!({ "c2w": frame3["pose"] });
    let truth3 = s.bytes(&format!("/v1/sessions/{id}/frames/3/truth"));
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": B64.encode(&truth3), "pose": pose3, "depth_png16": B64.encode(&depth) }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(6)), "{r}");
    let (code, r) = step(json!({ "action": {}, "pose": pose3 }));
    assert_eq!((code, r["selection"]["warp_frames"][0].as_u64()), (200, Some(6)), "{r}");
    // Wrong depth, or an observing step with a pose, is refused by name and stores nothing.
    let (code, r) = s.post(&format!("/v1/sessions/{id}/observe"), &json!({ "image_png": B64.encode(&truth3), "pose": pose3, "depth_png16": B64.encode(&truth3) }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("depth_png16")), "{r}");
    let (code, r) = step(json!({ "action": {}, "pose": pose3, "observe": true }));
    assert_eq!((code, r["error"]["field"].as_str()), (400, Some("observe")), "{r}");
    let (_, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    let pose0 = json!({ "c2w": frame0["pose"] });
    s.kill();
    // After a restart the warp sources come back from the store.
    let s = Server::start(&store, &["--model", model]);
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {}, "pose": pose0 }));
    assert_eq!((code, r["index"].as_u64()), (200, Some(8)), "{r}");
    assert_eq!(r["selection"]["warp_frames"][0].as_u64(), Some(0), "{r}");
    // Occlusion-aware selection reads the restored depth: three observed frames have it.
    let select = |body: Value| s.post(&format!("/v1/sessions/{id}/select"), &body);
    let (code, r) = select(json!({ "pose": pose0, "covisibility": {} }));
    assert_eq!(code, 200, "{r}");
    let c = &r["covisibility"];
    assert!(c["candidates"].as_u64().unwrap() >= 3 && c["with_depth"] == 3 && c["surface_points"].as_u64().unwrap() > 0, "{r}");
    let (code, r) = select(json!({ "pose": pose0 }));
    assert!(code == 200 && r.get("covisibility").is_none(), "{r}");
    for (bad, field) in [(json!({ "cells": 0 }), "covisibility.cells"), (json!({ "tolerance": -1 }), "covisibility.tolerance"), (json!({ "nope": 1 }), "covisibility")] {
        let (code, r) = select(json!({ "pose": pose0, "covisibility": bad }));
        assert_eq!(code, 400, "{r}");
        assert!(r["error"]["field"].as_str().unwrap().starts_with(field), "{field}: {r}");
    }
    s.kill();
    // With --overlay-warp what the sources show is kept as seen: in a new session, at frame 0's own
    // pose, frame 0 (the only one with depth) warps onto every pixel, so the step gives it back.
    let s = Server::start(&store, &["--model", model, "--overlay-warp"]);
    let (_, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = created["session"].as_u64().unwrap();
    let (_, frame0) = s.get(&format!("/v1/sessions/{id}/frames/0"));
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": {}, "pose": { "c2w": frame0["pose"] } }));
    assert_eq!(code, 200, "{r}");
    assert_eq!(s.bytes(&format!("/v1/sessions/{id}/frames/1/image")), s.bytes(&format!("/v1/sessions/{id}/frames/0/image")));
    assert_eq!(r["truth"]["psnr_db"].as_f64(), Some(100.0), "{r}");
}

#[test]
fn overlay_warp_needs_a_geometry_model() {
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack"))
        .args(["serve", "--addr", "127.0.0.1:0", "--store", temp_store("overlay").to_str().unwrap(), "--overlay-warp"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--overlay-warp"), "{}", String::from_utf8_lossy(&out.stderr));
}

/// The paper's token geometry end to end (fixtures/paper_tokens: 224x224
/// frames, 28x28 latents, random weights): a synthetic session steps until
/// its memory fills the 22 packed slots, and every answer is a 224x224 frame.
#[test]
fn the_paper_token_geometry_serves_a_synthetic_session() {
    let store = temp_store("paper-tokens");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/paper_tokens");
    let s = Server::start(&store, &["--model", model]);
    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 }, "policy": { "kind": "worldpack" } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    for i in 1..=24u64 {
        let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": 15 } }));
        assert_eq!(code, 200, "{r}");
        let png = B64.decode(r["image_png"].as_str().unwrap()).unwrap();
        let side = |at: usize| u32::from_be_bytes(png[at..at + 4].try_into().unwrap());
        assert_eq!((&png[12..16], side(16), side(20)), (&b"IHDR"[..], 224, 224), "step {i}: the frame is 224x224");
        let slots = r["selection"]["plan"]["slots"].as_array().unwrap();
        let used_at = |rate: u64| slots.iter().filter(|s| s["rate"] == rate && s["frame"].is_u64()).count() as u64;
        let used = used_at(1) + used_at(4) + used_at(16);
        assert_eq!(used, i.min(22), "step {i}: every earlier frame fits until there are 22");
        if i > 22 {
            assert_eq!((used_at(1), used_at(4), used_at(16)), (2, 4, 16), "step {i}: the paper's 2 + 4 + 16 slots");
        }
    }
}

/// `serve --covisible`: each step's plan and warp sources come from
/// co-visibility over the observed frames' depth.
#[test]
fn covisible_serving_chooses_warp_sources_among_the_observed_frames() {
    let store = temp_store("covisible");
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry");
    let s = Server::start(&store, &["--model", model, "--covisible"]);
    let (code, created) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    assert_eq!(code, 201, "{created}");
    let id = created["session"].as_u64().unwrap();
    let step = |body: Value| s.post(&format!("/v1/sessions/{id}/step"), &body);
    for _ in 0..3 {
        let (code, r) = step(json!({ "action": { "forward": true }, "observe": true }));
        assert_eq!((code, r["source"].as_str()), (200, Some("observed")), "{r}");
    }
    for i in 4..=6u64 {
        let (code, r) = step(json!({ "action": { "forward": true } }));
        assert_eq!((code, r["index"].as_u64()), (200, Some(i)), "{r}");
        let sources: Vec<u64> = r["selection"]["warp_frames"].as_array().unwrap().iter().map(|f| f.as_u64().unwrap()).collect();
        assert!(!sources.is_empty() && sources.iter().all(|&f| f <= 3), "observed frames 0-3 have depth: {r}");
        assert_eq!(r["selection"]["exact_evaluations"], 0, "co-visibility reports no frustum evaluations: {r}");
        let used = r["selection"]["plan"]["slots"].as_array().unwrap().iter().filter(|s| s["frame"].is_u64()).count() as u64;
        assert_eq!(used, i, "every earlier frame fits: {r}");
    }
}

/// Batching across sessions: four identical sessions step at once with the
/// same seed and share model calls; each frame equals the frame a lone step
/// makes, within 1/255 per pixel (a batched call may round differently).
#[test]
fn batched_steps_make_the_frames_a_lone_step_makes() {
    let store = temp_store("batching");
    let s = Server::start(&store, &["--batch-window-ms", "200", "--batch-max", "8"]);
    let ids: Vec<u64> = (0..5)
        .map(|_| s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } })).1["session"].as_u64().unwrap())
        .collect();
    let body = json!({ "action": { "forward": true, "yaw_deg": 5 }, "seed": 11 });
    let frames: Vec<Value> = std::thread::scope(|scope| {
        let (s, body) = (&s, &body);
        let workers: Vec<_> = ids[..4].iter().map(|&id| scope.spawn(move || s.post(&format!("/v1/sessions/{id}/step"), body))).collect();
        workers.into_iter().map(|w| w.join().unwrap()).map(|(code, r)| { assert_eq!(code, 200, "{r}"); r }).collect()
    });
    let text = HTTP.get(&format!("{}/metrics", s.url)).call().unwrap().into_string().unwrap();
    let counter = |name: &str| text.lines().find(|l| l.starts_with(name)).and_then(|l| l.split_whitespace().nth(1)).unwrap().parse::<u64>().unwrap();
    let (calls, items) = (counter("worldpack_batched_calls_total"), counter("worldpack_batched_items_total"));
    assert_eq!(items, 4, "{text}");
    assert!(calls < items, "concurrent steps shared a call: {calls} calls for {items} steps");
    // The fifth session steps alone, in a call of its own.
    let (code, alone) = s.post(&format!("/v1/sessions/{}/step", ids[4]), &body);
    assert_eq!(code, 200, "{alone}");
    let pixels = |r: &Value| world::picture::decode_rgb(&B64.decode(r["image_png"].as_str().unwrap()).unwrap()).unwrap().0;
    let lone = pixels(&alone);
    for r in &frames {
        let worst = pixels(r).iter().zip(&lone).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst <= 1, "a batched frame differs from the lone one by {worst}/255");
    }
}

/// A geometry model with a fusion head serves its blend through the same
/// step: walking out with observing steps and back without them, the frames
/// it shows are closer to the world than those of the same model without the
/// head, and the step still reports the warp's cost.
#[test]
fn a_fusion_head_serves_frames_closer_to_the_world() {
    let walk = |name: &str| -> f64 {
        let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/variants").join(name);
        let s = Server::start(&temp_store(&format!("fusion-{name}")), &["--model", model.to_str().unwrap()]);
        let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 4 }, "policy": { "kind": "worldpack" } }));
        let id = c["session"].as_u64().unwrap();
        let step = |body: Value| {
            let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &body);
            assert_eq!(code, 200, "{name}: {r}");
            r
        };
        for _ in 0..4 {
            step(json!({ "action": { "forward": true }, "observe": true }));
        }
        let turn = step(json!({ "action": { "yaw_deg": 90 }, "observe": true }));
        assert!(turn["truth"].is_null());
        step(json!({ "action": { "yaw_deg": 90 }, "observe": true }));
        let back: Vec<Value> = (0..4).map(|k| step(json!({ "action": { "forward": true }, "seed": k }))).collect();
        for r in &back {
            assert!(r["timings_ms"]["warp"].as_f64().unwrap() > 0.0 && !r["selection"]["warp_frames"].as_array().unwrap().is_empty(), "{name}: {r}");
        }
        back.iter().map(|r| r["truth"]["psnr_db"].as_f64().unwrap()).sum::<f64>() / back.len() as f64
    };
    let (fused, alone) = (walk("worldpack_geometry_fused"), walk("worldpack_geometry"));
    eprintln!("the way back: {fused:.2} dB with the fusion head, {alone:.2} without");
    assert!(fused > alone, "mean PSNR on the way back: {fused:.2} dB with the head, {alone:.2} without");
}

/// How long a Triton host may take to load a model folder's graphs.
const TRITON_START: Duration = Duration::from_secs(240);

/// The Triton tests run one at a time: each host loads every graph in its
/// own Python and Triton processes, and several at once beside the other
/// servers starve a small CI machine.
fn triton_alone() -> std::sync::MutexGuard<'static, ()> {
    static ONE: Mutex<()> = Mutex::new(());
    ONE.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// `serving/triton/host.py`: a real Triton Inference Server (PyPI's
/// `tritonserver`, in `.venv-triton`, which scripts/test.sh makes) hosting a
/// model folder's graphs on free loopback ports; killed with its process
/// group on drop.
struct TritonHost {
    child: Child,
    ports: [u16; 3],
    _stdout: BufReader<std::process::ChildStdout>,
}

impl TritonHost {
    /// Starts it on `ports` (http, grpc, metrics) or on free ones. A start
    /// on free ports that fails (another process took one of them between
    /// the probe and Triton's bind) is tried once more on new ones.
    fn start(model: &str, ports: Option<[u16; 3]>) -> TritonHost {
        let free = || std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        match (TritonHost::try_start(model, ports.unwrap_or_else(|| [free(), free(), free()])), ports) {
            (Ok(host), _) => host,
            (Err(why), Some(_)) => panic!("{why}"),
            (Err(why), None) => {
                eprintln!("{why}; trying once more on other ports");
                TritonHost::try_start(model, [free(), free(), free()]).unwrap_or_else(|why| panic!("{why}"))
            }
        }
    }

    /// Waits at most [`TRITON_START`] for `serving/triton/host.py` to say it
    /// serves; otherwise kills it and returns why, with the end of its log.
    fn try_start(model: &str, [http, grpc, metrics]: [u16; 3]) -> Result<TritonHost, String> {
        use std::os::unix::process::CommandExt;
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let python = std::env::var_os("WORLDPACK_TRITON_PYTHON").map(PathBuf::from).unwrap_or(root.join(".venv-triton/bin/python"));
        assert!(python.exists(), "{} is missing: run ./scripts/test.sh once (it makes .venv-triton with PyPI's nvidia-pytriton)", python.display());
        let log = std::env::temp_dir().join(format!("worldpack-triton-{}-{http}.log", std::process::id()));
        let mut child = Command::new(python)
            .arg(root.join("serving/triton/host.py"))
            .arg("--model").arg(root.join(model))
            .args(["--http-port", &http.to_string(), "--grpc-port", &grpc.to_string(), "--metrics-port", &metrics.to_string()])
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .process_group(0)
            .spawn()
            .unwrap();
        // The first line that says "serving", read on a thread so that the wait has a deadline.
        let (said, heard) = std::sync::mpsc::channel();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        std::thread::spawn(move || {
            let mut line = String::new();
            while !line.starts_with("serving ") {
                line.clear();
                if stdout.read_line(&mut line).unwrap_or(0) == 0 {
                    return; // dropping `said` reports the exit
                }
            }
            let _ = said.send(stdout);
        });
        match heard.recv_timeout(TRITON_START) {
            Ok(stdout) => Ok(TritonHost { child, ports: [http, grpc, metrics], _stdout: stdout }),
            Err(waited) => {
                unsafe { libc_kill(-(child.id() as i32), 9) };
                let _ = child.wait();
                let text = std::fs::read_to_string(&log).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(15).collect::<Vec<_>>().into_iter().rev().collect();
                let how = match waited {
                    std::sync::mpsc::RecvTimeoutError::Timeout => format!("did not serve within {TRITON_START:?}"),
                    std::sync::mpsc::RecvTimeoutError::Disconnected => "exited before serving".into(),
                };
                Err(format!("serving/triton/host.py on ports {http}/{grpc}/{metrics} {how}; the end of its log ({}):\n{}", log.display(), tail.join("\n")))
            }
        }
    }

    /// The `--model-backend` URL.
    fn backend(&self) -> String {
        format!("triton://127.0.0.1:{}", self.ports[0])
    }

    /// A counter from Triton's Prometheus metrics for one model.
    fn metric(&self, name: &str, model: &str) -> f64 {
        let text = HTTP.get(&format!("http://127.0.0.1:{}/metrics", self.ports[2])).call().unwrap().into_string().unwrap();
        let prefix = format!("{name}{{model=\"{model}\",");
        text.lines().find(|l| l.starts_with(&prefix)).and_then(|l| l.rsplit(' ').next()).and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no {prefix} in Triton's metrics"))
    }

    fn stop(&mut self) {
        unsafe { libc_kill(-(self.child.id() as i32), 9) }; // the whole group: python and tritonserver
        let _ = self.child.wait();
    }
}

impl Drop for TritonHost {
    fn drop(&mut self) {
        self.stop();
    }
}


/// The graphs on Triton compute what they compute in this process (float
/// tolerance), and a served session makes the same frames, byte for byte,
/// with the same seeds.
#[test]
fn triton_runs_the_graphs_as_the_local_backend_does() {
    let _alone = triton_alone();
    let triton = TritonHost::start("fixtures/small", None);
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let local = model::Model::load(&dir, model::RuntimeOptions::default()).unwrap();
    let manifest = local.manifest().clone();
    let remote = model::Model::with_backend(&dir, manifest.clone(), Box::new(triton::TritonBackend::connect(&triton.backend(), &manifest).unwrap()));
    assert_eq!(remote.provider(), "triton");
    // Every graph on a batch of 3 pseudo-random inputs of its declared shapes.
    let mut state = 7u64;
    let mut noise = move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    let mut graphs = vec![(model::GraphRole::Encoder, manifest.autoencoder.encoder.clone()), (model::GraphRole::Decoder, manifest.autoencoder.decoder.clone())];
    graphs.extend(manifest.denoiser.layouts.iter().map(|l| (model::GraphRole::Denoiser(&l.name), l.graph())));
    for (role, spec) in graphs {
        let inputs: Vec<(String, model::Tensor)> = spec
            .inputs
            .iter()
            .map(|t| {
                let shape: Vec<usize> = t.dims().iter().map(|&d| if d < 0 { 3 } else { d as usize }).collect();
                let mut data: Vec<f32> = (0..shape.iter().product()).map(|_| noise()).collect();
                if t.name.starts_with("context_mask") {
                    data.iter_mut().for_each(|v| *v = 1.0);
                } else if t.name == "timestep" || t.name == "rel_time" {
                    data.iter_mut().for_each(|v| *v = (v.abs() * 10.0).round().max(1.0));
                }
                (t.name.clone(), model::Tensor::new(shape, data))
            })
            .collect();
        let named: Vec<(&str, &model::Tensor)> = inputs.iter().map(|(n, t)| (n.as_str(), t)).collect();
        let (want, got) = (local.run(role, &named).unwrap(), remote.run(role, &named).unwrap());
        for (w, g) in want.iter().zip(&got) {
            assert_eq!(w.shape, g.shape, "{role:?}");
            let worst = w.data.iter().zip(&g.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
            assert!(worst <= 1e-5, "{role:?}: Triton differs from the local backend by {worst}");
        }
    }
    // The same session served both ways.
    let frames = |extra: &[&str]| -> Vec<Vec<u8>> {
        let s = Server::start(&temp_store(&format!("triton-parity{}", extra.len())), extra);
        let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 5 } }));
        let id = c["session"].as_u64().unwrap();
        (1..=3u64)
            .map(|k| {
                let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true, "yaw_deg": 6 }, "seed": k }));
                assert_eq!(code, 200, "{r}");
                s.bytes(&format!("/v1/sessions/{id}/frames/{k}/image"))
            })
            .collect()
    };
    assert_eq!(frames(&[]), frames(&["--model-backend", &triton.backend()]), "frames served through Triton differ");
}

/// Triton stopped under a running server: steps answer 503 naming triton,
/// no frame is stored for them, and service resumes when Triton is back on
/// the same port.
#[test]
fn a_stopped_triton_answers_503_and_service_resumes() {
    let _alone = triton_alone();
    let mut triton = TritonHost::start("fixtures/small", None);
    let s = Server::start(&temp_store("triton-fault"), &["--model-backend", &triton.backend()]);
    let (_, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    let id = c["session"].as_u64().unwrap();
    let step = || s.post(&format!("/v1/sessions/{id}/step"), &json!({ "action": { "forward": true } }));
    assert_eq!(step().0, 200);
    triton.stop();
    let (code, r) = step();
    assert_eq!((code, r["error"]["field"].as_str()), (503, Some("triton")), "{r}");
    assert_eq!(s.get(&format!("/v1/sessions/{id}")).1["frames"].as_u64(), Some(2), "the refused step stored nothing");
    let _back = TritonHost::start("fixtures/small", Some(triton.ports));
    let (code, r) = step();
    assert_eq!((code, r["index"].as_u64()), (200, Some(2)), "{r}");
}

/// A Triton URL that is malformed or serves no such model stops the server
/// at start with a message naming the flag.
#[test]
fn a_bad_model_backend_is_refused_at_start() {
    for (backend, says) in [("grpc://127.0.0.1:1", "triton://HOST:PORT"), ("triton://127.0.0.1:1", "triton is unavailable")] {
        let out = Command::new(env!("CARGO_BIN_EXE_worldpack"))
            .args(["serve", "--addr", "127.0.0.1:0", "--store", temp_store("bad-backend").to_str().unwrap(), "--model-backend", backend])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && stderr.contains("--model-backend") && stderr.contains(says), "{backend}: {stderr}");
    }
}
