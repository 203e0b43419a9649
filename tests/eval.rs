//! `worldpack eval` and `worldpack probe` end to end on a reduced suite
//! (two short trajectories, a few generated frames, two sampler steps), with
//! the committed variants: the whole pipeline in seconds.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_worldpack"))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).current_dir(root()).output().expect("worldpack runs")
}

fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(out.status.success(), "worldpack {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("worldpack-eval-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// A reduced suite of its own for each test (tests run in parallel in one process).
fn suite(test: &str) -> PathBuf {
    let dir = temp(&format!("suite-{test}"));
    ok(&["sim", "loopnav", "--per-cell", "1", "--tasks", "aba,abca", "--ranges", "5", "--seed", "3", "--out", dir.to_str().unwrap()]);
    dir
}

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn reduced_rollout_suite_runs_resumes_and_scores_every_frame() {
    let suite = suite("rollout");
    let out = temp("out");
    let args = ["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "5", "--steps", "2", "--threads", "1",
        "--strip", "worldpack,copy", "--strip-frames", "3", "--reconstruct", "worldpack",
        "--extra", "worldpack_keep_last=fixtures/variants/worldpack_keep_last"];
    ok(&args);
    let first = json(&out.join("results.json"));
    strip_shows_the_scored_frames(&first, &out.join("strip.png"));
    let rows: Vec<&str> = first["rows"].as_array().unwrap().iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(
        rows,
        ["baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldmem_greedy", "worldpack_keep_last", "worldpack_autoencoder", "copy", "reproject", "reproject_fused", "composite"]
    );
    let trajectories = first["trajectories"].as_array().unwrap();
    assert_eq!(trajectories.len(), 2);
    for (name, per_traj) in first["per_frame"].as_object().unwrap() {
        for (t, frames) in per_traj.as_array().unwrap().iter().enumerate() {
            let frames = frames.as_array().unwrap();
            assert_eq!(frames.len(), 5, "{name}: trajectory {t}");
            let start = trajectories[t]["returning_point"].as_u64().unwrap();
            for (j, f) in frames.iter().enumerate() {
                assert_eq!(f["t"].as_u64().unwrap(), start + j as u64, "{name}: frames in order from the returning point");
                let (psnr, ssim) = (f["psnr"].as_f64().unwrap(), f["ssim"].as_f64().unwrap());
                assert!(psnr > 5.0 && psnr <= 100.0, "{name}: PSNR {psnr}");
                assert!(ssim > -1.0 && ssim <= 1.0, "{name}: SSIM {ssim}");
                // Every synthetic truth has edges, so every frame has a sharpness ratio.
                let sharpness = f["sharpness"].as_f64().unwrap_or_else(|| panic!("{name}: no sharpness in {f}"));
                assert!(sharpness > 0.0 && sharpness.is_finite(), "{name}: sharpness {sharpness}");
            }
        }
    }
    // The memory-free reference and a learned policy must not score the same frames identically.
    assert_ne!(first["per_frame"]["copy"], first["per_frame"]["worldpack"]);
    // Policies with other contexts generate other frames.
    assert_ne!(first["per_frame"]["baseline"], first["per_frame"]["worldpack"]);
    // Pooled sharpness is the mean of the per-frame ratios.
    let pooled = first["pooled"].as_array().unwrap();
    let copy = pooled.iter().find(|r| r["row"] == "copy").unwrap();
    let ratios: Vec<f64> = first["per_frame"]["copy"].as_array().unwrap().iter().flat_map(|t| t.as_array().unwrap().iter().map(|f| f["sharpness"].as_f64().unwrap())).collect();
    let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
    assert!((copy["sharpness"]["mean"].as_f64().unwrap() - mean).abs() < 1e-9, "{copy}");
    // The revisit stratum keeps a subset of the frames, the same for every row.
    let revisit = &first["strata"][0];
    assert_eq!(revisit["name"], "revisit");
    let frames = revisit["frames"].as_u64().unwrap();
    assert!(frames <= 10, "{revisit}");
    for r in revisit["pooled"].as_array().unwrap() {
        assert_eq!(r["psnr"]["values"].as_u64().unwrap(), frames, "{r}");
    }
    // The autoencoder row is the truth through the model's autoencoder: closer to the truth
    // than any frame the model generates, but not the truth itself.
    let psnr_of = |row: &str| pooled.iter().find(|r| r["row"] == row).unwrap()["psnr"]["mean"].as_f64().unwrap();
    let ceiling = psnr_of("worldpack_autoencoder");
    assert!(ceiling < 60.0, "the reconstruction is not the truth: {ceiling}");
    for row in ["baseline", "worldpack", "worldpack_keep_last"] {
        assert!(ceiling > psnr_of(row) + 3.0, "{row}: {} against the autoencoder's {ceiling}", psnr_of(row));
    }
    // New ground is the rest of the return leg.
    let new_ground = &first["strata"][1];
    assert_eq!(new_ground["name"], "new_ground");
    let all_frames = copy["psnr"]["values"].as_u64().unwrap();
    assert_eq!(frames + new_ground["frames"].as_u64().unwrap(), all_frames, "{new_ground}");
    // The holes measure: the holes are the fused warp's of the exploration, so every row
    // is scored over the same frames there, and their sharpness with them.
    let values = |r: &Value, k: &str| r[k]["values"].as_u64().unwrap_or(0);
    let holes = values(copy, "holes_psnr");
    assert!(holes <= all_frames, "{copy}");
    for r in pooled {
        assert_eq!(values(r, "holes_psnr"), holes, "every row is scored over the same holes: {r}");
        assert!(values(r, "holes_sharpness") <= holes, "{r}");
    }

    // A second run reuses every row and reproduces the results.
    let log = ok(&args);
    assert_eq!(log.matches("reusing").count(), 11, "{log}");
    let second = json(&out.join("results.json"));
    assert_eq!(first["cells"], second["cells"]);
    // The probe's frames: 3 unless set, so saying 3 reuses every row; more frames make
    // other holes, so no row scored over the old ones is reused, and the holes shrink.
    let mut explicit = args.to_vec();
    explicit.extend(["--probe-frames", "3"]);
    let log = ok(&explicit);
    assert_eq!(log.matches("reusing").count(), 11, "{log}");
    let wider = ["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "5", "--steps", "2",
        "--threads", "1", "--policies", "baseline", "--probe-frames", "8"];
    let log = ok(&wider);
    assert!(!log.contains("reusing"), "{log}");
    let third = json(&out.join("results.json"));
    let pooled8 = third["pooled"].as_array().unwrap();
    let copy8 = pooled8.iter().find(|r| r["row"] == "copy").unwrap();
    let hole_frames8 = values(copy8, "holes_psnr");
    assert!(hole_frames8 <= holes, "8 frames leave holes in no more frames than 3: {hole_frames8} against {holes}");
    let fused_psnr = |p: &[Value]| p.iter().find(|r| r["row"] == "reproject_fused").unwrap()["psnr"]["mean"].as_f64().unwrap();
    assert_ne!(fused_psnr(pooled8), fused_psnr(pooled), "the fused reference warps 8 frames, not 3");
    // Other settings are not confused with saved rows.
    let log = ok(&["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "3", "--steps", "2",
        "--policies", "worldpack", "--no-references", "--threads", "1"]);
    assert!(!log.contains("reusing"), "{log}");

    // The report renders from the results (when the test venv is there).
    let python = root().join(".venv/bin/python");
    if python.exists() {
        let md = out.join("report/results.md");
        let status = Command::new(python)
            .args(["scripts/report.py", out.join("results.json").to_str().unwrap(), "-o", md.to_str().unwrap()])
            .current_dir(root())
            .status()
            .unwrap();
        assert!(status.success());
        let text = std::fs::read_to_string(&md).unwrap();
        assert!(text.contains("| **WorldPack** |") && text.contains("curves-abca.png"), "{text}");
        assert!(out.join("report/results/curves-aba.png").exists());
    }
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&out);
}

