"""Losses shared by the training stages."""

from __future__ import annotations

import torch


def gradient_difference(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
    """The gradient difference loss of Mathieu, Couprie & LeCun (2016, "Deep
    multi-scale video prediction beyond mean square error", eq. 5, alpha 1):
    mean |(|grad a|) - (|grad b|)| over both image axes. Where MSE alone
    settles for blur, this asks for edges as strong as the target's.
    `where` (N, 1, H, W, in [0, 1]): only pixel pairs it holds at both ends count."""
    dy = lambda x: x[..., 1:, :] - x[..., :-1, :]
    dx = lambda x: x[..., :, 1:] - x[..., :, :-1]
    if where is None:
        return (dy(a).abs() - dy(b).abs()).abs().mean() + (dx(a).abs() - dx(b).abs()).abs().mean()
    wy, wx = where[..., 1:, :] * where[..., :-1, :], where[..., :, 1:] * where[..., :, :-1]
    term = lambda d, w: ((d(a).abs() - d(b).abs()).abs() * w).sum() / (w.sum() * a.shape[1] + 1e-6)
    return term(dy, wy) + term(dx, wx)
