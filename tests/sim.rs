//! End-to-end checks of `worldpack sim`: the suite's files, determinism, the
//! LoopNav property that return legs revisit the exploration, and bad input.

use std::path::{Path, PathBuf};
use std::process::Command;

use memory::overlap::exact_overlap;
use memory::{Frustum, Intrinsics, Pose};

fn worldpack(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack")).args(args).output().expect("worldpack starts");
    (out.status.code().unwrap_or(-1), String::from_utf8(out.stdout).unwrap(), String::from_utf8(out.stderr).unwrap())
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("worldpack-sim-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Every regular file under `dir`, relative path → bytes.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// Camera-to-world poses from a trajectory's `poses.npy`.
fn poses(dir: &Path) -> Vec<Pose> {
    let (shape, data) = world::npy::read::<f64>(&dir.join("poses.npy")).unwrap();
    assert_eq!(&shape[1..], &[4, 4]);
    data.chunks_exact(16)
        .map(|m| Pose::from_matrix_rows([0, 1, 2, 3].map(|i| [m[4 * i], m[4 * i + 1], m[4 * i + 2], m[4 * i + 3]])).unwrap())
        .collect()
}

#[test]
fn loopnav_suite_return_legs_revisit_the_exploration() {
    let out = temp_dir("suite");
    let (code, stdout, stderr) = worldpack(&["sim", "loopnav", "--per-cell", "2", "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("wrote 16 trajectories"), "{stdout}");
    let index = json(&out.join("index.json"));
    let entries = index["trajectories"].as_array().unwrap();
    assert_eq!(entries.len(), 16);
    assert_eq!(index["split"], "test");
    for e in entries {
        let dir = out.join(e["dir"].as_str().unwrap());
        let meta = json(&dir.join("meta.json"));
        let k: Intrinsics = serde_json::from_value(meta["intrinsics"].clone()).unwrap();
        let (n, r) = (meta["frames"].as_u64().unwrap() as usize, meta["returning_point"].as_u64().unwrap() as usize);
        let (rgb_shape, _) = world::npy::read::<u8>(&dir.join("rgb.npy")).unwrap();
        assert_eq!(rgb_shape, vec![n, 64, 64, 3]);
        let (phase_shape, phase) = world::npy::read::<u8>(&dir.join("phase.npy")).unwrap();
        assert_eq!(phase_shape, vec![n]);
        assert!(phase[..r].iter().all(|&p| p < 2) && phase[r..].iter().all(|&p| p == 2));
        // Every frame of the way back should find a stored frame that sees
        // much of the same space; the last one is back at A, where the
        // agent looked all around.
        let ps = poses(&dir);
        assert_eq!(ps.len(), n);
        let frusta: Vec<Frustum> = ps.iter().map(|p| Frustum::new(*p, k).unwrap()).collect();
        let best: Vec<f64> = (r..n)
            .map(|t| frusta[..r].iter().map(|f| exact_overlap(&frusta[t], f)).fold(0.0, f64::max))
            .collect();
        let mean = best.iter().sum::<f64>() / best.len() as f64;
        let last = *best.last().unwrap();
        let name = e["dir"].as_str().unwrap();
        eprintln!("{name}: {n} frames, returning point {r}, best overlap on the way back: mean {mean:.3}, last {last:.3}");
        // Measured over this suite: means 0.42–0.84, last frames 0.84–0.995.
        assert!(mean > 0.35, "{name}: mean best overlap on the return leg {mean:.3}");
        assert!(last > 0.8, "{name}: the final frame's best overlap is {last:.3}");
    }
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn same_seed_same_bytes_other_seed_other_bytes() {
    let run = |seed: &str, name: &str| {
        let out = temp_dir(name);
        let args = ["sim", "loopnav", "--per-cell", "1", "--ranges", "5,15", "--seed", seed, "--out", out.to_str().unwrap()];
        let (code, _, stderr) = worldpack(&args);
        assert_eq!(code, 0, "{stderr}");
        let f = files(&out);
        std::fs::remove_dir_all(&out).unwrap();
        f
    };
    let (a, b, c) = (run("7", "det-a"), run("7", "det-b"), run("8", "det-c"));
    assert_eq!(a.len(), 4 * 8 + 1, "4 trajectories of 8 files and index.json");
    assert!(a == b, "two runs with seed 7 wrote different bytes");
    let rgb = |f: &[(PathBuf, Vec<u8>)]| f.iter().find(|(p, _)| p.ends_with("rgb.npy")).unwrap().1.clone();
    assert_ne!(rgb(&a), rgb(&c));
}

#[test]
fn training_and_test_worlds_are_disjoint() {
    let out = temp_dir("dataset");
    let (code, stdout, stderr) = worldpack(&["sim", "dataset", "--trajectories", "6", "--size", "16x16", "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("wrote 6 trajectories"), "{stdout}");
    let index = json(&out.join("index.json"));
    assert_eq!(index["split"], "train");
    for e in index["trajectories"].as_array().unwrap() {
        let meta = json(&out.join(e["dir"].as_str().unwrap()).join("meta.json"));
        assert!(meta["world_seed"].as_u64().unwrap() >> 63 == 0, "training world seed in the test half");
        assert_eq!(meta["split"], "train");
    }
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn bad_sim_input_names_the_flag() {
    let out = temp_dir("bad");
    let o = out.to_str().unwrap();
    for (args, needle) in [
        (vec!["sim", "loopnav", "--out", o, "--size", "3x64"], "--size"),
        (vec!["sim", "loopnav", "--out", o, "--ranges", "0"], "--ranges"),
        (vec!["sim", "loopnav", "--out", o, "--tasks", "abc"], "--tasks"),
        (vec!["sim", "render", "--out", o, "--pose", "1,2,3"], "--pose"),
        (vec!["sim", "render", "--out", o, "--pose", "1,2,3,nan,0"], "--pose"),
        (vec!["sim", "render", "--out", o, "--pose", "1e300,2,3,0,0"], "--pose"),
        (vec!["sim", "render", "--out", o, "--probe", "64,0"], "--probe"),
        (vec!["sim", "render", "--out", o, "--biome", "jungle"], "--biome"),
    ] {
        let (code, _, stderr) = worldpack(&args);
        assert_eq!(code, 2, "{args:?}: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: error does not name {needle}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn plan_files_are_the_memory_crate_selection() {
    let out = temp_dir("plan");
    let dir = out.to_str().unwrap();
    let (code, _, stderr) = worldpack(&["sim", "loopnav", "--per-cell", "1", "--ranges", "5", "--tasks", "aba", "--out", dir]);
    assert_eq!(code, 0, "{stderr}");
    let (code, stdout, stderr) = worldpack(&["plan", "--data", dir, "--policies", "baseline,worldpack"]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("wrote plans for 1 trajectories"), "{stdout}");
    let described = json(&out.join("plans.json"));
    let rates: Vec<u64> = described["policies"][1]["rates"].as_array().unwrap().iter().map(|r| r.as_u64().unwrap()).collect();
    assert_eq!(rates, [vec![1; 2], vec![4; 4], vec![16; 16]].concat());

    let traj = out.join(json(&out.join("index.json"))["trajectories"][0]["dir"].as_str().unwrap());
    let k: Intrinsics = serde_json::from_value(json(&traj.join("meta.json"))["intrinsics"].clone()).unwrap();
    let frames: Vec<memory::MemoryFrame> = poses(&traj)
        .into_iter()
        .enumerate()
        .map(|(t, p)| memory::MemoryFrame { id: t as u64, time: t as u64, frustum: Frustum::new(p, k).unwrap() })
        .collect();
    let (shape, baseline) = world::npy::read::<i32>(&traj.join("plan-baseline.npy")).unwrap();
    assert_eq!(shape, [frames.len(), 4]);
    for t in 0..frames.len() {
        let want: Vec<i32> = (1..=4).map(|d| if d <= t { (t - d) as i32 } else { -1 }).collect();
        assert_eq!(&baseline[t * 4..t * 4 + 4], &want[..], "baseline row {t}");
    }
    // The written plans are the brute-force selection over every earlier frame.
    let (shape, packed) = world::npy::read::<i32>(&traj.join("plan-worldpack.npy")).unwrap();
    assert_eq!(shape, [frames.len(), 22]);
    assert!(packed[..22].iter().all(|&i| i == -1), "frame 0 has no context");
    let policy = memory::Policy::preset(memory::PolicyKind::WorldPack);
    for t in (1..frames.len()).step_by(7) {
        let plan = memory::select_by_brute_force(&policy, &frames[t].frustum, &frames[..t]);
        let want: Vec<i32> = plan.slots.iter().map(|s| s.frame.map_or(-1, |f| f.id as i32)).collect();
        assert_eq!(&packed[t * 22..(t + 1) * 22], &want[..], "worldpack row {t}");
    }

    // The memory need: only written when asked, one share per frame, close to
    // the full-resolution share the probe's strata use.
    assert!(!traj.join("memory-need.npy").exists());
    let (code, _, stderr) = worldpack(&["plan", "--data", dir, "--policies", "baseline", "--memory-need"]);
    assert_eq!(code, 0, "{stderr}");
    let (shape, need) = world::npy::read::<f32>(&traj.join("memory-need.npy")).unwrap();
    assert_eq!(shape, [frames.len()]);
    assert_eq!(need[0], 0.0, "frame 0 has no memory");
    assert!(need.iter().all(|n| (0.0..=1.0).contains(n)), "shares: {need:?}");
    let loaded = &eval::suite::load(&out, None).unwrap()[0];
    let every_5th: Vec<usize> = (1..frames.len()).step_by(5).collect();
    let full = eval::strata::features(loaded, &every_5th).unwrap();
    let gap = full.iter().map(|f| (f.memory_only - need[f.t] as f64).abs()).sum::<f64>() / full.len() as f64;
    assert!(gap < 0.03, "mean gap to the full-resolution share: {gap}");
    assert!(full.iter().any(|f| f.memory_only >= 0.1), "some frames need memory");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bad_plan_input_names_the_flag() {
    let (code, _, stderr) = worldpack(&["plan", "--data", "/nonexistent/suite"]);
    assert_eq!(code, 2);
    assert!(stderr.contains("--data") && stderr.contains("worldpack sim dataset"), "{stderr}");
    let (code, _, stderr) = worldpack(&["plan", "--data", "/tmp", "--policies", "worldpack,bogus"]);
    assert_eq!(code, 2);
    assert!(stderr.contains("--policies") && stderr.contains("bogus"), "{stderr}");
}
