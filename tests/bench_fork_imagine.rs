//! `worldpack bench fork` and `bench imagine` run end to end on small inputs and report
//! what they measured (the figures themselves are not asserted: a test is no benchmark).

use std::process::Command;

#[test]
fn bench_fork_reports_the_fork_the_copy_and_the_runs() {
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack")).args(["bench", "fork", "--frames", "300", "--forks", "3", "--json"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stdout)));
    assert_eq!((r["frames"].as_u64(), r["forks"].as_u64()), (Some(300), Some(3)), "{r}");
    // Two forks a round, each after a new frame: the first run and one more per fork.
    assert_eq!(r["runs"].as_u64(), Some(7), "{r}");
    for field in ["fork_median_ms", "memory_fork_median_ms", "copy_median_ms", "select_runs_median_ms", "select_one_run_median_ms"] {
        assert!(r[field].as_f64().is_some_and(|v| v.is_finite() && v >= 0.0), "{field}: {r}");
    }
    let (code, bad) = {
        let o = Command::new(env!("CARGO_BIN_EXE_worldpack")).args(["bench", "fork", "--frames", "0"]).output().unwrap();
        (o.status.code(), String::from_utf8_lossy(&o.stderr).to_string())
    };
    assert!(code != Some(0) && bad.contains("--frames"), "{bad}");
}

/// `worldpack bench imagine` on the small model: every row has the three ways' rates and their stages.
#[test]
fn bench_imagine_reports_batched_alone_and_stepped_rates() {
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/small");
    let args = ["bench", "imagine", "--model", fixture, "--steps", "2", "--method", "ancestral", "--covisible", "false", "--candidates", "1,3", "--horizon", "2", "--explore", "3", "--rounds", "1", "--json"];
    let out = Command::new(env!("CARGO_BIN_EXE_worldpack")).args(args).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let rows = r["rows"].as_array().unwrap();
    assert_eq!(rows.iter().map(|row| row["candidates"].as_u64().unwrap()).collect::<Vec<_>>(), [1, 3]);
    for row in rows {
        for field in ["batched_fps", "alone_fps", "stepped_fps"] {
            assert!(row[field].as_f64().is_some_and(|v| v.is_finite() && v > 0.0), "{field}: {row}");
        }
        assert_eq!((row["batched_ms"].as_array().unwrap().len(), row["stepped_ms"].as_array().unwrap().len()), (4, 8), "{row}");
    }
}
