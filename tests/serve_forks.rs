//! Forks over HTTP (docs/api.md#forks): a fork shares its parent's frames in
//! memory and in the store, steps apart from it, forks again, survives a
//! restart on redb and PostgreSQL, keeps its parent from being deleted or
//! expired, and is served by a replica that did not make it.

mod support;

use std::path::Path;
use std::time::Duration;

use serde_json::{Value, json};
use support::*;

fn delete(s: &Server, id: u64) -> (u16, Value) {
    answer(HTTP.delete(&format!("{}/v1/sessions/{id}", s.url)).call())
}

fn step(s: &Server, id: u64, body: Value) -> Value {
    let (code, r) = s.post(&format!("/v1/sessions/{id}/step"), &body);
    assert_eq!(code, 200, "step of {id}: {r}");
    r
}

fn fork(s: &Server, id: u64) -> Value {
    let (code, r) = s.post(&format!("/v1/sessions/{id}/fork"), &json!({}));
    assert_eq!(code, 201, "fork of {id}: {r}");
    r
}

fn frames(s: &Server, id: u64) -> u64 {
    let (code, r) = s.get(&format!("/v1/sessions/{id}"));
    assert_eq!(code, 200, "{r}");
    r["frames"].as_u64().unwrap()
}

fn image(s: &Server, id: u64, index: u64) -> Vec<u8> {
    s.bytes(&format!("/v1/sessions/{id}/frames/{index}/image"))
}

#[test]
fn forks_share_step_apart_and_survive_a_restart_on_redb() {
    let store = temp_store("forks");
    forks_share_step_apart_and_survive_a_restart(&store);
    let _ = std::fs::remove_dir_all(store.parent().unwrap());
}

#[test]
fn forks_share_step_apart_and_survive_a_restart_on_postgres() {
    let pg = PgCluster::start("forks");
    forks_share_step_apart_and_survive_a_restart(&pg.url());
}

fn forks_share_step_apart_and_survive_a_restart(store: &Path) {
    let s = Server::start(store, &[]);
    let (code, c) = s.post("/v1/sessions", &json!({ "synthetic": { "seed": 3 } }));
    assert_eq!(code, 201, "{c}");
    let parent = c["session"].as_u64().unwrap();
    for seed in 0..3 {
        step(&s, parent, json!({ "action": { "forward": true }, "seed": seed }));
    }
    let f = fork(&s, parent);
    assert_eq!((f["parent"].as_u64(), f["frames"].as_u64()), (Some(parent), Some(4)), "{f}");
    let child = f["session"].as_u64().unwrap();
    let (_, info) = s.get(&format!("/v1/sessions/{child}"));
    assert_eq!((info["parent"].as_u64(), info["forked_at"].as_u64(), info["frames"].as_u64()), (Some(parent), Some(4), Some(4)), "{info}");

    // The same step from both gives the same frame from the same memories: the fork's memory is the parent's.
    let same = json!({ "action": { "forward": true, "yaw_deg": 10 }, "seed": 9 });
    let (a, b) = (step(&s, parent, same.clone()), step(&s, child, same));
    assert_eq!((a["index"].as_u64(), b["index"].as_u64()), (Some(4), Some(4)));
    assert_eq!(a["selection"]["plan"], b["selection"]["plan"]);
    assert_eq!(a["image_png"], b["image_png"], "a fork steps as its parent would");
    // Then they part: the fork's steps are its own, and never the parent's.
    let own = step(&s, child, json!({ "action": { "left": true, "yaw_deg": -30 }, "seed": 1 }));
    assert_eq!(own["index"].as_u64(), Some(5));
    assert_eq!((frames(&s, parent), frames(&s, child)), (5, 6));
    assert_eq!(s.get(&format!("/v1/sessions/{parent}/frames/5")).0, 404, "the fork's step is not the parent's");
    for i in 0..4 {
        assert_eq!(image(&s, child, i), image(&s, parent, i), "shared frame {i}");
    }
    // A fork of the fork, stepped once.
    let g = fork(&s, child);
    assert_eq!(g["frames"].as_u64(), Some(6));
    let grandchild = g["session"].as_u64().unwrap();
    assert_eq!(step(&s, grandchild, json!({ "action": { "back": true } }))["index"].as_u64(), Some(6));
    assert_eq!(frames(&s, child), 6, "the grandchild's step is not the fork's");
    s.kill();

    // In the store each frame is stored once, under the session that made it.
    {
        let st = api::store::Store::open(store).unwrap();
        let own: Vec<usize> = [parent, child, grandchild].iter().map(|&id| st.frames_from(id, 0).unwrap().len()).collect();
        assert_eq!(own, [5, 2, 1], "rows stored under parent, fork, fork of the fork: no frame copied");
        let (read, theirs) = (st.frames(grandchild).unwrap(), st.frames(parent).unwrap());
        assert_eq!(read.len(), 7);
        assert_eq!(read[..4], theirs[..4], "the fork of the fork reads the parent's frames");
        assert_eq!(st.frames(child).unwrap()[..6], read[..6]);
    }

    // After a restart each session has its history, and steps on from it.
    let s = Server::start(store, &[]);
    assert_eq!((frames(&s, parent), frames(&s, child), frames(&s, grandchild)), (5, 6, 7));
    assert_eq!(image(&s, grandchild, 2), image(&s, parent, 2));
    assert_eq!(image(&s, grandchild, 5), image(&s, child, 5));
    assert_eq!(step(&s, grandchild, json!({ "action": { "forward": true } }))["index"].as_u64(), Some(7));
    assert_eq!(step(&s, child, json!({ "action": { "forward": true } }))["index"].as_u64(), Some(6));
    assert_eq!(step(&s, parent, json!({ "action": { "forward": true } }))["index"].as_u64(), Some(5));

    // A session is not deleted while forks of it live; its forks are.
    let (code, r) = delete(&s, parent);
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("session")), "{r}");
    assert!(r["error"]["message"].as_str().unwrap().contains(&child.to_string()), "the refusal names the fork: {r}");
    assert_eq!(delete(&s, child).0, 409, "the fork has a fork of its own");
    assert_eq!(frames(&s, parent), 6, "a refused delete leaves the session whole");
    for id in [grandchild, child, parent] {
        assert_eq!(delete(&s, id).0, 204, "session {id}");
    }
    s.kill();
    let s = Server::start(store, &[]);
    for id in [parent, child, grandchild] {
        assert_eq!(s.get(&format!("/v1/sessions/{id}")).0, 404, "session {id} stays deleted");
    }
}