/// The strip is truth, worldpack, copy at 3 evenly spaced frames of the
/// chosen leg; each tile scores against the truth tile as results.json says
/// that frame scored (copy exactly; the model within its batch tolerance).
fn strip_shows_the_scored_frames(results: &Value, path: &Path) {
    let strip = &results["strip"];
    assert_eq!(strip["rows"], serde_json::json!(["truth", "worldpack", "copy"]));
    let frames: Vec<u64> = strip["frames"].as_array().unwrap().iter().map(|f| f.as_u64().unwrap()).collect();
    let ti = results["trajectories"].as_array().unwrap().iter().position(|t| t["dir"] == strip["trajectory"]).unwrap();
    let start = results["trajectories"][ti]["returning_point"].as_u64().unwrap();
    assert_eq!(frames, [start, start + 2, start + 4], "5 generated frames, 3 columns");

    let mut decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().unwrap();
    let mut px = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut px).unwrap();
    let (w, size, gap) = (info.width as usize, 64, 2);
    assert_eq!((info.width, info.height), (3 * 64 + 2 * 2, 3 * 64 + 2 * 2));
    let tile = |r: usize, c: usize| -> Vec<u8> {
        (0..size).flat_map(|y| {
            let at = ((r * (size + gap) + y) * w + c * (size + gap)) * 3;
            px[at..at + size * 3].to_vec()
        }).collect()
    };
    let psnr = |a: &[u8], b: &[u8]| {
        let mse = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
        10.0 * (255.0f64 * 255.0 / mse).log10()
    };
    for (row, name, tolerance) in [(1, "worldpack", 0.05), (2, "copy", 1e-9)] {
        for (c, &t) in frames.iter().enumerate() {
            let scored = results["per_frame"][name][ti].as_array().unwrap().iter().find(|f| f["t"] == t).unwrap()["psnr"].as_f64().unwrap();
            let shown = psnr(&tile(row, c), &tile(0, c));
            assert!((shown - scored).abs() <= tolerance, "{name} at frame {t}: the strip shows {shown} dB, the row scored {scored}");
        }
    }
}

