import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.model.noise import affine_noise


def _pixels(a, b, n=2000, samples=150, params=7, seed=0, dtype=torch.float64):
    """Residual sums of squares of ``n`` fitted pixels under the noise ``a y + b``: chi^2 with
    ``samples - params`` degrees of freedom times the pixel's mean variance."""
    g = torch.Generator().manual_seed(seed)
    level = torch.exp(torch.empty(n, dtype=dtype).uniform_(math.log(0.01), math.log(5.0), generator=g))
    dof = samples - params
    chi2 = torch.randn(n, dof, generator=g, dtype=dtype).pow(2).sum(-1)
    sum_squares = chi2 * (a * level + b)
    count = torch.full((n,), samples, dtype=torch.long)
    return sum_squares, level * samples, count


@pytest.mark.parametrize(("a", "b"), [(1e-5, 0.0), (1e-4, 1e-6), (0.0, 4e-6), (2e-3, 1e-4)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_recovers_shot_and_read_noise(a, b, dtype):
    squares, values, count = _pixels(a, b, dtype=dtype)
    fa, fb = affine_noise(squares, values, count, 7)
    assert fa.dtype == dtype and fa.shape == () and fb.shape == ()
    # 2000 pixels of 143 degrees of freedom: the variance at any level within 2 %.
    level = torch.tensor([0.01, 0.1, 1.0, 5.0], dtype=torch.float64)
    true, fitted = a * level + b, float(fa) * level + float(fb)
    err = ((fitted - true) / true).abs().max()
    assert err < 0.02, f"relative error of the variance {err:.3g} (a {float(fa):.3g}, b {float(fb):.3g})"
    assert float(fa) >= 0 and float(fb) >= 0


def test_misfit_pixels_do_not_raise_the_noise():
    """A third of the pixels with a model that does not explain them (residual 2 to 100 times the
    noise) moves the fitted noise by less than 3 %."""
    squares, values, count = _pixels(1e-5, 1e-7, seed=1)
    g = torch.Generator().manual_seed(2)
    bad = torch.rand(squares.shape, generator=g, dtype=torch.float64) < 1 / 3
    factor = torch.exp(
        torch.empty(squares.shape, dtype=torch.float64).uniform_(math.log(2), math.log(100), generator=g)
    )
    squares = torch.where(bad, squares * factor, squares)
    fa, fb = affine_noise(squares, values, count, 7)
    level = torch.tensor([0.01, 1.0, 5.0], dtype=torch.float64)
    err = ((float(fa) * level + float(fb)) / (1e-5 * level + 1e-7) - 1).abs().max()
    assert err < 0.03, f"relative error {err:.3g}"


def test_unusable_pixels_are_left_out():
    squares, values, count = _pixels(1e-5, 0.0, n=500)
    squares[:10] = math.nan
    count[10:20] = 5  # no degree of freedom left with 7 parameters
    values[20:30] = math.inf
    fa, _ = affine_noise(squares, values, count, 7)
    assert abs(float(fa) / 1e-5 - 1) < 0.03, float(fa)
    zero = affine_noise(squares[:10], values[:10], count[:10], 7)
    assert float(zero[0]) == 0.0 and float(zero[1]) == 0.0


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.floats(1e-3, 1e3), st.integers(0, 10_000))
def test_variance_scales_with_the_residuals(k, seed):
    """Residuals ``k`` times larger (in variance) give ``k`` times the noise; recorded values
    ``k`` times larger give ``k`` times ``a`` and the same ``b``."""
    squares, values, count = _pixels(2e-5, 3e-7, n=300, seed=seed)
    a, b = affine_noise(squares, values, count, 7)
    ka, kb = affine_noise(k * squares, values, count, 7)
    torch.testing.assert_close(torch.stack([ka, kb]), k * torch.stack([a, b]), rtol=1e-6, atol=1e-300)
    # The same pixels at k times the level with k times a: the same variances.
    va, vb = affine_noise(squares, k * values, count, 7)
    torch.testing.assert_close(torch.stack([va * k, vb]), torch.stack([a, b]), rtol=1e-5, atol=1e-12)


def test_pixels_without_any_residual_say_nothing_of_the_noise():
    """All-zero pixels (a black border, padding) are fitted exactly: kept, they would pin the line to
    the origin and the read noise to 0."""
    generator = torch.Generator().manual_seed(0)
    n, k, variance = 96, 100, 1.88e-3
    x = torch.linspace(0.06, 0.25, n, dtype=torch.float64)
    squares = (torch.randn(n, k, generator=generator, dtype=torch.float64) ** 2).sum(-1) * variance
    zeros = torch.zeros(12, dtype=torch.float64)
    a, b = affine_noise(torch.cat([squares, zeros]), torch.cat([x * k, zeros]), torch.full((n + 12,), k), 3)
    clean = affine_noise(squares, x * k, torch.full((n,), k), 3)
    torch.testing.assert_close((a, b), clean)
    assert abs(float(a * 0.15 + b) / variance - 1) < 0.1
