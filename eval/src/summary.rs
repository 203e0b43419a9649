//! Per-cell and per-frame summaries of rollouts: each (task, range) cell's
//! mean and spread over trajectories, and each task's mean curve along the
//! return leg.

use serde::Serialize;

use crate::probe::FrameScore;
use crate::stats::mean_std;

#[derive(Serialize)]
pub struct CellRow {
    pub task: String,
    pub range: i32,
    pub row: String,
    pub trajectories: usize,
    /// Mean and std over trajectories of each trajectory's mean.
    pub psnr: (f64, f64),
    pub ssim: (f64, f64),
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<(f64, f64)>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dreamsim: Option<(f64, f64)>,
}

#[derive(Serialize)]
pub struct Curve {
    pub task: String,
    pub row: String,
    /// Mean over trajectories at each frame index of the return leg (while at least one trajectory is that long).
    pub psnr: Vec<f64>,
    pub ssim: Vec<f64>,
}

/// One row over every trajectory of a task (all its ranges).
#[derive(Serialize)]
pub struct TaskRow {
    pub task: String,
    pub row: String,
    pub trajectories: usize,
    /// Mean over the task's trajectories of each trajectory's mean.
    pub psnr: f64,
    pub ssim: f64,
}

pub struct Summary {
    pub cells: Vec<CellRow>,
    pub tasks: Vec<TaskRow>,
    pub curves: Vec<Curve>,
}

/// The (task, range) cells of a suite, sorted.
pub fn cells_of(trajs: &[(String, i32)]) -> Vec<(String, i32)> {
    let mut keys: Vec<(String, i32)> = trajs.to_vec();
    keys.sort();
    keys.dedup();
    keys
}

pub fn summarise(trajs: &[(String, i32)], results: &[(&str, &[Vec<FrameScore>])]) -> Summary {
    let keys = cells_of(trajs);
    let mut cells = Vec::new();
    for (task, range) in &keys {
        let idx: Vec<usize> = (0..trajs.len()).filter(|&i| &trajs[i].0 == task && trajs[i].1 == *range).collect();
        for &(name, r) in results {
            let per = |m: fn(&FrameScore) -> Option<f64>| -> Vec<f64> {
                idx.iter().map(|&i| mean_std(&r[i].iter().filter_map(m).collect::<Vec<_>>()).0).filter(|v| v.is_finite()).collect()
            };
            let optional = |m: fn(&FrameScore) -> Option<f64>| Some(per(m)).filter(|v| !v.is_empty()).map(|v| mean_std(&v));
            cells.push(CellRow {
                task: task.clone(),
                range: *range,
                row: name.to_string(),
                trajectories: idx.len(),
                psnr: mean_std(&per(|f| Some(f.psnr))),
                ssim: mean_std(&per(|f| Some(f.ssim))),
                lpips: optional(|f| f.lpips),
                dreamsim: optional(|f| f.dreamsim),
            });
        }
    }
    let mut tasks: Vec<String> = keys.iter().map(|k| k.0.clone()).collect();
    tasks.dedup();
    let mut curves = Vec::new();
    let mut task_rows = Vec::new();
    for task in &tasks {
        let idx: Vec<usize> = (0..trajs.len()).filter(|&i| &trajs[i].0 == task).collect();
        for &(name, r) in results {
            let mean_of = |m: fn(&FrameScore) -> f64| mean_std(&idx.iter().map(|&i| mean_std(&r[i].iter().map(m).collect::<Vec<_>>()).0).filter(|v| v.is_finite()).collect::<Vec<_>>()).0;
            task_rows.push(TaskRow { task: task.clone(), row: name.to_string(), trajectories: idx.len(), psnr: mean_of(|f| f.psnr), ssim: mean_of(|f| f.ssim) });
        }
        for &(name, r) in results {
            let longest = idx.iter().map(|&i| r[i].len()).max().unwrap_or(0);
            let at = |j: usize, m: fn(&FrameScore) -> f64| mean_std(&idx.iter().filter_map(|&i| r[i].get(j).map(m)).collect::<Vec<_>>()).0;
            curves.push(Curve {
                task: task.clone(),
                row: name.to_string(),
                psnr: (0..longest).map(|j| at(j, |f| f.psnr)).collect(),
                ssim: (0..longest).map(|j| at(j, |f| f.ssim)).collect(),
            });
        }
    }
    Summary { cells, tasks: task_rows, curves }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_average_trajectories_and_curves_average_frames() {
        let f = |t: usize, psnr: f64| FrameScore { t, psnr, ssim: 0.5, lpips: None, dreamsim: None, sharpness: None, psnr_in_warp: None, psnr_out_warp: None, sharpness_out_warp: None };
        let labels = vec![("aba".to_string(), 5), ("aba".to_string(), 5), ("abca".to_string(), 15)];
        let frames = vec![vec![f(0, 10.0), f(1, 20.0)], vec![f(0, 30.0)], vec![f(0, 7.0)]];
        let s = summarise(&labels, &[("row", &frames)]);
        assert_eq!(cells_of(&labels), vec![("aba".to_string(), 5), ("abca".to_string(), 15)]);
        let aba = &s.cells[0];
        assert_eq!((aba.trajectories, aba.psnr.0), (2, 22.5), "trajectory means 15 and 30");
        assert_eq!((s.tasks[0].task.as_str(), s.tasks[0].trajectories, s.tasks[0].psnr), ("aba", 2, 22.5));
        assert_eq!((s.tasks[1].task.as_str(), s.tasks[1].psnr), ("abca", 7.0));
        assert!(aba.lpips.is_none());
        let curve = s.curves.iter().find(|c| c.task == "aba").unwrap();
        assert_eq!(curve.psnr, vec![20.0, 20.0], "frame 0: (10 + 30) / 2; frame 1: only the longer leg");
    }
}
