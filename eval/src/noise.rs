//! Pose noise as a robot's odometry or SLAM would add it, and how much a
//! policy's selection changes under it (DESIGN §9: pose noise changes the
//! ranking).
//!
//! A noisy trajectory keeps its true frames but *believes* other poses:
//! selection, the model's relative-pose conditioning and the depth warp all
//! see the believed ones, as a deployed system would.

use glam::{DMat3, DVec3};
use memory::rng::SplitMix64;
use memory::{ContextPlan, Frustum, FrameMemory, MemoryFrame, Policy, Pose};
use serde::{Deserialize, Serialize};

/// How the believed poses differ from the true ones.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum PoseNoise {
    /// Independent per frame: each position axis gets N(0, σ_t²) blocks, and
    /// the orientation turns about a random axis by |N(0, σ_r²)| degrees per axis
    /// (a rotation vector with N(0, σ_r²) components).
    Independent { translation: f64, rotation_deg: f64 },
    /// Random-walk odometry: each step's motion is measured with the
    /// independent error above, and errors accumulate along the trajectory
    /// (dead reckoning), so the drift grows like √t.
    Drift { translation: f64, rotation_deg: f64 },
}

/// A standard normal draw (Box–Muller).
fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u = 1.0 - rng.next_f64(); // (0, 1]: the log is finite
    SplitMix64::box_muller(u, rng.next_f64()).0
}

fn random_rotation(rng: &mut SplitMix64, sigma_rad: f64) -> DMat3 {
    let rvec = DVec3::new(gaussian(rng), gaussian(rng), gaussian(rng)) * sigma_rad;
    let angle = rvec.length();
    if angle == 0.0 { DMat3::IDENTITY } else { DMat3::from_axis_angle(rvec / angle, angle) }
}

/// The believed poses for `truth` under `noise`, deterministic in `seed`.
/// Frame 0 is believed exactly (odometry starts from a known pose).
pub fn apply(truth: &[Pose], noise: PoseNoise, seed: u64) -> Vec<Pose> {
    let mut rng = SplitMix64::new(seed);
    let mut out: Vec<Pose> = Vec::with_capacity(truth.len());
    for (t, p) in truth.iter().enumerate() {
        let believed = match noise {
            _ if t == 0 => *p,
            PoseNoise::Independent { translation, rotation_deg } => {
                let dp = DVec3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng)) * translation;
                let dr = random_rotation(&mut rng, rotation_deg.to_radians());
                Pose::new(dr * p.rotation(), p.position() + dp).expect("finite noise keeps a pose valid")
            }
            PoseNoise::Drift { translation, rotation_deg } => {
                // The true step in the previous camera's frame, measured with error,
                // then chained onto the previous believed pose.
                let step = p.relative_to(&truth[t - 1]);
                let dp = DVec3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng)) * translation;
                let dr = random_rotation(&mut rng, rotation_deg.to_radians());
                let measured_r = dr * step.rotation();
                let measured_p = step.position() + dp;
                let prev = out[t - 1];
                Pose::new(prev.rotation() * measured_r, prev.camera_to_world(measured_p)).expect("finite noise keeps a pose valid")
            }
        };
        out.push(believed);
    }
    out
}

/// Mean distance and mean angle (degrees) between believed and true poses.
pub fn pose_error(truth: &[Pose], believed: &[Pose]) -> (f64, f64) {
    let n = truth.len().max(1) as f64;
    let d: f64 = truth.iter().zip(believed).map(|(a, b)| a.position().distance(b.position())).sum();
    let r: f64 = truth.iter().zip(believed).map(|(a, b)| memory::stability::rotation_angle(a, b).to_degrees()).sum();
    (d / n, r / n)
}

/// `|A ∩ B| / |A ∪ B|` of two id sets; 1 when both are empty.
pub fn jaccard(a: &[u64], b: &[u64]) -> f64 {
    let common = a.iter().filter(|x| b.contains(x)).count();
    let union = a.len() + b.len() - common;
    if union == 0 { 1.0 } else { common as f64 / union as f64 }
}

/// Ranks 1..n with ties sharing their mean rank.
fn ranks(x: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..x.len()).collect();
    order.sort_by(|&i, &j| x[i].total_cmp(&x[j]));
    let mut r = vec![0.0; x.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && x[order[j + 1]] == x[order[i]] {
            j += 1;
        }
        let mean = (i + j) as f64 / 2.0 + 1.0;
        for &k in &order[i..=j] {
            r[k] = mean;
        }
        i = j + 1;
    }
    r
}

/// Spearman's ρ with tied ranks averaged; `None` when either side is constant.
pub fn spearman(x: &[f64], y: &[f64]) -> Option<f64> {
    let (rx, ry) = (ranks(x), ranks(y));
    let n = rx.len() as f64;
    let mean = (n + 1.0) / 2.0;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in rx.iter().zip(&ry) {
        sxy += (a - mean) * (b - mean);
        sxx += (a - mean).powi(2);
        syy += (b - mean).powi(2);
    }
    (sxx > 0.0 && syy > 0.0).then(|| sxy / (sxx * syy).sqrt())
}

