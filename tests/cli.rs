//! End-to-end checks of the `worldpack` binary.

use std::io::Write;
use std::process::{Command, Stdio};

fn worldpack(args: &[&str], stdin: &str) -> (i32, String, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_worldpack"))
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("worldpack starts");
    child.stdin.take().unwrap().write_all(stdin.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    (out.status.code().unwrap_or(-1), String::from_utf8(out.stdout).unwrap(), String::from_utf8(out.stderr).unwrap())
}

/// Parses the demo table into (policy, view covered %).
fn coverage(table: &str) -> Vec<(String, f64)> {
    table
        .lines()
        .filter_map(|l| {
            let cols: Vec<&str> = l.split_whitespace().collect();
            let pct = cols.get(1)?.strip_suffix('%')?.parse().ok()?;
            Some((cols[0].to_string(), pct))
        })
        .collect()
}

#[test]
fn demo_shows_worldpack_covering_more_of_the_next_view_than_the_baseline() {
    let (code, out, err) = worldpack(&["demo", "--range", "15"], "");
    assert_eq!(code, 0, "{err}");
    let rows = coverage(&out);
    let get = |name: &str| rows.iter().find(|(p, _)| p == name).map(|r| r.1).unwrap_or_else(|| panic!("{name} in {out}"));
    assert_eq!(rows.len(), 5, "{out}");
    assert!(get("WorldPack") > get("Baseline") + 3.0, "{out}");
    assert!(get("WorldPack") >= get("MemoryRetrieval"), "{out}");
}

#[test]
fn demo_refuses_a_zero_range() {
    let (code, _, err) = worldpack(&["demo", "--range", "0"], "");
    assert_eq!(code, 2);
    assert!(err.contains("--range"), "{err}");
}

#[test]
fn geometry_answers_a_select_request_with_token_counts() {
    let request = r#"{"op": "select", "policy": {"kind": "worldpack", "query": "target"}, "latent": {"height": 28, "width": 28, "patch": 2},
        "target": {"pose": {"pose5": {"x": 0, "y": 64, "z": 0, "pitch": 0, "yaw": 0, "convention": "minecraft", "unit": "degrees"}},
                   "intrinsics": {"hfov_deg": 90, "width": 64, "height": 64}},
        "frames": [
          {"id": 1, "time": 0, "pose": {"pose5": {"x": 0, "y": 64, "z": 0, "pitch": 0, "yaw": 0, "convention": "minecraft", "unit": "degrees"}},
           "intrinsics": {"hfov_deg": 90, "width": 64, "height": 64}},
          {"id": 2, "time": 1, "pose": {"pose5": {"x": 0, "y": 64, "z": 0, "pitch": 0, "yaw": 180, "convention": "minecraft", "unit": "degrees"}},
           "intrinsics": {"hfov_deg": 90, "width": 64, "height": 64}}]}"#;
    let (code, out, err) = worldpack(&["geometry"], request);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["plan"]["slots"][0]["frame"]["id"], 1);
    assert_eq!(v["plan"]["slots"][0]["frame"]["overlap"], 1.0);
    assert_eq!(v["plan"]["slots"][1]["frame"]["overlap"], 0.0);
    assert_eq!(v["tokens"]["used"], 392);
    assert_eq!(v["tokens"]["capacity"], 844);
    // Algorithm 1 (the preset) scores against the newest frame's view instead: that frame leads.
    let (code, out, err) = worldpack(&["geometry"], &request.replace(r#", "query": "target""#, ""));
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["plan"]["slots"][0]["frame"]["id"], 2);
    assert_eq!(v["plan"]["slots"][0]["frame"]["overlap"], 1.0);
}

