"""DDPM schedule and the two reference samplers, in NumPy so that the torch-free
tests can run them against ONNX Runtime.

Schedule: 1000 steps, linear betas 1e-4..0.02; the model predicts epsilon.
Ancestral sampling uses the posterior variance beta-tilde (DiT's "fixed
small"); a respaced sampler keeps `steps` of the 1000 timesteps, recomputes
betas from the kept cumulative alphas, and feeds the model the *original*
timestep index. Coefficients are computed in float64 and applied to a float32
state, which is what the Rust sampler does too."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .config import DiffusionConfig


class Schedule:
    def __init__(self, cfg: DiffusionConfig):
        self.timesteps = cfg.timesteps
        self.betas = np.linspace(cfg.beta_start, cfg.beta_end, cfg.timesteps, dtype=np.float64)
        self.alphas_cumprod = np.cumprod(1.0 - self.betas)


def respaced_timesteps(total: int, steps: int) -> np.ndarray:
    """`steps` original indices spread evenly over [0, total-1], ascending, first 0 and last total-1."""
    if not 1 <= steps <= total:
        raise ValueError(f"steps must lie in 1..={total}, got {steps}")
    return np.unique(np.round(np.linspace(0, total - 1, steps)).astype(np.int64))


@dataclass
class Trace:
    """What a sampler did: `timesteps[k]` is the original index fed to the model at
    step k (descending), `x[0]` the start noise, `x[k+1]` the state after step k,
    `eps[k]` the model output and `noise[k]` the injected noise of step k."""

    timesteps: np.ndarray
    x: np.ndarray
    eps: np.ndarray
    noise: np.ndarray


EpsFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Sampler:
    """A respaced sampler: `steps` runs, step i feeds the model the original
    timestep `timesteps[i]` (descending) and moves the state one kept step down."""

    def __init__(self, schedule: Schedule, steps: int, method: str = "ancestral", eta: float = 0.0,
                 timesteps: list[int] | None = None):
        if method not in ("ancestral", "ddim"):
            raise ValueError(f"method must be ancestral or ddim, got {method!r}")
        self.method, self.eta = method, eta
        if timesteps is not None:  # a distilled model's own grid, descending
            if len(timesteps) != steps:
                raise ValueError(f"steps {steps} does not match the {len(timesteps)} given timesteps")
            self.timesteps = np.asarray(timesteps, dtype=np.int64)
        else:
            self.timesteps = respaced_timesteps(schedule.timesteps, steps)[::-1].copy()
        self.abar = schedule.alphas_cumprod[self.timesteps]
        self.abar_prev = np.concatenate([schedule.alphas_cumprod[self.timesteps[1:]], [1.0]])

    def __len__(self) -> int:
        return len(self.timesteps)

    def step(self, i: int, x: np.ndarray, eps: np.ndarray, z: np.ndarray) -> np.ndarray:
        """State after step i from state x, model output eps and injected noise z
        (ignored on the last step)."""
        ab, ab_prev = self.abar[i], self.abar_prev[i]
        f = np.float32
        x0 = (x - f(np.sqrt(1 - ab)) * eps) / f(np.sqrt(ab))
        if i == len(self) - 1:
            z = np.zeros_like(x)
        if self.method == "ancestral":
            beta = 1 - ab / ab_prev
            c0 = beta * np.sqrt(ab_prev) / (1 - ab)
            ct = (1 - ab_prev) * np.sqrt(1 - beta) / (1 - ab)
            var = beta * (1 - ab_prev) / (1 - ab)
            out = f(c0) * x0 + f(ct) * x + f(np.sqrt(var)) * z
        else:
            sigma = self.eta * np.sqrt((1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev))
            out = f(np.sqrt(ab_prev)) * x0 + f(np.sqrt(max(1 - ab_prev - sigma**2, 0.0))) * eps + f(sigma) * z
        return out.astype(np.float32)


def sample(eps_fn: EpsFn, schedule: Schedule, x_T: np.ndarray, steps: int, method: str = "ancestral",
           eta: float = 0.0, noise: np.ndarray | None = None, rng: np.random.Generator | None = None,
           timesteps: list[int] | None = None) -> Trace:
    """Runs `steps` denoising steps from `x_T` (float32). `eps_fn(x, t)` gets the
    batch and a float32 vector of original timestep indices. Injected noise,
    when given, has shape (steps, *x_T.shape) in the order the steps run; the
    last step never adds noise. `timesteps`: the descending grid a distilled
    model was trained on, instead of the respaced one."""
    sampler = Sampler(schedule, steps, method, eta, timesteps)
    if noise is None:
        rng = rng or np.random.default_rng(0)
        noise = rng.standard_normal((len(sampler), *x_T.shape)).astype(np.float32)
    noise = noise.astype(np.float32).copy()
    noise[-1] = 0.0
    x = x_T.astype(np.float32)
    xs, epss = [x], []
    for i, t in enumerate(sampler.timesteps):
        eps = eps_fn(x, np.full(x.shape[0], t, dtype=np.float32)).astype(np.float32)
        x = sampler.step(i, x, eps, noise[i])
        xs.append(x)
        epss.append(eps)
    return Trace(sampler.timesteps, np.stack(xs), np.stack(epss), noise)