/// A fork made on one replica is served by the other, which reads the frames
/// it shares from the database once; each replica sees the other's steps.
#[test]
fn a_fork_made_on_one_replica_steps_on_the_other() {
    let pg = PgCluster::start("fork-replicas");
    let (a, b) = (Server::start(&pg.url(), &[]), Server::start(&pg.url(), &[]));
    let (_, c) = a.post("/v1/sessions", &json!({ "synthetic": { "seed": 5 } }));
    let parent = c["session"].as_u64().unwrap();
    step(&a, parent, json!({ "action": { "forward": true } }));
    let child = fork(&a, parent)["session"].as_u64().unwrap();
    let same = json!({ "action": { "yaw_deg": 20 }, "seed": 4 });
    let on_b = step(&b, child, same.clone());
    let on_a = step(&a, parent, same);
    assert_eq!((on_b["index"].as_u64(), on_b["image_png"].clone()), (Some(2), on_a["image_png"].clone()), "replica b steps the fork from the parent's frames");
    assert_eq!(frames(&a, child), 3, "replica a sees the step b made");
    assert_eq!(image(&a, child, 1), image(&b, parent, 1));
    let (code, r) = delete(&b, parent);
    assert_eq!((code, r["error"]["field"].as_str()), (409, Some("session")), "the database refuses it on any replica: {r}");
}

/// Retention never expires a session whose forks live; once they are gone
/// it expires like any other.
#[test]
fn retention_keeps_a_parent_while_its_forks_live() {
    let s = Server::start(&temp_store("fork-retention"), &["--memory-only", "--retain-idle-secs", "1"]);
    let png = png_8x8();
    let (code, c) = s.post("/v1/sessions", &json!({ "frames": [{ "image_png": png, "pose": c2w([0.0; 3]) }], "intrinsics": { "hfov_deg": 70, "width": 8, "height": 8 } }));
    assert_eq!(code, 201, "{c}");
    let parent = c["session"].as_u64().unwrap();
    let child = fork(&s, parent)["session"].as_u64().unwrap();
    // The fork is kept busy for well past the idle time; the parent, idle all along, stays.
    for k in 1..=12 {
        let (code, r) = s.post(&format!("/v1/sessions/{child}/observe"), &json!({ "image_png": png, "pose": c2w([k as f64, 0.0, 0.0]) }));
        assert_eq!(code, 200, "{r}");
        std::thread::sleep(Duration::from_millis(250));
    }
    assert_eq!(s.get(&format!("/v1/sessions/{parent}")).0, 200, "an idle parent with a live fork is kept");
    // Left alone, the fork expires, and then the parent.
    let start = std::time::Instant::now();
    while s.get(&format!("/v1/sessions/{parent}")).0 != 404 {
        assert!(start.elapsed() < Duration::from_secs(20), "the parent was never expired");
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(s.get(&format!("/v1/sessions/{child}")).0, 404, "the fork went first");
}

fn png_8x8() -> String {
    use base64::Engine;
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, 8, 8);
    encoder.set_color(png::ColorType::Rgb);
    encoder.write_header().unwrap().write_image_data(&[90; 8 * 8 * 3]).unwrap();
    base64::engine::general_purpose::STANDARD.encode(bytes)
}
