import math

import pytest
import torch

from torchspec.start.fri import pulses

F64 = torch.float64


@pytest.mark.parametrize("kind", pulses.KINDS)
def test_spectrum_matches_numerical_fourier_series(kind):
    """a_m against a brute-force Fourier series of the periodised kernel."""
    width, period, bands = 0.08, 1.3, 6
    dt, half = 1e-4, 400  # the box's edges, +-width / 2, fall on grid points: trapezoid rule there
    k = torch.arange(-520000, 520001)
    t = k.to(F64) * dt
    if kind == "gaussian":
        p = torch.exp(-t**2 / (2 * width**2)) / (width * math.sqrt(2 * math.pi))
    elif kind == "lorentzian":
        p = (width / math.pi) / (t**2 + width**2)
    elif kind == "box":
        p = ((k.abs() < half).to(F64) + 0.5 * (k.abs() == half).to(F64)) / width
    elif kind == "triangle":
        p = (1 - t.abs() / width).clamp(min=0) / width
    else:
        p = torch.where(t.abs() < width / 2, (1 + torch.cos(2 * math.pi * t / width)) / width, 0.0)
    m = torch.arange(bands + 1, dtype=F64)
    numeric = (p * torch.cos(2 * math.pi * m[:, None] * t / period)).sum(-1) * dt / period
    tol = 2e-3 if kind == "lorentzian" else 1e-4  # the Lorentzian's tails outlive the window
    torch.testing.assert_close(pulses.spectrum(kind, torch.tensor(width, dtype=F64), bands, period=period),
                               numeric, rtol=tol, atol=tol / period)


def test_samples_are_the_truncated_series():
    a = pulses.spectrum("gaussian", torch.tensor([0.05, 0.1], dtype=F64), 4)  # (2, M + 1)
    x = torch.tensor([0.2, 0.7], dtype=F64)
    y = pulses.sample(a[:, None, :], x[:, None], num_samples=9)
    t = torch.arange(9, dtype=F64) / 9
    m = torch.arange(1, 5, dtype=F64)
    expected = a[:, :1] + 2 * (a[:, None, 1:] * torch.cos(2 * math.pi * m * (t[:, None] - x[:, None, None]))).sum(-1)
    torch.testing.assert_close(y, expected)


def test_sample_2d_grid_equals_scattered():
    spec = pulses.outer(pulses.spectrum("gaussian", torch.tensor(0.1, dtype=F64), 2),
                        pulses.spectrum("box", torch.tensor(0.2, dtype=F64), 3))
    x = torch.tensor([0.3, 0.6], dtype=F64)
    grid = pulses.sample_2d(spec, x, shape=(5, 7), period=(1.0, 2.0))
    t1, t2 = torch.meshgrid(torch.arange(5, dtype=F64) / 5, 2 * torch.arange(7, dtype=F64) / 7, indexing="ij")
    scattered = pulses.sample_2d(spec, x, positions=torch.stack([t1, t2], -1).reshape(-1, 2), period=(1.0, 2.0))
    torch.testing.assert_close(grid.reshape(-1), scattered)


def test_bad_calls():
    with pytest.raises(ValueError, match="kind must be one of"):
        pulses.spectrum("cauchy", torch.tensor(0.1), 3)
    with pytest.raises(TypeError, match="width must be a tensor"):
        pulses.spectrum("gaussian", 0.1, 3)
    with pytest.raises(ValueError, match="period must be > 0"):
        pulses.spectrum("gaussian", torch.tensor(0.1), 3, period=0.0)
    with pytest.raises(ValueError, match="exactly one of num_samples and positions"):
        pulses.sample(torch.ones(3), torch.zeros(1))
