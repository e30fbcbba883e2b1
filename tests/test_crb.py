import math

import pytest
import torch

import torchspec as ts
from torchspec.start.fri import pulses

F64 = torch.float64


@pytest.mark.parametrize("kind,width", [("gaussian", 0.05), ("gaussian", 0.2236), ("lorentzian", 0.03), ("box", 0.3)])
@pytest.mark.parametrize("bands,n", [(2, 5), (8, 17), (7, 16)])
def test_closed_form_equals_autograd_fisher_1d(kind, width, bands, n):
    """With the location, the gain and every kernel coefficient unknown, the bound on the
    location equals the closed form: the kernel's amplitudes are orthogonal to the location."""
    a = pulses.spectrum(kind, torch.tensor(width, dtype=F64), bands)
    location, sigma = 0.37, 0.3

    def forward(params):  # params: location, then a_0..a_M (free real kernel spectrum)
        return pulses.sample(params[..., None, 1:], params[..., :1], num_samples=n)

    params = torch.cat([torch.tensor([location], dtype=F64), a])
    fisher = ts.model.crb.fisher_information(forward, params, sigma)
    numeric = ts.model.crb.bound(fisher)[0, 0]
    closed = ts.model.crb.location_1d(a, num_samples=n, noise_sigma=sigma)
    torch.testing.assert_close(numeric, closed, rtol=1e-10, atol=0)


def test_closed_form_equals_autograd_fisher_2d():
    spec = pulses.outer(pulses.spectrum("gaussian", torch.tensor(0.07, dtype=F64), 3),
                        pulses.spectrum("triangle", torch.tensor(0.1, dtype=F64), 2))
    sigma, shape = 0.2, (8, 5)

    def forward(params):  # location (2) and a gain
        return (params[..., 2:] * pulses.sample_2d(spec, params[..., :2], shape=shape).flatten(-2))

    params = torch.tensor([0.3, 0.8, 1.0], dtype=F64)
    numeric = ts.model.crb.bound(ts.model.crb.fisher_information(forward, params, sigma))[:2, :2]
    closed = ts.model.crb.location_2d(spec, num_samples=shape, noise_sigma=sigma)
    torch.testing.assert_close(numeric, closed, rtol=1e-10, atol=1e-18)


def test_closed_form_scales():
    a = pulses.spectrum("gaussian", torch.tensor(0.05, dtype=F64), 4)
    base = ts.model.crb.location_1d(a, num_samples=9, noise_sigma=1.0)
    torch.testing.assert_close(ts.model.crb.location_1d(a, num_samples=18, noise_sigma=2.0), 2 * base)
    torch.testing.assert_close(ts.model.crb.location_1d(a, num_samples=9, noise_sigma=1.0, period=3.0), 9 * base)
    batched = ts.model.crb.location_1d(a.expand(5, 5), num_samples=9, noise_sigma=torch.linspace(1, 2, 5, dtype=F64))
    assert batched.shape == (5,)


def test_fisher_information_batched_and_heteroscedastic():
    def forward(params):  # y_n = p0 + p1 * n, n = 0..3
        n = torch.arange(4, dtype=params.dtype)
        return params[..., :1] + params[..., 1:] * n

    params = torch.ones(6, 2, dtype=F64)
    sigma = torch.tensor([1.0, 2.0, 1.0, 0.5], dtype=F64)
    fisher = ts.model.crb.fisher_information(forward, params, sigma)
    design = torch.stack([torch.ones(4, dtype=F64), torch.arange(4, dtype=F64)], -1)
    expected = design.T @ torch.diag(1 / sigma**2) @ design
    assert fisher.shape == (6, 2, 2)
    torch.testing.assert_close(fisher, expected.expand(6, 2, 2))


def test_bound_of_a_singular_fisher_is_nan():
    assert bool(ts.model.crb.bound(torch.zeros(2, 2, dtype=F64)).isnan().all())


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda a: ts.model.crb.location_1d(a, num_samples=8, noise_sigma=1.0), r"num_samples must be >= 2M \+ 1 = 9"),
        (lambda a: ts.model.crb.location_1d(a, num_samples=9, noise_sigma=0.0), "noise_sigma must be > 0"),
        (lambda a: ts.model.crb.location_1d(a, num_samples=9, noise_sigma=1.0, period=-1.0), "period must be > 0"),
        (
            lambda a: ts.model.crb.location_2d(pulses.outer(a, a), num_samples=(9, 4), noise_sigma=1.0),
            r"num_samples\[1\]",
        ),
        (
            lambda a: ts.model.crb.fisher_information(lambda p: p, torch.tensor(1.0), 1.0),
            r"params must have shape \(\*, P\)",
        ),
    ],
)
def test_bad_calls(call, match):
    with pytest.raises(ValueError, match=match):
        call(pulses.spectrum("gaussian", torch.tensor(0.05, dtype=F64), 4))


def test_known_single_dirac_bound():
    """Blu et al. 2008: one Dirac through the Dirichlet kernel sin(pi B t) / (B sin(pi t)) of
    bandwidth B = 2M + 1 (tau = 1), N samples: std(x) >= sqrt(3B / (N (B^2 - 1))) / pi * sigma."""
    bands, n, sigma = 5, 15, 0.01
    b = 2 * bands + 1
    flat = torch.full((bands + 1,), 1.0 / b, dtype=F64)  # that kernel's coefficients
    std = math.sqrt(float(ts.model.crb.location_1d(flat, num_samples=n, noise_sigma=sigma)))
    assert std == pytest.approx(math.sqrt(3 * b / (n * (b * b - 1))) / math.pi * sigma, rel=1e-12)
