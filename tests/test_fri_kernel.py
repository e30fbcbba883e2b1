"""``locate(..., kernel=...)`` and :func:`torchspec.start.fri.estimate_kernel`: the known (or pooled)
kernel's matched filter."""

import math

import pytest
import torch
from conftest import TOLERANCE, circular_error

import torchspec as ts
from torchspec.start.fri import pulses

F64 = torch.float64
KERNELS = [("gaussian", 0.05), ("gaussian", 0.2236), ("lorentzian", 0.03), ("box", 0.32), ("raised-cosine", 0.25)]


def _samples(kind, width, n, batch, *, snr_db=None, seed=0, gains=False):
    """1D lowpass samples of one pulse at random locations (float64), with random gains and
    offsets if ``gains``; white noise at ``snr_db`` (the mean square of the samples over the noise
    variance) if given. Returns ``(y, x, spectrum, bound)``."""
    g = torch.Generator().manual_seed(seed)
    a = pulses.spectrum(kind, torch.tensor(width, dtype=F64), (n - 1) // 2)
    x = torch.rand(batch, 1, dtype=F64, generator=g)
    gain = 0.5 + torch.rand(batch, 1, dtype=F64, generator=g) if gains else torch.ones(batch, 1, dtype=F64)
    offset = torch.randn(batch, 1, dtype=F64, generator=g) if gains else torch.zeros(batch, 1, dtype=F64)
    y = gain * pulses.sample(a, x, num_samples=n) + offset
    bound = None
    if snr_db is not None:
        sigma = (
            (gain * pulses.sample(a, x, num_samples=n)).pow(2).mean(-1, keepdim=True).div(10 ** (snr_db / 10)).sqrt()
        )
        y = y + sigma * torch.randn(y.shape, dtype=F64, generator=g)
        bound = ts.model.crb.location_1d(a, num_samples=n, noise_sigma=sigma[:, 0] / gain[:, 0])
    return y, x[:, 0], a, bound


@pytest.mark.parametrize("kind,width", KERNELS)
@pytest.mark.parametrize("n", [5, 16, 17])
def test_noise_free_1d_is_exact(kind, width, n, dtype, device):
    y, x, a, _ = _samples(kind, width, n, 32, gains=True)
    y = y.to(dtype=dtype, device=device)
    for kernel in (a, 3.0 * a, "pooled"):  # any scale
        result = ts.start.fri.locate(y, period=1.0, kernel=kernel)
        err = circular_error(result.position.double().cpu(), x).abs().max().item()
        assert err <= TOLERANCE[dtype], (
            f"{kind} N={n} kernel={kernel if isinstance(kernel, str) else 'true'}: {err:.3g}"
        )
        assert result.position.dtype == dtype and result.position.device == y.device


@pytest.mark.parametrize("shape", [(8, 8), (9, 6)])
def test_noise_free_2d_is_exact(shape, dtype):
    g = torch.Generator().manual_seed(3)
    bands = tuple((n - 1) // 2 for n in shape)
    a = pulses.outer(*(pulses.spectrum("gaussian", torch.tensor(0.15, dtype=F64), b) for b in bands))
    x = torch.rand(16, 2, dtype=F64, generator=g)
    y = pulses.sample_2d(a, x, shape=shape, period=(1.0, 1.0)).to(dtype)
    for kernel in (a, "pooled"):
        position = ts.start.fri.locate(y, period=(1.0, 1.0), kernel=kernel).position
        assert circular_error(position.double(), x).abs().max().item() <= TOLERANCE[dtype]


@pytest.mark.parametrize(
    "kind,width,n,tolerance", [("gaussian", 0.2236, 17, 1e-12), ("gaussian", 0.05, 5, 1e-12), ("box", 0.32, 9, 1e-6)]
)
def test_known_kernel_is_the_matched_filter_maximum(kind, width, n, tolerance):
    """With the kernel given, the position is the global maximum of the known-kernel likelihood
    ``h(x) = sum_m a_m Re(Y_m e^{i 2 pi m x})``: brute force on a dense float64 grid, polished by
    Newton to convergence. The fixed three Newton steps of ``locate`` leave at most ~1e-7 (a box
    kernel at 5 dB), far below the noise's ~1e-2."""
    y, _, a, _ = _samples(kind, width, n, 200, snr_db=5.0, seed=7)
    position = ts.start.fri.locate(y, period=1.0, kernel=a).position
    bands = (n - 1) // 2
    coefficients = torch.fft.rfft(y, dim=-1)[:, 1 : bands + 1] / n
    m = torch.arange(1, bands + 1, dtype=F64)
    grid = torch.linspace(0.0, 1.0, 20001, dtype=F64)[:-1]
    matched = ((a[1:] * coefficients)[:, :, None] * torch.exp(2j * math.pi * m[:, None] * grid)).real.sum(1)
    best = grid[matched.argmax(-1)]
    for _ in range(30):
        rotated = coefficients * torch.exp(2j * math.pi * m * best[:, None])
        slope = -(a[1:] * m * rotated.imag).sum(-1)
        curvature = -(a[1:] * m * m * rotated.real).sum(-1)
        best = best - slope / curvature / (2.0 * math.pi)
    assert circular_error(position, best).abs().max().item() < tolerance


def test_closed_form_with_one_coefficient():
    """M = 1: the known-kernel maximum likelihood is the phase of ``Y_1``, whatever the kernel's sign."""
    y, _, a, _ = _samples("gaussian", 0.1, 3, 50, snr_db=0.0, seed=2)
    closed = torch.remainder(-torch.angle(torch.fft.rfft(y, dim=-1)[:, 1]) / (2.0 * math.pi), 1.0)
    position = ts.start.fri.locate(y, period=1.0, kernel=a).position
    assert circular_error(position, closed).abs().max().item() < 1e-12


@pytest.mark.parametrize("kind,width,n", [("gaussian", 0.2236, 17), ("gaussian", 0.05, 17), ("box", 0.32, 9)])
def test_estimate_kernel_recovers_a_known_kernel(kind, width, n):
    a = pulses.spectrum(kind, torch.tensor(width, dtype=F64), (n - 1) // 2)
    unit = a[1:] / a[1:].norm()
    clean, _, _, _ = _samples(kind, width, n, 64, gains=True, seed=1)
    exact = ts.start.fri.estimate_kernel(clean, period=1.0)
    assert exact[0] == 0 and torch.allclose(exact[1:], unit, atol=1e-12)
    # 20 dB: the noise per coefficient is ~0.1 / sqrt(N) of the pulse, so over 4000 problems the
    # pooled spectrum's error is ~2e-3 of its norm.
    noisy, _, _, _ = _samples(kind, width, n, 4000, snr_db=20.0, gains=True, seed=2)
    error = (ts.start.fri.estimate_kernel(noisy, period=1.0)[1:] - unit).abs().max().item()
    assert error < 0.01, f"{kind}: max error {error:.3g}"


def test_estimate_kernel_2d_layout_and_edge_cases():
    a = pulses.outer(*(pulses.spectrum("gaussian", torch.tensor(0.1, dtype=F64), b) for b in (3, 2)))
    x = torch.rand(40, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    y = pulses.sample_2d(a, x, shape=(7, 5), period=(1.0, 1.0))
    estimate = ts.start.fri.estimate_kernel(y, period=(1.0, 1.0))
    assert estimate.shape == (7, 5) and estimate[3, 2] == 0
    truth = a.clone()
    truth[3, 2] = 0.0
    truth = truth / (truth.norm() / math.sqrt(2.0))  # unit norm over one half-plane
    assert torch.allclose(estimate, truth, atol=1e-12)
    empty = ts.start.fri.estimate_kernel(torch.zeros(0, 9, dtype=F64), period=1.0)
    assert torch.equal(empty, torch.zeros(5, dtype=F64))
    nan = torch.full((3, 9), math.nan, dtype=F64)
    assert torch.equal(ts.start.fri.estimate_kernel(nan, period=1.0), torch.zeros(5, dtype=F64))
    for empty in (torch.zeros(0, 9, dtype=F64), nan, torch.ones(3, 9, dtype=F64)):  # nothing to pool
        pooled, alone = ts.start.fri.locate(empty, period=1.0, kernel="pooled"), ts.start.fri.locate(empty, period=1.0)
        assert torch.equal(pooled.position, alone.position) or bool(pooled.position.isnan().all())
        assert torch.equal(pooled.quality, alone.quality)
    mixed = torch.cat(
        [nan, pulses.sample(pulses.spectrum("gaussian", torch.tensor(0.1, dtype=F64), 4), x[:8, :1], num_samples=9)]
    )
    assert torch.isfinite(ts.start.fri.estimate_kernel(mixed, period=1.0)).all()


def test_pooled_kernel_is_near_the_bound_where_the_default_is_not():
    """The paper's variance-0.05 kernel at M = 8 and 10 dB (issue 23): the per-problem envelope
    costs ~14 % over the bound there; the pooled kernel ~3 % (experiments/fig2_crb.py)."""
    y, x, _, bound = _samples("gaussian", 0.2236, 17, 4000, snr_db=10.0, seed=11)
    ratio = {
        kernel: circular_error(ts.start.fri.locate(y, period=1.0, kernel=kernel).position, x).pow(2).mean().item()
        / bound.mean().item()
        for kernel in (None, "pooled")
    }
    assert ratio["pooled"] < 1.08 and ratio["pooled"] < ratio[None] - 0.05, ratio


def test_std_and_quality_with_a_kernel():
    y, x, a, _ = _samples("gaussian", 0.05, 17, 4000, snr_db=20.0, seed=5)
    result = ts.start.fri.locate(y, period=1.0, kernel=a)
    rms_error = circular_error(result.position, x).pow(2).mean().sqrt().item()
    rms_std = result.std.pow(2).mean().sqrt().item()
    assert 0.85 < rms_error / rms_std < 1.15, f"rms error {rms_error:.3g} vs predicted {rms_std:.3g}"
    assert float(result.quality.median()) > 0.9
    noise = ts.start.fri.locate(
        torch.randn(500, 17, dtype=F64, generator=torch.Generator().manual_seed(4)), period=1.0, kernel=a
    )
    assert float(noise.quality.median()) < 0.2


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(period=1.0, kernel=torch.ones(5, dtype=F64)), r"kernel must have shape \(K \+ 1,\) with K >= 7"),
        (dict(period=1.0, kernel=torch.ones(3, 9, dtype=F64)), "kernel must have shape"),
        (dict(period=(1.0, 1.0), kernel=torch.ones(9, dtype=F64)), r"\(2 K1 \+ 1, 2 K2 \+ 1\)"),
        (dict(period=1.0, kernel=[1.0] * 8), "kernel must be a real floating tensor"),
        (dict(period=1.0, kernel="mean"), "kernel must be a real floating tensor"),
        (dict(period=1.0, kernel=torch.ones(8, dtype=torch.int64)), "real floating tensor"),
        (dict(period=1.0, kernel=torch.zeros(8, dtype=F64)), "not all zero"),
        (dict(period=1.0, kernel=torch.full((8,), math.nan, dtype=F64)), "finite"),
        (dict(period=1.0, kernel=torch.ones(8, dtype=F64), method="ls"), "kernel is used by method 'coherent'"),
    ],
)
def test_bad_kernels_name_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ts.start.fri.locate(torch.rand(4, 16, dtype=F64), **kwargs)
