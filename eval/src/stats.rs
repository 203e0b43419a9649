//! Summaries and intervals. Frames of one trajectory are strongly
//! correlated, so intervals resample whole trajectories (a cluster
//! bootstrap) rather than frames, which would claim far too much certainty.

use memory::rng::SplitMix64;
use serde::Serialize;

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
