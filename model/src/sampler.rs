//! The DDPM schedule and the two samplers (respaced ancestral with the
//! posterior variance, and DDIM), exactly as the Python reference
//! (`model/python/worldpack_model/diffusion.py`): coefficients in f64, state
//! in f32, the model fed the original timestep indices.

use crate::error::ModelError;
use crate::manifest::DiffusionSpec;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    Ancestral,
    Ddim,
}

impl Method {
    /// As flags, manifests and saved results write it (the inverse of `from_str`).
    pub fn name(self) -> &'static str {
        match self {
            Method::Ancestral => "ancestral",
            Method::Ddim => "ddim",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "ancestral" => Ok(Method::Ancestral),
            "ddim" => Ok(Method::Ddim),
            _ => Err(format!("unknown sampler {s:?}; one of ancestral, ddim")),
        }
    }
}

/// A respaced sampler: step `i` feeds the model `timesteps[i]` (descending).
#[derive(Clone, Debug)]
pub struct Sampler {
    pub method: Method,
    pub eta: f64,
    pub timesteps: Vec<usize>,
    abar: Vec<f64>,
    abar_prev: Vec<f64>,
}

impl Sampler {
    pub fn new(schedule: &DiffusionSpec, steps: usize, method: Method, eta: f64) -> Result<Sampler, ModelError> {
        let total = schedule.timesteps;
        if !(1..=total).contains(&steps) {
            return Err(ModelError::input("steps", format!("must lie in 1..={total}, got {steps}")));
        }
        if !(0.0..=1.0).contains(&eta) {
            return Err(ModelError::input("eta", format!("must lie in [0, 1], got {eta}")));
        }

        let mut alphas_cumprod = Vec::with_capacity(total);
        let mut acc = 1.0f64;
        for i in 0..total {
            // numpy.linspace(beta_start, beta_end, total)
            let beta = if total == 1 {
                schedule.beta_start
            } else {
                schedule.beta_start + (schedule.beta_end - schedule.beta_start) * i as f64 / (total - 1) as f64
            };
            acc *= 1.0 - beta;
            alphas_cumprod.push(acc);
        }
        let (kept, method, eta) = match &schedule.distilled {
            // A student learned its own grid's jumps and nothing else: whatever
            // was asked, it runs them, by deterministic DDIM.
            Some(d) => (d.timesteps.clone(), Method::Ddim, 0.0),
            None => {
                // unique(round(linspace(0, total-1, steps))), round half to even as numpy does.
                let mut kept: Vec<usize> = (0..steps)
                    .map(|i| if steps == 1 { 0.0 } else { (total - 1) as f64 * i as f64 / (steps - 1) as f64 })
                    .map(|x| x.round_ties_even() as usize)
                    .collect();
                kept.dedup();
                kept.reverse();
                (kept, method, eta)
            }
        };
        let abar: Vec<f64> = kept.iter().map(|&t| alphas_cumprod[t]).collect();
        let abar_prev = (0..kept.len()).map(|i| if i + 1 < kept.len() { abar[i + 1] } else { 1.0 }).collect();
        Ok(Sampler { method, eta, timesteps: kept, abar, abar_prev })
    }

    pub fn len(&self) -> usize {
        self.timesteps.len()
    }

    /// Whether step `i` adds noise: never on the last step, nor in DDIM with eta 0.
    pub fn injects_noise(&self, i: usize) -> bool {
        i + 1 < self.len() && (self.method == Method::Ancestral || self.eta > 0.0)
    }

    pub fn is_empty(&self) -> bool {
        self.timesteps.is_empty()
    }

    /// The state after step `i`, from the state `x`, the model's `eps` and the
    /// injected noise `z` (unused on the last step).
    pub fn step(&self, i: usize, x: &[f32], eps: &[f32], z: &[f32]) -> Vec<f32> {
        let (ab, ab_prev) = (self.abar[i], self.abar_prev[i]);
        let last = i + 1 == self.len();
        let (noise_sd, signal) = ((1.0 - ab).sqrt() as f32, ab.sqrt() as f32);
        let x0 = x.iter().zip(eps).map(|(&x, &e)| (x - noise_sd * e) / signal);
        match self.method {
            Method::Ancestral => {
                let beta = 1.0 - ab / ab_prev;
                let c0 = (beta * ab_prev.sqrt() / (1.0 - ab)) as f32;
                let ct = ((1.0 - ab_prev) * (1.0 - beta).sqrt() / (1.0 - ab)) as f32;
                let sd = (beta * (1.0 - ab_prev) / (1.0 - ab)).sqrt() as f32;
                x0.zip(x).zip(z)
                    .map(|((x0, &x), &z)| c0 * x0 + ct * x + if last { 0.0 } else { sd * z })
                    .collect()
            }
            Method::Ddim => {
                let sigma = self.eta * ((1.0 - ab_prev) / (1.0 - ab) * (1.0 - ab / ab_prev)).sqrt();
                let a = ab_prev.sqrt() as f32;
                let b = (1.0 - ab_prev - sigma * sigma).max(0.0).sqrt() as f32;
                let s = sigma as f32;
                x0.zip(eps).zip(z)
                    .map(|((x0, &e), &z)| a * x0 + b * e + if last { 0.0 } else { s * z })
                    .collect()
            }
        }
    }
}