/// The ids of a plan in rank order.
fn ids(plan: &ContextPlan) -> Vec<u64> {
    plan.selected().map(|(_, f)| f.id).collect()
}

/// Rank agreement of two plans: over every frame either one selected,
/// Spearman's ρ between the positions in the two rankings, a frame that a
/// plan left out counting as tied last there. 1 for the same order, about
/// −1 for disjoint sets; `None` when it is undefined (fewer than two frames).
pub fn rank_agreement(a: &ContextPlan, b: &ContextPlan) -> Option<f64> {
    let (a, b) = (ids(a), ids(b));
    let mut union = a.clone();
    union.extend(b.iter().filter(|x| !a.contains(x)));
    let position = |list: &[u64], id: u64| list.iter().position(|&x| x == id).unwrap_or(list.len()) as f64;
    let pa: Vec<f64> = union.iter().map(|&id| position(&a, id)).collect();
    let pb: Vec<f64> = union.iter().map(|&id| position(&b, id)).collect();
    spearman(&pa, &pb)
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Agreement {
    pub t: usize,
    pub jaccard: f64,
    pub rank: Option<f64>,
}

/// For each target, how much `policy`'s selection from `believed` frusta
/// agrees with its selection from the `truth` frusta (frame `t` chooses
/// among frames `0..t`).
pub fn selection_agreement(policy: &Policy, truth: &[Frustum], believed: &[Frustum], targets: &[usize]) -> Vec<Agreement> {
    let (mut a, mut b) = (FrameMemory::new(), FrameMemory::new());
    let mut out = Vec::with_capacity(targets.len());
    let mut next = targets.iter().peekable();
    for t in 0..truth.len().min(believed.len()) {
        if next.peek() == Some(&&t) {
            next.next();
            let (pa, _) = a.select(policy, &truth[t], None);
            let (pb, _) = b.select(policy, &believed[t], None);
            out.push(Agreement { t, jaccard: jaccard(&ids(&pa), &ids(&pb)), rank: rank_agreement(&pa, &pb) });
        }
        if next.peek().is_none() {
            break;
        }
        let frame = |f: &Frustum| MemoryFrame { id: t as u64, time: t as u64, frustum: f.clone() };
        a.insert(frame(&truth[t])).expect("ids are new and increasing");
        b.insert(frame(&believed[t])).expect("ids are new and increasing");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spearman_of_known_orders() {
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[10.0, 20.0, 30.0]), Some(1.0));
        assert!((spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]).unwrap() + 1.0).abs() < 1e-12);
        assert_eq!(spearman(&[1.0, 1.0], &[1.0, 2.0]), None);
        // Ties take their mean rank: x ranks (1.5, 1.5, 3).
        let r = spearman(&[5.0, 5.0, 9.0], &[1.0, 2.0, 3.0]).unwrap();
        assert!((r - 0.866_025_403_784_438_6).abs() < 1e-12, "{r}");
    }

    #[test]
    fn jaccard_of_known_sets() {
        assert_eq!(jaccard(&[1, 2, 3], &[2, 3, 4]), 0.5);
        assert_eq!(jaccard(&[], &[]), 1.0);
        assert_eq!(jaccard(&[1], &[2]), 0.0);
    }

    #[test]
    fn zero_noise_believes_the_truth() {
        let truth: Vec<Pose> = (0..20).map(|i| Pose::from_position(DVec3::new(i as f64, 0.0, 0.5 * i as f64))).collect();
        for noise in [PoseNoise::Independent { translation: 0.0, rotation_deg: 0.0 }, PoseNoise::Drift { translation: 0.0, rotation_deg: 0.0 }] {
            let (d, r) = pose_error(&truth, &apply(&truth, noise, 3));
            assert!(d < 1e-9 && r < 1e-6, "{noise:?}: {d} {r}");
        }
    }

    #[test]
    fn independent_noise_has_the_asked_spread_and_drift_grows() {
        let truth: Vec<Pose> = (0..4001).map(|i| Pose::from_position(DVec3::new(i as f64 * 0.5, 0.0, 0.0))).collect();
        let noisy = apply(&truth, PoseNoise::Independent { translation: 0.2, rotation_deg: 0.0 }, 1);
        // E|N(0, σ² I₃)| = σ·2√(2/π) ≈ 1.596 σ.
        let (d, _) = pose_error(&truth, &noisy);
        assert!((d / 0.2 - 1.596).abs() < 0.05, "mean error {d}");
        let drift = apply(&truth, PoseNoise::Drift { translation: 0.01, rotation_deg: 0.0 }, 1);
        let err = |t: usize| truth[t].position().distance(drift[t].position());
        let early: f64 = (90..110).map(err).sum::<f64>() / 20.0;
        let late: f64 = (3900..4000).map(err).sum::<f64>() / 100.0;
        assert!(late > 3.0 * early, "drift does not grow: {early} then {late}");
    }
}
