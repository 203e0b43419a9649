//! `worldpack bench fork` runs end to end on a small session and reports
//! what it measured (the figures themselves are not asserted: a test is no benchmark).

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