#[test]
fn feature_networks_add_lpips_dreamsim_and_fvd() {
    let suite = suite("features");
    let out = temp("features");
    let nets = root().join("fixtures/metrics");
    let net = |f: &str| nets.join(f).to_str().unwrap().to_string();
    ok(&["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "8", "--steps", "1", "--threads", "1",
        "--policies", "worldpack", "--lpips", &net("lpips_tiny.onnx"), "--dreamsim", &net("embed_tiny.onnx"), "--fvd", &net("video_tiny.onnx")]);
    let r = json(&out.join("results.json"));
    for cell in r["cells"].as_array().unwrap() {
        let (lpips, dreamsim) = (cell["lpips"][0].as_f64().unwrap(), cell["dreamsim"][0].as_f64().unwrap());
        assert!(lpips > 0.0 && (0.0..=2.0).contains(&dreamsim), "{cell}");
    }
    // 8 frames per trajectory, clips of 4: two clips per trajectory, one trajectory per cell.
    for (row, cells) in r["fvd"].as_object().unwrap() {
        let cells = cells.as_array().unwrap();
        assert_eq!(cells.len(), 2, "{row}");
        for c in cells {
            assert_eq!(c["clips"], 2);
            let (v, lo, hi) = (c["fvd"].as_f64().unwrap(), c["lo"].as_f64().unwrap(), c["hi"].as_f64().unwrap());
            assert!(v >= 0.0 && lo <= hi, "{c}");
        }
    }
    // A network that breaks the contract is refused, naming the flag.
    let e = run(&["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--lpips", &net("embed_tiny.onnx")]);
    assert_eq!(e.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&e.stderr).contains("--lpips"), "{}", String::from_utf8_lossy(&e.stderr));
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn probe_compares_every_row_with_the_baseline() {
    let suite = suite("probe");
    let out = temp("probe").join("probe.json");
    // The first-trained generation: its WorldPack also has a recency layout, so every probe row runs.
    let models = temp("probe-models");
    for (name, from) in [("baseline", "baseline_12k"), ("worldpack", "worldpack_12k"), ("nearest_frame_packing", "nearest_frame_packing"),
        ("memory_retrieval", "memory_retrieval"), ("worldpack_keep_last", "worldpack_keep_last")] {
        copy_dir(&root().join("fixtures/variants").join(from), &models.join(name));
    }
    ok(&["probe", "--suite", suite.to_str().unwrap(), "--models", models.to_str().unwrap(), "--steps", "2", "--stride", "6", "--latency-calls", "2",
        "--threads", "1", "--sweep-steps", "1", "--out", out.to_str().unwrap()]);
    let report = json(&out);
    let rows = report["rows"].as_array().unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldpack_keep_last",
        "worldpack weights, recency contexts", "worldpack weights, newest frame kept", "worldpack, 1 steps",
        "copy best-overlap frame", "reproject best-overlap frame", "reproject 3 best frames, fused", "fused warp, baseline in its holes"]);
    let frames = rows[0]["frames"].as_u64().unwrap();
    assert!(frames > 0);
    for r in rows {
        assert_eq!(r["frames"].as_u64(), Some(frames), "every row scores the same frames");
        assert!(r["latency_ms"].as_f64().unwrap() > 0.0);
        if r["name"] == "baseline" {
            assert!(r["psnr_vs_baseline"].is_null());
            continue;
        }
        let iv = &r["psnr_vs_baseline"];
        let (lo, mean, hi) = (iv["lo"].as_f64().unwrap(), iv["mean"].as_f64().unwrap(), iv["hi"].as_f64().unwrap());
        assert!(lo <= mean + 1e-9 && mean <= hi + 1e-9, "{}: {lo} {mean} {hi}", r["name"]);
        let direct = r["psnr"].as_f64().unwrap() - rows[0]["psnr"].as_f64().unwrap();
        assert!((direct - mean).abs() < 1e-9, "{}: paired mean {mean} vs difference of means {direct}", r["name"]);
    }
    assert_eq!(report["contrasts"].as_array().unwrap().len(), 6);
    // Inside the validity mask the composite shows the fused warp's own pixels, as the fused reference does;
    // outside, one shows the baseline's prediction and the other filled cracks and the best frame's pixels.
    let row = |name: &str| rows.iter().find(|r| r["name"] == name).unwrap();
    let (fused, composite) = (row("reproject 3 best frames, fused"), row("fused warp, baseline in its holes"));
    assert_eq!(fused["psnr_in_warp"].as_f64(), composite["psnr_in_warp"].as_f64());
    assert_ne!(fused["psnr_out_warp"].as_f64(), composite["psnr_out_warp"].as_f64());
    let depth = &report["warped_depth"];
    let (abs_rel, coverage) = (depth["abs_rel"].as_f64().unwrap(), depth["coverage"].as_f64().unwrap());
    assert!(abs_rel > 0.0 && abs_rel < 0.5 && coverage > 0.05 && coverage <= 1.0, "warped depth: {depth}");
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(out.parent().unwrap());
}