/// Three frames facing a plane 9.5 units ahead of the target: the newest just
/// behind the target, A a step further back with a wall right in front of its
/// lens, B six units back with a clear view. Frustum overlap ranks A second;
/// with their depth, co-visibility knows A saw nothing of the plane.
#[test]
fn geometry_selects_by_co_visibility_from_depth() {
    let frame = |id: u32, z: f64, depth: f64| {
        let depth = vec![depth.to_string(); 16 * 12].join(",");
        format!(
            r#"{{"id": {id}, "time": {id}, "pose": {{"c2w": {{"rotation": [[1,0,0],[0,1,0],[0,0,1]], "position": [0, 0, {z}]}}}},
               "intrinsics": {{"hfov_deg": 60, "width": 16, "height": 12}}, "depth": [{depth}]}}"#
        )
    };
    let frames = [frame(3, -0.5, 10.0), frame(2, -1.0, 0.5), frame(1, -6.0, 15.5)].join(",");
    let request = |extra: &str| {
        format!(
            r#"{{"op": "select", "policy": {{"kind": "worldpack"}}{extra},
                "target": {{"pose": {{"c2w": {{"rotation": [[1,0,0],[0,1,0],[0,0,1]], "position": [0, 0, 0]}}}}, "intrinsics": {{"hfov_deg": 60, "width": 16, "height": 12}}}},
                "frames": [{frames}]}}"#
        )
    };
    let order = |v: &serde_json::Value| -> Vec<u64> { v["plan"]["slots"].as_array().unwrap().iter().filter_map(|s| s["frame"]["id"].as_u64()).collect() };
    let (code, out, err) = worldpack(&["geometry"], &request(""));
    assert_eq!(code, 0, "{err}");
    assert_eq!(order(&serde_json::from_str(&out).unwrap()), [3, 2, 1], "by frustum overlap and recency");
    let (code, out, err) = worldpack(&["geometry"], &request(r#", "covisibility": {"candidates": 8, "sources": 2, "cells": 8, "tolerance": 0.1}"#));
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(order(&v), [3, 1, 2], "{v}");
    assert_eq!(v["covisibility"]["with_depth"], 3, "{v}");
    assert_eq!(v["plan"]["slots"][2]["frame"]["overlap"], 0.0, "the wall hid the whole plane from frame 2: {v}");
    // A depth map of the wrong size is named.
    let bad = request(r#", "covisibility": {"candidates": 8, "sources": 2, "cells": 8, "tolerance": 0.1}"#).replacen("[10,", "[", 1);
    let (code, out, _) = worldpack(&["geometry"], &bad);
    assert_eq!(code, 2);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["error"]["field"], "frames[0].depth", "{v}");
}

#[test]
fn geometry_rejects_duplicate_frame_ids_by_field() {
    let frame = r#"{"id": 4, "time": 0, "pose": {"opencv": {"rvec": [0,0,0], "tvec": [0,0,0]}}, "intrinsics": {"fx": 30, "width": 64, "height": 64}}"#;
    let request = format!(
        r#"{{"op": "select", "policy": {{"kind": "baseline"}}, "target": {{"pose": {{"opencv": {{"rvec": [0,0,0], "tvec": [0,0,0]}}}}, "intrinsics": {{"fx": 30, "width": 64, "height": 64}}}}, "frames": [{frame}, {frame}]}}"#
    );
    let (code, out, _) = worldpack(&["geometry"], &request);
    assert_eq!(code, 2);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["error"]["field"], "frames[1].id");
}

#[test]
fn bench_step_compares_the_two_contexts() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/small");
    let (code, stdout, stderr) = worldpack(&["bench", "step", "--model", fixture, "--calls", "2", "--steps", "1,2", "--batches", "1,3", "--json"], "");
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(r["provider"], "cpu");
    assert_eq!((r["baseline"]["frames"].as_u64(), r["worldpack"]["frames"].as_u64()), (Some(4), Some(22)));
    assert_eq!(r["baseline"]["context_tokens"], r["worldpack"]["context_tokens"], "the same token budget");
    for key in ["time_ratio", "peak_ratio"] {
        assert!(r[key].as_f64().unwrap() > 0.0, "{key}");
    }
    // The per-call memory is reported exactly when the high-water-mark reset took.
    for layout in ["baseline", "worldpack"] {
        let row = &r[layout];
        let reset = row["hwm_reset"].as_bool().unwrap();
        assert_eq!(row["call_memory_mib"].as_f64().is_some_and(|m| m > 0.0), reset, "{row}");
    }
    assert_eq!(r["call_memory_ratio"].is_null(), !(r["baseline"]["hwm_reset"] == true && r["worldpack"]["hwm_reset"] == true));
    let rows = r["next_frame"].as_array().unwrap();
    assert_eq!(rows.iter().map(|s| s["steps"].as_u64().unwrap()).collect::<Vec<_>>(), [1, 2]);
    let batching = r["batching"].as_array().unwrap();
    assert_eq!(batching.iter().map(|b| b["batch"].as_u64().unwrap()).collect::<Vec<_>>(), [1, 3]);
    assert!(batching.iter().all(|b| b["baseline_ms_per_item"].as_f64().unwrap() > 0.0 && b["worldpack_ms_per_item"].as_f64().unwrap() > 0.0));
}

