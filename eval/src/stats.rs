//! Summaries and intervals. Frames of one trajectory are strongly
//! correlated, so intervals resample whole trajectories (a cluster
//! bootstrap) rather than frames, which would claim far too much certainty.

use memory::rng::SplitMix64;
use serde::Serialize;

use crate::probe::FrameScore;

/// Mean and sample standard deviation (0 for fewer than two values).
pub fn mean_std(xs: &[f64]) -> (f64, f64) {
    let n = xs.len();
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let mean = xs.iter().sum::<f64>() / n as f64;
    if n < 2 {
        return (mean, 0.0);
    }
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    (mean, var.sqrt())
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Interval {
    /// The frame-weighted mean over all clusters.
    pub mean: f64,
    pub lo: f64,
    pub hi: f64,
    pub clusters: usize,
    pub values: usize,
}

impl Interval {
    /// The interval lies wholly above zero.
    pub fn above_zero(&self) -> bool {
        self.lo > 0.0
    }
}

/// The 95% percentile interval of the pooled mean of `clusters` (each one
/// trajectory's paired per-frame differences), resampling clusters with
/// replacement `reps` times. Deterministic in `seed`.
pub fn cluster_bootstrap(clusters: &[Vec<f64>], reps: usize, seed: u64) -> Interval {
    let sums: Vec<(f64, usize)> = clusters.iter().filter(|c| !c.is_empty()).map(|c| (c.iter().sum(), c.len())).collect();
    let total: f64 = sums.iter().map(|s| s.0).sum();
    let count: usize = sums.iter().map(|s| s.1).sum();
    let mean = if count == 0 { f64::NAN } else { total / count as f64 };
    let k = sums.len();
    if k == 0 {
        return Interval { mean, lo: f64::NAN, hi: f64::NAN, clusters: 0, values: 0 };
    }
    let mut rng = SplitMix64::new(seed);
    let mut means: Vec<f64> = (0..reps.max(1))
        .map(|_| {
            let (mut s, mut n) = (0.0, 0usize);
            for _ in 0..k {
                let (cs, cn) = sums[(rng.next_u64() % k as u64) as usize];
                s += cs;
                n += cn;
            }
            s / n as f64
        })
        .collect();
    means.sort_by(f64::total_cmp);
    let at = |q: f64| means[((q * (means.len() - 1) as f64).round() as usize).min(means.len() - 1)];
    Interval { mean, lo: at(0.025), hi: at(0.975), clusters: k, values: count }
}

/// The `q`-quantile (0 to 1) of sorted values, by the nearest rank; NaN when there are none.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize]
}

/// One row over every scored frame of a suite.
#[derive(Clone, Debug, Serialize)]
pub struct PooledRow {
    pub row: String,
    /// Frame-weighted mean with a 95% bootstrap interval over trajectories.
    pub psnr: Interval,
    pub ssim: Interval,
    /// The mean of each trajectory's mean (every trajectory counts once).
    pub psnr_trajectory_weighted: f64,
    pub ssim_trajectory_weighted: f64,
    /// This row minus the reference row, frame by frame, pooled (absent for the reference itself).
    pub psnr_diff: Option<Interval>,
    pub ssim_diff: Option<Interval>,
    /// The mean sharpness ratio (prediction's gradient energy over the
    /// truth's) over the frames that have one; absent when none has.
    pub sharpness: Option<Interval>,
    /// PSNR and sharpness over the fused warp's holes, where memory has no
    /// pixels (frames with enough hole pixels; absent when none has), and the
    /// PSNR there paired against the reference row.
    pub holes_psnr: Option<Interval>,
    pub holes_psnr_diff: Option<Interval>,
    pub holes_sharpness: Option<Interval>,
}