#[test]
fn bad_arguments_name_what_is_wrong() {
    let err = |args: &[&str]| {
        let out = run(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let missing = temp("missing");
    let e = err(&["eval", "--suite", missing.to_str().unwrap()]);
    assert!(e.contains("index.json") && e.contains("worldpack sim loopnav"), "{e}");
    let suite = suite("bad");
    let empty = temp("empty-models");
    std::fs::create_dir_all(&empty).unwrap();
    let bad_out = temp("bad-out");
    let e = err(&["eval", "--suite", suite.to_str().unwrap(), "--models", empty.to_str().unwrap(), "--out", bad_out.to_str().unwrap()]);
    assert!(e.contains("--models") && e.contains("baseline"), "{e}");
    let e = err(&["probe", "--suite", suite.to_str().unwrap(), "--models", empty.to_str().unwrap()]);
    assert!(e.contains("--models") && e.contains("baseline/"), "{e}");
    let e = err(&["eval", "--suite", suite.to_str().unwrap(), "--policies", "worldpak"]);
    assert!(e.contains("worldpak") && e.contains("worldmem_greedy"), "{e}");
    let e = err(&["probe", "--suite", suite.to_str().unwrap(), "--extra", "nodir"]);
    assert!(e.contains("NAME=DIR"), "{e}");
    let e = err(&["eval", "--suite", suite.to_str().unwrap(), "--probe-frames", "0"]);
    assert!(e.contains("--probe-frames"), "{e}");
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&empty);
    let _ = std::fs::remove_dir_all(&bad_out);
}

#[test]
fn study_pairs_every_condition_and_resumes() {
    let suite = suite("study");
    // "Estimated" poses that are the true ones: that condition must change nothing at all.
    for entry in std::fs::read_dir(&suite).unwrap() {
        let dir = entry.unwrap().path();
        if dir.join("poses.npy").exists() {
            std::fs::copy(dir.join("poses.npy"), dir.join("poses-same.npy")).unwrap();
        }
    }
    let out = temp("study-out");
    let (s, o) = (suite.to_str().unwrap(), out.to_str().unwrap());
    let args = [
        "study", "--suite", s, "--out", o, "--quick", "--steps", "2", "--sweep-steps", "1", "--stride", "4", "--latency-calls", "1", "--threads", "1", "--rollout-frames", "6", "--vo",
        "poses-same.npy", "--contrast", "worldpack:baseline",
    ];
    ok(&args);
    let study = json(&out.join("study.json"));

    let points = study["tradeoff"].as_array().unwrap();
    let names: Vec<&str> = points.iter().map(|p| p["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "baseline", "nearest_frame_packing", "memory_retrieval", "worldpack", "worldpack_keep_last", "worldmem_greedy", "worldpack, 1 steps",
            "worldpack_keep_last, 1 steps",
            "worldpack, Monte Carlo 1000", "worldpack, Monte Carlo 10000", "copy", "reproject"
        ]
    );
    let at = |p: &Value, k: &str| p[k].as_f64().unwrap();
    for p in points {
        assert!(at(p, "latency_ms") > 0.0 && at(p, "psnr") > 5.0, "{p}");
        // The front flag means exactly "no other point is at least as fast and as accurate".
        let beaten = points.iter().any(|q| {
            at(q, "latency_ms") <= at(p, "latency_ms") && at(q, "psnr") >= at(p, "psnr") && (at(q, "latency_ms") < at(p, "latency_ms") || at(q, "psnr") > at(p, "psnr"))
        });
        assert_eq!(p["pareto"].as_bool().unwrap(), !beaten, "{}", p["name"]);
    }

    let noise = study["noise"].as_array().unwrap();
    let conditions: Vec<&str> = noise.iter().map(|c| c["condition"].as_str().unwrap()).collect();
    assert_eq!(conditions, ["translation σ 0.25", "rotation σ 2.5°", "estimated poses (poses-same.npy)"]);
    let same = &noise[2];
    assert_eq!(at(same, "pose_error_blocks"), 0.0);
    for r in same["rows"].as_array().unwrap() {
        assert_eq!(r["psnr_vs_clean"]["mean"].as_f64().unwrap(), 0.0, "{}: the true poses changed a prediction", r["row"]);
    }
    for a in same["selection"].as_array().unwrap() {
        assert_eq!((at(a, "jaccard"), at(a, "rank")), (1.0, 1.0), "{}", a["policy"]);
    }
    let rotated = &noise[1];
    assert!(at(rotated, "pose_error_deg") > 2.0);
    for a in rotated["selection"].as_array().unwrap() {
        let policy = a["policy"].as_str().unwrap();
        if policy == "baseline" || policy == "nearest_frame_packing" {
            assert_eq!(at(a, "jaccard"), 1.0, "{policy} selects by recency alone");
        }
    }
    let reproject = rotated["rows"].as_array().unwrap().iter().find(|r| r["row"] == "reproject").unwrap();
    assert!(reproject["psnr_vs_clean"]["mean"].as_f64().unwrap() < 0.0, "warping with wrong poses should cost: {reproject}");

    // A contrast in every condition: the paired mean is the difference of the rows' means, and the true poses change nothing.
    let contrasts = study["contrasts"].as_array().unwrap();
    let names: Vec<&str> = contrasts.iter().map(|c| c["condition"].as_str().unwrap()).collect();
    assert_eq!(names, ["clean", "translation σ 0.25", "rotation σ 2.5°", "estimated poses (poses-same.npy)"]);
    let mean = |c: &Value| c["psnr"]["mean"].as_f64().unwrap();
    let psnr_of = |name: &str| at(points.iter().find(|p| p["name"] == name).unwrap(), "psnr");
    assert!((mean(&contrasts[0]) - (psnr_of("worldpack") - psnr_of("baseline"))).abs() < 1e-9, "{}", contrasts[0]);
    assert_eq!(mean(&contrasts[3]), mean(&contrasts[0]));
    assert_ne!(mean(&contrasts[2]), mean(&contrasts[0]), "rotated poses change WorldPack's frames, not the baseline's");

    // Rollouts under the same poses are the noise-free rollouts, frame for frame.
    let rollouts = study["rollouts"].as_array().unwrap();
    let names: Vec<&str> = rollouts.iter().map(|c| c["condition"].as_str().unwrap()).collect();
    assert_eq!(names, ["clean", "estimated poses (poses-same.npy)"]);
    assert!(rollouts[1]["frames"].as_u64().unwrap() > 0);
    for r in rollouts[1]["rows"].as_array().unwrap() {
        assert_eq!(r["psnr_vs_clean"]["mean"].as_f64().unwrap(), 0.0, "{}: the true poses changed a rollout", r["row"]);
    }

    let strata = study["strata"].as_array().unwrap();
    assert_eq!(strata.len(), 7);
    assert_eq!(strata[5]["stratum"], "revisit");
    assert_eq!(strata[0]["stratum"], "all");
    assert_eq!(strata[0]["targets"], study["targets"]);
    assert!(strata.iter().all(|s| s["targets"].as_u64().unwrap() <= study["targets"].as_u64().unwrap()));
    // Selection policies are also paired with nearest frame packing, the same packing filled by recency.
    let row = |name: &str| strata[0]["rows"].as_array().unwrap().iter().find(|r| r["row"] == name).unwrap().clone();
    let (kept, recency) = (row("worldpack_keep_last"), row("nearest_frame_packing"));
    let gap = kept["psnr_vs_recency"]["mean"].as_f64().unwrap() - (at(&kept, "psnr") - at(&recency, "psnr"));
    assert!(gap.abs() < 1e-9, "paired mean against NFP is the difference of means: {gap}");
    for name in ["baseline", "nearest_frame_packing", "copy", "reproject"] {
        assert!(row(name)["psnr_vs_recency"].is_null(), "{name} is not a selection policy compared with recency");
    }
    // The recommendation is a learned point of the learned front; the report draws what study.json says.
    let recommended = study["recommended"]["name"].as_str().unwrap();
    let point = study["tradeoff"].as_array().unwrap().iter().find(|p| p["name"] == recommended).unwrap();
    assert!(point["pareto_learned"].as_bool().unwrap() && point["group"] != "reference", "{point}");
    let python = root().join(".venv/bin/python");
    if python.exists() {
        let pictures = out.join("pictures");
        let report = Command::new(python)
            .args(["scripts/study_report.py", out.join("study.json").to_str().unwrap(), pictures.to_str().unwrap()])
            .current_dir(root())
            .output()
            .unwrap();
        assert!(report.status.success(), "{}", String::from_utf8_lossy(&report.stderr));
        let text = String::from_utf8_lossy(&report.stdout);
        assert!(text.contains("**Recommended default: "), "{text}");
        assert!(pictures.join("tradeoff.png").exists() && pictures.join("tradeoff.svg").exists());
    }

    // A second run reuses every condition and reports the same numbers.
    let log = ok(&args);
    assert_eq!(log.matches("reused").count(), 6, "{log}");
    assert_eq!(json(&out.join("study.json"))["tradeoff"], study["tradeoff"]);

    // A poses file that is not there is named before any work.
    let bad = run(&["study", "--suite", s, "--out", o, "--quick", "--vo", "nope.npy"]);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("--vo: nope.npy"), "{err}");
    let bad = run(&["study", "--suite", s, "--out", o, "--quick", "--contrast", "worldpack:nope"]);
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("--contrast") && err.contains("\"nope\""), "{err}");
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&out);
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let dest = to.join(path.file_name().unwrap());
        if path.is_dir() { copy_dir(&path, &dest) } else { std::fs::copy(&path, &dest).map(|_| ()).unwrap() }
    }
}

