//! Overlap estimated by counting sampled points.
//!
//! Both sampled estimators have the same shape: draw a set `S` of points
//! that stand for the query's view, then `o_i = |{p ∈ S : p seen by i}| / |S|`.
//! Keeping `S` explicit lets the greedy coverage policy remove covered points
//! round by round, as WorldMem does.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::frustum::Frustum;
use crate::rng::SplitMix64;

/// The paper's estimator: points uniform in the query frustum `V_t`, tested
/// against each candidate's frustum.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MonteCarlo {
    pub samples: usize,
    pub seed: u64,
}

impl Default for MonteCarlo {
    fn default() -> Self {
        MonteCarlo { samples: 10_000, seed: 0 }
    }
}

/// WorldMem's estimator: points uniform in a ball around the query camera,
/// kept where they pass the query's angular field-of-view test, tested
/// against each candidate's angular field of view (no near plane, no far
/// plane beyond the ball). Assumes a y-up world, as Minecraft's.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldMemBall {
    pub samples: usize,
    pub radius: f64,
    pub hfov_deg: f64,
    pub vfov_deg: f64,
    pub seed: u64,
    /// Reproduce WorldMem's sign slip: its FoV test reads the 5-D pitch as
    /// "positive looks up" while its camera matrix looks down. With this set,
    /// each camera's elevation is negated before the angular test.
    #[serde(default)]
    pub pitch_sign_quirk: bool,
}

impl Default for WorldMemBall {
    fn default() -> Self {
        WorldMemBall { samples: 10_000, radius: 30.0, hfov_deg: 105.0, vfov_deg: 75.0, seed: 0, pitch_sign_quirk: false }
    }
}

/// How a sample point is tested against a candidate view.
#[derive(Clone, Copy, Debug)]
enum Membership {
    Frustum,
    Angular { half_h: f64, half_v: f64, quirk: bool },
}

/// The sampled stand-in for the query's view.
#[derive(Clone, Debug)]
pub struct ViewSamples {
    points: Vec<DVec3>,
    membership: Membership,
}

impl ViewSamples {
    pub fn monte_carlo(query: &Frustum, params: &MonteCarlo) -> ViewSamples {
        let k = query.intrinsics();
        let (l, r, t, b) = k.edge_slopes();
        let (n3, f3) = (k.near.powi(3), k.far.powi(3));
        let mut rng = SplitMix64::new(params.seed);
        let points = (0..params.samples)
            .map(|_| {
                // Cross-sections grow as z², so depth has density ∝ z².
                let z = (n3 + rng.next_f64() * (f3 - n3)).cbrt();
                let x = (l + rng.next_f64() * (r - l)) * z;
                let y = (t + rng.next_f64() * (b - t)) * z;
                query.pose().camera_to_world(DVec3::new(x, y, z))
            })
            .collect();
        ViewSamples { points, membership: Membership::Frustum }
    }

    pub fn worldmem(query: &Frustum, params: &WorldMemBall) -> ViewSamples {
        let membership = Membership::Angular {
            half_h: params.hfov_deg.to_radians() / 2.0,
            half_v: params.vfov_deg.to_radians() / 2.0,
            quirk: params.pitch_sign_quirk,
        };
        let centre = query.pose().position();
        let mut rng = SplitMix64::new(params.seed);
        let mut points = Vec::with_capacity(params.samples);
        for _ in 0..params.samples {
            let r = params.radius * rng.next_f64().cbrt();
            let phi = std::f64::consts::TAU * rng.next_f64();
            let cos_theta = 1.0 - 2.0 * rng.next_f64();
            let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
            points.push(centre + r * DVec3::new(sin_theta * phi.cos(), sin_theta * phi.sin(), cos_theta));
        }
        let mut samples = ViewSamples { points, membership };
        samples.points.retain(|&p| samples_sees(membership, query, p));
        samples
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Whether `candidate` sees sample point `p`.
    pub fn sees(&self, candidate: &Frustum, p: DVec3) -> bool {
        samples_sees(self.membership, candidate, p)
    }

    /// Fraction of the samples that `candidate` sees; 0 when no sample is left.
    pub fn overlap(&self, candidate: &Frustum) -> f64 {
        if self.points.is_empty() {
            return 0.0;
        }
        let seen = self.points.iter().filter(|&&p| self.sees(candidate, p)).count();
        seen as f64 / self.points.len() as f64
    }

    /// Drops the samples that `candidate` sees (greedy coverage).
    pub fn remove_seen_by(&mut self, candidate: &Frustum) {
        let membership = self.membership;
        self.points.retain(|&p| !samples_sees(membership, candidate, p));
    }
}

fn samples_sees(membership: Membership, view: &Frustum, p: DVec3) -> bool {
    match membership {
        Membership::Frustum => view.contains(p, 0.0),
        Membership::Angular { half_h, half_v, quirk } => {
            let (cam_az, cam_el) = azimuth_elevation(view.pose().forward());
            let cam_el = if quirk { -cam_el } else { cam_el };
            let (az, el) = azimuth_elevation(p - view.pose().position());
            angle_gap(az, cam_az) < half_h && angle_gap(el, cam_el) < half_v
        }
    }
}

/// WorldMem's angles of a y-up world vector: azimuth `atan2(x, z)` and
/// elevation above the horizontal plane (positive up).
fn azimuth_elevation(v: DVec3) -> (f64, f64) {
    (v.x.atan2(v.z), v.y.atan2(v.x.hypot(v.z)))
}

/// Absolute angular difference folded into `[0, π]`.
fn angle_gap(a: f64, b: f64) -> f64 {
    let d = (a - b).abs() % std::f64::consts::TAU;
    if d > std::f64::consts::PI { std::f64::consts::TAU - d } else { d }
}