/// Pooled PSNR and SSIM of each row (per trajectory, per frame; every row
/// scores the same frames in the same order), and each row's paired
/// difference to row `against`. `None` when no row is called `against`.
pub fn pooled(rows: &[(&str, &[Vec<FrameScore>])], against: &str, reps: usize) -> Option<Vec<PooledRow>> {
    let reference = rows.iter().find(|(n, _)| *n == against)?.1;
    let clusters = |r: &[Vec<FrameScore>], m: fn(&FrameScore) -> f64| -> Vec<Vec<f64>> { r.iter().map(|t| t.iter().map(m).collect()).collect() };
    let paired = |r: &[Vec<FrameScore>], m: fn(&FrameScore) -> f64| -> Vec<Vec<f64>> {
        r.iter().zip(reference).map(|(a, b)| a.iter().zip(b).map(|(x, y)| m(x) - m(y)).collect()).collect()
    };
    let some = |r: &[Vec<FrameScore>], m: fn(&FrameScore) -> Option<f64>| -> Option<Interval> {
        Some(cluster_bootstrap(&r.iter().map(|t| t.iter().filter_map(m).collect()).collect::<Vec<_>>(), reps, 7)).filter(|i| i.values > 0)
    };
    let paired_some = |r: &[Vec<FrameScore>], m: fn(&FrameScore) -> Option<f64>| -> Option<Interval> {
        let c: Vec<Vec<f64>> = r.iter().zip(reference).map(|(a, b)| a.iter().zip(b).filter_map(|(x, y)| Some(m(x)? - m(y)?)).collect()).collect();
        Some(cluster_bootstrap(&c, reps, 7)).filter(|i| i.values > 0)
    };
    let trajectory_mean = |c: &[Vec<f64>]| mean_std(&c.iter().filter(|t| !t.is_empty()).map(|t| mean_std(t).0).collect::<Vec<_>>()).0;
    let psnr = |f: &FrameScore| f.psnr;
    let ssim = |f: &FrameScore| f.ssim;
    Some(
        rows.iter()
            .map(|&(name, r)| {
                let (p, q) = (clusters(r, psnr), clusters(r, ssim));
                let own = name == against;
                PooledRow {
                    row: name.to_string(),
                    psnr: cluster_bootstrap(&p, reps, 7),
                    ssim: cluster_bootstrap(&q, reps, 7),
                    psnr_trajectory_weighted: trajectory_mean(&p),
                    ssim_trajectory_weighted: trajectory_mean(&q),
                    psnr_diff: (!own).then(|| cluster_bootstrap(&paired(r, psnr), reps, 7)),
                    ssim_diff: (!own).then(|| cluster_bootstrap(&paired(r, ssim), reps, 7)),
                    sharpness: some(r, |f| f.sharpness),
                    holes_psnr: some(r, |f| f.psnr_out_warp),
                    holes_psnr_diff: if own { None } else { paired_some(r, |f| f.psnr_out_warp) },
                    holes_sharpness: some(r, |f| f.sharpness_out_warp),
                }
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_takes_the_nearest_rank() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!((percentile(&v, 0.0), percentile(&v, 0.5), percentile(&v, 0.99), percentile(&v, 1.0)), (1.0, 3.0, 5.0, 5.0));
        assert!(percentile(&[], 0.5).is_nan());
    }

    #[test]
    fn mean_std_matches_hand_values() {
        let (m, s) = mean_std(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(m, 2.5);
        assert!((s - (5.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(mean_std(&[7.0]), (7.0, 0.0));
    }

    #[test]
    fn a_clear_shift_excludes_zero_and_clusters_that_disagree_do_not() {
        let mut rng = SplitMix64::new(9);
        // Each trajectory has its own offset (±1 around `shift`) plus frame noise.
        let mut clusters = |shift: f64| -> Vec<Vec<f64>> {
            (0..20)
                .map(|i| {
                    let offset = if i % 2 == 0 { 1.0 } else { -1.0 };
                    (0..30).map(|_| shift + offset + rng.next_f64() - 0.5).collect()
                })
                .collect()
        };
        let shifted = cluster_bootstrap(&clusters(2.0), 2000, 1);
        assert!(shifted.above_zero() && shifted.lo < 2.0 && shifted.hi > 2.0, "{shifted:?}");
        // Frame-level resampling would call this mean (about 0 ± 0.03) certain;
        // across trajectories it is not.
        let centred = cluster_bootstrap(&clusters(0.0), 2000, 1);
        assert!(centred.lo < -0.2 && centred.hi > 0.2, "{centred:?}");
        assert_eq!((centred.clusters, centred.values), (20, 600));
    }

    #[test]
    fn one_deviant_cluster_widens_the_interval() {
        let mut clusters: Vec<Vec<f64>> = (0..10).map(|_| vec![1.0; 50]).collect();
        let tight = cluster_bootstrap(&clusters, 1000, 3);
        assert_eq!((tight.lo, tight.hi), (1.0, 1.0));
        clusters[0] = vec![-9.0; 50];
        let wide = cluster_bootstrap(&clusters, 1000, 3);
        assert!(wide.lo < 0.0 && wide.hi == 1.0, "{wide:?}");
    }

    #[test]
    fn pooled_rows_pair_frames_and_weigh_trajectories() {
        let score = |t: usize, psnr: f64| FrameScore { t, psnr, ssim: psnr / 100.0, lpips: None, dreamsim: None, sharpness: None, psnr_in_warp: None, psnr_out_warp: None, sharpness_out_warp: None };
        // Two trajectories, of 3 frames and 1 frame; the second row is 1 dB better on every frame.
        let a = vec![vec![score(0, 10.0), score(1, 10.0), score(2, 10.0)], vec![score(0, 20.0)]];
        let b: Vec<Vec<FrameScore>> = a.iter().map(|t| t.iter().map(|f| score(f.t, f.psnr + 1.0)).collect()).collect();
        let rows = pooled(&[("a", &a), ("b", &b)], "a", 200).unwrap();
        assert!((rows[0].psnr.mean - 12.5).abs() < 1e-12, "frame-weighted: (30 + 20) / 4");
        assert!((rows[0].psnr_trajectory_weighted - 15.0).abs() < 1e-12, "trajectory-weighted: (10 + 20) / 2");
        assert!(rows[0].psnr_diff.is_none());
        let d = rows[1].psnr_diff.as_ref().unwrap();
        assert!((d.mean - 1.0).abs() < 1e-12 && (d.lo - 1.0).abs() < 1e-12 && (d.hi - 1.0).abs() < 1e-12, "{d:?}");
        assert!(pooled(&[("a", &a)], "missing", 10).is_none());
        assert!(rows[0].sharpness.is_none(), "no frame has a sharpness ratio");
        let sharp: Vec<Vec<FrameScore>> = a.iter().map(|t| t.iter().map(|f| FrameScore { sharpness: Some(0.5), ..*f }).collect()).collect();
        let s = pooled(&[("a", &sharp)], "a", 10).unwrap()[0].sharpness.unwrap();
        assert_eq!((s.mean, s.values), (0.5, 4));
    }

    #[test]
    fn the_holes_measure_pairs_only_frames_with_holes_in_both_rows() {
        let f = |t: usize, holes: Option<f64>| FrameScore {
            t, psnr: 20.0, ssim: 0.5, lpips: None, dreamsim: None, sharpness: Some(1.0), psnr_in_warp: None, psnr_out_warp: holes,
            sharpness_out_warp: holes.map(|p| p / 40.0),
        };
        // Frame 1 has no holes; the second row is 2 dB better in the holes of frames 0 and 2.
        let a = vec![vec![f(0, Some(10.0)), f(1, None), f(2, Some(14.0))]];
        let b = vec![vec![f(0, Some(12.0)), f(1, None), f(2, Some(16.0))]];
        let rows = pooled(&[("a", &a), ("b", &b)], "a", 50).unwrap();
        let (psnr, diff, sharp) = (rows[1].holes_psnr.unwrap(), rows[1].holes_psnr_diff.unwrap(), rows[0].holes_sharpness.unwrap());
        assert_eq!((psnr.mean, psnr.values), (14.0, 2));
        assert_eq!((diff.mean, diff.values), (2.0, 2));
        assert!((sharp.mean - 0.3).abs() < 1e-12 && sharp.values == 2, "{sharp:?}");
        assert!(rows[0].holes_psnr_diff.is_none(), "no difference against itself");
        let none = vec![vec![f(0, None)]];
        assert!(pooled(&[("a", &none)], "a", 10).unwrap()[0].holes_psnr.is_none(), "no frame with holes: no figure");
    }
}