#[test]
fn bench_step_bad_input_names_the_flag() {
    let (code, _, stderr) = worldpack(&["bench", "step", "--model", "/nonexistent/model"], "");
    assert_eq!(code, 2);
    assert!(stderr.contains("/nonexistent/model") && stderr.contains("manifest.json"), "{stderr}");
    let (code, _, stderr) = worldpack(&["bench", "step", "--provider", "gpu"], "");
    assert_eq!(code, 2);
    assert!(stderr.contains("--provider") && stderr.contains("cpu, cuda, auto"), "{stderr}");
    let (code, _, stderr) = worldpack(&["bench", "step", "--steps", "0"], "");
    assert_eq!(code, 2);
    assert!(stderr.contains("--steps"), "{stderr}");
}

#[test]
fn bench_serve_compares_http_with_the_library_call() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/small");
    let args = ["bench", "serve", "--model", fixture, "--steps", "1", "--calls", "2", "--sessions", "1,3", "--per-session", "2", "--batch-window-ms", "5", "--json"];
    let (code, stdout, stderr) = worldpack(&args, "");
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert!(r["http_over_library"].as_f64().unwrap() > 0.0);
    let rows = r["concurrency"].as_array().unwrap();
    let shape: Vec<(u64, u64, u64)> =
        rows.iter().map(|x| (x["batch_window_ms"].as_u64().unwrap(), x["sessions"].as_u64().unwrap(), x["steps"].as_u64().unwrap())).collect();
    assert_eq!(shape, [(0, 1, 2), (0, 3, 6), (5, 1, 2), (5, 3, 6)], "each row without batching, then with");
    let (code, _, stderr) = worldpack(&["bench", "serve", "--sessions", "0"], "");
    assert_eq!(code, 2);
    assert!(stderr.contains("--sessions"), "{stderr}");
}

#[test]
fn bench_parity_of_the_cpu_provider_with_itself_is_exact() {
    // The same walk twice through the CPU provider: every latent and picture must
    // agree to the bit, or a provider's drift could not be told from the walk's own.
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/variants/worldpack_geometry_fused_1step");
    let args = ["bench", "parity", "--model", fixture, "--provider", "cpu", "--explore", "6", "--back", "2", "--json"];
    let (code, stdout, stderr) = worldpack(&args, "");
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let frames = r["frames"].as_array().unwrap();
    let generated: Vec<&serde_json::Value> = frames.iter().filter(|f| f["generated"] == true).collect();
    assert_eq!((frames.len(), generated.len()), (6 + 18 + 2, 18 + 2), "observed, then the turn and the way back generated");
    assert!(frames.iter().all(|f| f["latent_max_abs"] == 0.0 && f["frame_max_abs"] == 0), "{stdout}");
    assert_eq!(r["decoder_max_abs"], 0.0);
    assert!(generated.iter().all(|f| f["truth_psnr_db_cpu"].as_f64().unwrap() > 5.0 && f["truth_psnr_db_cpu"] == f["truth_psnr_db_other"]));
    let (code, _, stderr) = worldpack(&["bench", "parity", "--provider", "tpu"], "");
    assert_eq!(code, 2);
    assert!(stderr.contains("--provider"), "{stderr}");
}

#[test]
fn bench_store_writes_and_reads_back_both_databases() {
    let (code, stdout, stderr) = worldpack(&["bench", "store", "--frames", "5", "--json"], "");
    assert_eq!(code, 0, "{stderr}");
    let rows: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let names: Vec<&str> = rows.as_array().unwrap().iter().map(|r| r["store"].as_str().unwrap()).collect();
    assert!(names[0].starts_with("redb") && names[1].starts_with("SQLite"), "{names:?}");
    for r in rows.as_array().unwrap() {
        assert_eq!(r["frames"], 5);
        assert!(r["bytes_per_frame"].as_u64().unwrap() > 4096, "a latent alone is 4 KiB");
    }
}

#[test]
fn the_where_to_add_table_names_real_files() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let doc = std::fs::read_to_string(root.join("docs/architecture.md")).unwrap();
    let table = doc.split("## Where to add things").nth(1).expect("the section exists").split("\n## ").next().unwrap();
    let paths: Vec<&str> = table.split('`').skip(1).step_by(2).filter(|t| t.contains('/') && t.contains('.') && !t.contains(' ')).collect();
    assert!(paths.len() >= 12, "the table names files: {paths:?}");
    for p in paths {
        assert!(root.join(p).exists(), "docs/architecture.md names {p}, which does not exist");
    }
}
