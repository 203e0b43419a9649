//! The DDPM schedule and the samplers: respaced ancestral with the posterior
//! variance, and DDIM, exactly as the Python reference
//! (`train/worldpack_train/core/diffusion.py`), and DPM-Solver++(2M) (Lu et
//! al. 2022), which reaches the 10-step DDIM's frames in fewer model calls and
//! is the Rust sampler's alone (it only serves). Coefficients in f64, state in
//! f32, the model fed the original timestep indices.

use crate::error::ModelError;
use crate::manifest::DiffusionSpec;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    Ancestral,
    Ddim,
    /// DPM-Solver++(2M): second-order multistep on the probability-flow ODE,
    /// deterministic, on a trailing grid (`Sampler::new` says why).
    Dpm2m,
}

impl Method {
    /// As flags, manifests and saved results write it (the inverse of `from_str`).
    pub fn name(self) -> &'static str {
        match self {
            Method::Ancestral => "ancestral",
            Method::Ddim => "ddim",
            Method::Dpm2m => "dpm2m",
        }
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "ancestral" => Ok(Method::Ancestral),
            "ddim" => Ok(Method::Ddim),
            "dpm2m" => Ok(Method::Dpm2m),
            _ => Err(format!("unknown sampler {s:?}; one of ancestral, ddim, dpm2m")),
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
        if method == Method::Dpm2m && eta != 0.0 {
            return Err(ModelError::input("eta", format!("dpm2m is deterministic: eta must be 0, got {eta}")));
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
            // Trailing: from total-1 down in strides of total/steps, the last call
            // at timestep total/steps - 1 rather than 0. The evenly spread grid's
            // last call, at t = 0, is nearly an identity, and the jump before it
            // is too long for the second-order correction (it blows up).
            None if method == Method::Dpm2m => ((0..steps).map(|i| total - 1 - i * total / steps).collect(), method, eta),
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

    /// Whether step `i` adds noise: never on the last step, in DPM-Solver++,
    /// nor in DDIM with eta 0.
    pub fn injects_noise(&self, i: usize) -> bool {
        i + 1 < self.len() && (self.method == Method::Ancestral || (self.method == Method::Ddim && self.eta > 0.0))
    }

    pub fn is_empty(&self) -> bool {
        self.timesteps.is_empty()
    }

    /// The state after step `i`, from the state `x`, the model's `eps` and the
    /// injected noise `z` (unused on the last step). `history` carries the
    /// clean estimate from one step to the next, which DPM-Solver++(2M) reads
    /// and writes; start each sample with `None`.
    pub fn step(&self, i: usize, x: &[f32], eps: &[f32], z: &[f32], history: &mut Option<Vec<f32>>) -> Vec<f32> {
        let (ab, ab_prev) = (self.abar[i], self.abar_prev[i]);
        let last = i + 1 == self.len();
        let (noise_sd, signal) = ((1.0 - ab).sqrt() as f32, ab.sqrt() as f32);
        let x0 = x.iter().zip(eps).map(|(&x, &e)| (x - noise_sd * e) / signal);
        match self.method {
            Method::Dpm2m => self.dpm_solver_2m(i, x, x0.collect(), history),
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

    /// Half-log signal-to-noise ratio, the solver's time variable.
    fn lambda(abar: f64) -> f64 {
        0.5 * (abar / (1.0 - abar)).ln()
    }

    /// One DPM-Solver++(2M) step (Lu et al. 2022, algorithm 2): a first-order
    /// step (which is DDIM's) on a clean estimate extrapolated linearly, in
    /// lambda, through the previous step's. The first and the last step use
    /// the estimate as it is, the last returning it.
    fn dpm_solver_2m(&self, i: usize, x: &[f32], x0: Vec<f32>, history: &mut Option<Vec<f32>>) -> Vec<f32> {
        let (ab, ab_next) = (self.abar[i], self.abar_prev[i]);
        if i + 1 == self.len() {
            *history = None;
            return x0;
        }
        let h = Self::lambda(ab_next) - Self::lambda(ab);
        let d: Vec<f32> = match history.as_deref() {
            Some(prev) if i > 0 => {
                let r = (Self::lambda(ab) - Self::lambda(self.abar[i - 1])) / h;
                let (now, before) = ((1.0 + 0.5 / r) as f32, (0.5 / r) as f32);
                x0.iter().zip(prev).map(|(&a, &b)| now * a - before * b).collect()
            }
            _ => x0.clone(),
        };
        let keep = ((1.0 - ab_next) / (1.0 - ab)).sqrt() as f32;
        let towards = (ab_next.sqrt() * (1.0 - (-h).exp())) as f32;
        let out = x.iter().zip(&d).map(|(&x, &d)| keep * x + towards * d).collect();
        *history = Some(x0);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schedule() -> DiffusionSpec {
        DiffusionSpec { timesteps: 1000, beta_start: 1e-4, beta_end: 0.02, prediction: "epsilon".into(), distilled: None }
    }

    /// Samples from `x` with the exact noise prediction for data drawn from
    /// N(0, 1) (given x_t the clean frame's posterior mean is sqrt(abar) x_t,
    /// so eps = sqrt(1 - abar) x_t). `carry`: pass the history between steps;
    /// without it, DPM-Solver++(2M) is its first-order form, DDIM on its grid.
    fn sample_unit_gaussian(s: &Sampler, x: f32, carry: bool) -> f32 {
        let (mut state, mut history) = (vec![x], None);
        for i in 0..s.len() {
            let eps = [((1.0 - s.abar[i]).sqrt() as f32) * state[0]];
            if !carry {
                history = None;
            }
            state = s.step(i, &state, &eps, &[0.0], &mut history);
        }
        state[0]
    }

    /// For N(0, 1) data the probability-flow ODE holds x_t still (it is
    /// N(0, 1) at every t), so from x a grid's exact answer is the posterior
    /// mean at its last timestep, sqrt(abar_last) x.
    #[test]
    fn dpm_solver_2m_follows_the_ode_where_its_first_order_drifts() {
        for steps in [8, 10] {
            let s = Sampler::new(&schedule(), steps, Method::Dpm2m, 0.0).unwrap();
            assert_eq!((s.timesteps[0], s.timesteps[steps - 1]), (999, 1000 / steps - 1));
            assert!(!(0..steps).any(|i| s.injects_noise(i)));
            let exact = s.abar[steps - 1].sqrt() as f32;
            let first_order = sample_unit_gaussian(&s, 1.0, false);
            assert!((first_order - exact).abs() / exact > 0.1, "{steps} steps, first order: {first_order} against {exact}");
            let second_order = sample_unit_gaussian(&s, 1.0, true);
            assert!((second_order - exact).abs() / exact < 0.02, "{steps} steps: {second_order} against {exact}");
        }
    }

    #[test]
    fn dpm_solver_2m_is_deterministic_and_named() {
        let err = Sampler::new(&schedule(), 8, Method::Dpm2m, 0.5).unwrap_err();
        assert!(err.to_string().starts_with("eta:"), "{err}");
        assert_eq!("dpm2m".parse::<Method>().unwrap().name(), "dpm2m");
        assert!("dpm".parse::<Method>().unwrap_err().contains("dpm2m"));
    }
}
