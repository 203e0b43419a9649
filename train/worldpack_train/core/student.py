"""A distilled student's model: its timestep grid and the v-to-epsilon wrapper it is exported in."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .cdit import CDiT


def parse_grid(text: str, timesteps: int) -> list[int]:
    """'999,499' -> [999, 499]: strictly descending original indices, the first the last timestep."""
    try:
        grid = [int(x) for x in text.split(",")]
    except ValueError:
        raise SystemExit(f"--grid: comma-separated timestep indices, got {text!r}")
    if grid[0] != timesteps - 1 or any(a <= b for a, b in zip(grid, grid[1:])) or grid[-1] < 0:
        raise SystemExit(f"--grid: must start at {timesteps - 1} and descend strictly to a value >= 0, got {grid}")
    return grid


class EpsFromV(nn.Module):
    """A v-predicting CDiT seen as an epsilon-predicting one:
    eps = sqrt(1 - abar_t) x_t + sqrt(abar_t) v."""

    def __init__(self, model: CDiT, alphas_cumprod: np.ndarray):
        super().__init__()
        self.model, self.cfg = model, model.cfg
        self.register_buffer("alpha_bar", torch.tensor(alphas_cumprod, dtype=torch.float32), persistent=False)

    def forward(self, x_t, t, action, rel_time, groups, rates=None, warp=None):
        v = self.model(x_t, t, action, rel_time, groups, rates=rates, warp=warp)
        ab = self.alpha_bar[t.long()].view(-1, 1, 1, 1)
        return (1 - ab).sqrt() * x_t + ab.sqrt() * v