#[test]
fn a_model_changed_in_place_is_not_mistaken_for_its_saved_rows() {
    let suite = suite("changed");
    let (models, out) = (temp("changed-models"), temp("changed-out"));
    for name in ["baseline", "nearest_frame_packing"] {
        copy_dir(&root().join("fixtures/variants").join(name), &models.join(name));
    }
    let args = [
        "eval", "--suite", suite.to_str().unwrap(), "--models", models.to_str().unwrap(), "--out", out.to_str().unwrap(), "--policies",
        "baseline,nearest_frame_packing", "--no-references", "--max-frames", "2", "--steps", "1", "--threads", "1",
    ];
    ok(&args);
    assert_eq!(ok(&args).matches("reusing").count(), 2);
    // Re-exporting writes new files at the same path; any change to them must rerun that row only.
    let manifest = models.join("nearest_frame_packing/manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, text + "\n").unwrap();
    let log = ok(&args);
    assert_eq!(log.matches("reusing").count(), 1, "{log}");
    for dir in [suite, models, out] {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// The occluder suite and occlusion-aware selection in rollouts: the geometry
/// model runs with frustum-overlap plans and warp sources, with co-visible
/// ones, and warping only its own plan's frames, on two walled scenes.
#[test]
fn occluder_scenes_and_co_visible_rollouts() {
    let suite = temp("occluders");
    ok(&["sim", "occluders", "--count", "2", "--range", "6", "--seed", "3", "--out", suite.to_str().unwrap()]);
    let index = json(&suite.join("index.json"));
    assert_eq!(index["kind"], "occluders");
    for t in index["trajectories"].as_array().unwrap() {
        assert_eq!(t["task"], "occluder");
        let (frames, back) = (t["frames"].as_u64().unwrap(), t["returning_point"].as_u64().unwrap());
        assert!(back > 20 && frames > back + 10, "an exploration around the wall and a way back: {t}");
    }
    let out = temp("occluders-out");
    let geometry = root().join("fixtures/variants/worldpack_geometry");
    let extra = format!("worldpack_geometry={}", geometry.display());
    let args = ["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "4", "--steps", "2", "--threads", "1",
        "--policies", "baseline", "--no-references", "--extra", &extra, "--covisible", "worldpack_geometry", "--plan-warps", "worldpack_geometry"];
    ok(&args);
    let results = json(&out.join("results.json"));
    let rows: Vec<&str> = results["rows"].as_array().unwrap().iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(rows, ["baseline", "worldpack_geometry", "worldpack_geometry_covisible", "worldpack_geometry_plan_warps"]);
    for row in ["worldpack_geometry_covisible", "worldpack_geometry_plan_warps"] {
        for per_traj in results["per_frame"][row].as_array().unwrap() {
            let frames = per_traj.as_array().unwrap();
            assert_eq!(frames.len(), 4);
            assert!(frames.iter().all(|f| f["psnr"].as_f64().unwrap() > 5.0), "{row}: {per_traj}");
        }
    }
    for (flag, row, says) in [("--covisible", "nope", "nope"), ("--plan-warps", "baseline", "no warp input")] {
        let bad = run(&["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--policies", "baseline", flag, row, "--no-references"]);
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(!bad.status.success() && err.contains(flag) && err.contains(says), "{err}");
    }
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&out);
}

/// `worldpack fusion-data` writes what a fusion head trains on, and the
/// committed geometry model with its fusion head, probed one step ahead on a
/// fresh suite, beats both of what it blends: the same model without the
/// head and the fused warp of its sources.
#[test]
fn a_fusion_head_beats_the_model_and_the_warp_it_blends() {
    let suite = suite("fusion");
    let data = temp("fusion-data");
    let geometry = root().join("fixtures/variants/worldpack_geometry");
    ok(&["fusion-data", "--suite", suite.to_str().unwrap(), "--model", geometry.to_str().unwrap(), "--stride", "3", "--steps", "2",
        "--threads", "1", "--out", data.to_str().unwrap()]);
    let shape = |name: &str| world::npy::read::<u8>(&data.join(format!("{name}.npy"))).unwrap().0;
    let n = shape("truth")[0];
    assert!(n > 0);
    for name in ["predicted", "reference", "truth"] {
        assert_eq!(shape(name), [n, 64, 64, 3], "{name}");
    }
    assert_eq!(shape("landed"), [n, 64, 64]);
    let fused = root().join("fixtures/variants/worldpack_geometry_fused");
    let e = String::from_utf8_lossy(&run(&["fusion-data", "--suite", suite.to_str().unwrap(), "--model", fused.to_str().unwrap(),
        "--out", data.to_str().unwrap()]).stderr).into_owned();
    assert!(e.contains("fusion head already"), "{e}");
    // From the fused model's own rollouts, the head's input remade by its twin without the head.
    let rollout = temp("fusion-data-rollout");
    let from_rollouts = |model: &Path, with: &Path| {
        run(&["fusion-data", "--suite", suite.to_str().unwrap(), "--stride", "1", "--steps", "2", "--threads", "1", "--out", rollout.to_str().unwrap(),
            "--model", model.to_str().unwrap(), "--rollout-with", with.to_str().unwrap()])
    };
    let made = from_rollouts(&geometry, &fused);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let taken = world::npy::read::<u8>(&rollout.join("truth.npy")).unwrap().0[0];
    assert_eq!(world::npy::read::<u8>(&rollout.join("landed.npy")).unwrap().0, [taken, 64, 64]);
    assert!(taken > n, "every generated frame of the return legs at stride 1 ({taken}) against every third teacher-forced one ({n})");
    let e = String::from_utf8_lossy(&from_rollouts(&root().join("fixtures/variants/worldpack_recipe"), &fused).stderr).into_owned();
    assert!(e.contains("--model") && e.contains("without its head"), "{e}");
    let e = String::from_utf8_lossy(&from_rollouts(&geometry, &geometry).stderr).into_owned();
    assert!(e.contains("--rollout-with") && e.contains("no fusion head"), "{e}");
    let _ = std::fs::remove_dir_all(&rollout);

    let out = temp("fusion-probe").join("probe.json");
    ok(&["probe", "--suite", suite.to_str().unwrap(), "--stride", "2", "--latency-calls", "1", "--threads", "1",
        "--extra", &format!("worldpack_geometry={}", geometry.display()), "--extra", &format!("worldpack_geometry_fused={}", fused.display()),
        "--out", out.to_str().unwrap()]);
    let report = json(&out);
    let psnr = |name: &str| report["rows"].as_array().unwrap().iter().find(|r| r["name"] == name).unwrap()["psnr"].as_f64().unwrap();
    let (head, alone, warp) = (psnr("worldpack_geometry_fused"), psnr("worldpack_geometry"), psnr("reproject 3 best frames, fused"));
    assert!(head > alone && head > warp, "with the head {head:.2} dB, the model alone {alone:.2}, the fused warp {warp:.2}");
    let _ = std::fs::remove_dir_all(&suite);
    let _ = std::fs::remove_dir_all(&data);
    let _ = std::fs::remove_dir_all(out.parent().unwrap());
}

/// On a suite larger than the model's frames, a model row shows full-size
/// frames (`model::full_size`) and `--upsampled` adds the bicubic floor
/// under it; both are scored against the full-size truth, with the full-size
/// fused warp beside them. On a suite at the model's size the floor is refused.
#[test]
fn a_suite_at_96_scores_full_size_frames_beside_the_upsampled_floor() {
    let suite = temp("suite-96");
    ok(&["sim", "loopnav", "--per-cell", "1", "--tasks", "aba", "--ranges", "5", "--seed", "3", "--size", "96x96", "--out", suite.to_str().unwrap()]);
    let out = temp("out-96");
    let served = "served=fixtures/variants/worldpack_geometry_fused_1step";
    ok(&["eval", "--suite", suite.to_str().unwrap(), "--out", out.to_str().unwrap(), "--max-frames", "6", "--threads", "1", "--policies", "baseline",
        "--extra", served, "--only", "served", "--upsampled", "served", "--only", "served_upsampled_64", "--against", "served_upsampled_64"]);
    let r = json(&out.join("results.json"));
    let rows: Vec<&str> = r["rows"].as_array().unwrap().iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(rows, ["served", "served_upsampled_64", "copy", "reproject", "reproject_fused"]);
    let frames = |row: &str| r["per_frame"][row].as_array().unwrap().iter().flat_map(|t| t.as_array().unwrap().iter().cloned()).collect::<Vec<Value>>();
    let (full, floor) = (frames("served"), frames("served_upsampled_64"));
    assert_eq!(full.len(), 6);
    // The same model frames, shown two ways: they differ where the warp was shown, never in count.
    assert!(full.iter().zip(&floor).any(|(a, b)| a["psnr"] != b["psnr"]), "the full-size frames show the stored frames somewhere");
    assert!(full.iter().chain(&floor).all(|f| f["psnr"].as_f64().unwrap().is_finite() && f["sharpness"].as_f64().unwrap() > 0.0));
    // At the model's own size there is nothing to upsample.
    let small = suite_at_model_size();
    let refused = run(&["eval", "--suite", small.to_str().unwrap(), "--out", temp("out-64").to_str().unwrap(), "--max-frames", "2", "--threads", "1",
        "--policies", "baseline", "--extra", served, "--only", "served", "--upsampled", "served", "--only", "served_upsampled_64", "--no-references"]);
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("nothing to upsample"), "{}", String::from_utf8_lossy(&refused.stderr));
}

fn suite_at_model_size() -> PathBuf {
    let dir = temp("suite-64");
    ok(&["sim", "loopnav", "--per-cell", "1", "--tasks", "aba", "--ranges", "5", "--seed", "3", "--out", dir.to_str().unwrap()]);
    dir
}
