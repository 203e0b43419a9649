"""Losses shared by the training stages."""

import torch


def gradient_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The gradient difference loss of Mathieu, Couprie & LeCun (2016, "Deep
    multi-scale video prediction beyond mean square error", eq. 5, alpha 1):
    mean |(|grad a|) - (|grad b|)| over both image axes. Where MSE alone
    settles for blur, this asks for edges as strong as the target's."""
    dy = lambda x: (x[..., 1:, :] - x[..., :-1, :]).abs()
    dx = lambda x: (x[..., :, 1:] - x[..., :, :-1]).abs()
    return (dy(a) - dy(b)).abs().mean() + (dx(a) - dx(b)).abs().mean()
