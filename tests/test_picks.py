"""Picks of a fixed size inside a solver step (:mod:`torchspec.lm.picks`): the pairs ``nonzero``
gives, padded; an overflow seen at the check and its steps taken again; and a solve under an
extended kernel equal to the one whose every pick is exact (``nonzero``, the picks before issue 36),
also when the capacities overflow at every check."""

import pytest
import torch
from pixel_cases import grid_lights, random_svbrdf
from torch import Tensor

import torchspec.lm.picks as picks
from torchspec.lm import LMConfig, bounded, solve
from torchspec.lm.picks import Capacities, fixed_pick, keep, pick_pairs
from torchspec.model.brdf import SVBRDF
from torchspec.model.diffuse import diffuse_integral
from torchspec.model.geometry import normalize
from torchspec.model.lights import Kernel, diffuse_directions
from torchspec.model.quadrature import QUADRATURES
from torchspec.model.registry import MODELS, get_model
from torchspec.model.rendering import render

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


@pytest.mark.parametrize("share", [0.0, 0.05, 0.3, 1.0])
def test_a_fixed_pick_is_nonzero_padded_with_other_pairs(share):
    g = torch.Generator().manual_seed(1)
    mask = torch.rand(13, 7, generator=g) < 0.2
    capacity = round(share * mask.numel())
    rows, cols, valid, count = fixed_pick(mask, capacity)
    expected = mask.nonzero()
    assert int(count) == expected.shape[0] and rows.shape == cols.shape == valid.shape == (capacity,)
    taken = min(capacity, expected.shape[0])
    assert torch.equal(torch.stack([rows, cols], -1)[:taken], expected[:taken])  # nonzero's order
    assert valid[:taken].all() and not valid[taken:].any()
    assert not mask[rows[taken:], cols[taken:]].any()  # the padding: other pairs ...
    assert len(set((rows * 7 + cols).tolist())) == capacity  # ... each once


def test_keep_writes_back_the_valid_rows_only():
    new, old = torch.ones(3, 2), torch.zeros(3, 2)
    assert torch.equal(keep(torch.tensor([True, False, True]), new, old), torch.tensor([[1.0, 1], [0, 0], [1, 1]]))
    assert keep(None, new, old) is new


def _tilted(count: int, tilt: float, seed: int = 3) -> SVBRDF:
    """``count`` pixels of :func:`random_svbrdf`, their normals tilted by about ``tilt`` (radians of slope)."""
    g = torch.Generator().manual_seed(seed)
    base = random_svbrdf(count, g)
    slope = tilt * torch.randn(count, 2, generator=g, dtype=F64)
    normal = normalize(torch.cat([slope, torch.ones(count, 1, dtype=F64)], -1))
    return SVBRDF(normal, base.diffuse, base.specular, base.roughness, base.rotation)


@pytest.mark.parametrize("clamp", ["exact", "fast"])
def test_the_diffuse_clamp_under_capacities_equals_nonzero_and_an_overflow_is_seen(clamp):
    lights = grid_lights(Kernel("gaussian", sigma=0.15), n=7, extent=0.9)
    normal = _tilted(30, 0.6).normal
    direction = diffuse_directions(lights)
    value, grad = diffuse_integral(normal, lights, direction, gradient=True, clamp=clamp)
    capacities = Capacities()
    capacities.evaluate(diffuse_integral, normal, lights, direction, exact=True)  # the first capacities
    running, overflowed = capacities.check(torch.tensor(1))
    assert (running, overflowed) == (1, False) and capacities.shares[("diffuse clamp", 0)] > 0
    picked = capacities.evaluate(lambda: diffuse_integral(normal, lights, direction, gradient=True, clamp=clamp))
    assert not capacities.check(torch.tensor(1))[1]
    torch.testing.assert_close(picked, (value, grad), rtol=1e-13, atol=1e-15)
    capacities.shares[("diffuse clamp", 0)] /= 2.0  # too few: seen at the check, the capacity raised
    capacities.evaluate(diffuse_integral, normal, lights, direction)
    assert capacities.check(torch.tensor(1))[1] and capacities.shares[("diffuse clamp", 0)] > 0


def test_a_pick_outside_a_solve_is_nonzero():
    mask = torch.tensor([[False, True], [True, True]])
    rows, cols, valid = pick_pairs(mask, "any")
    assert rows.tolist() == [0, 1, 1] and cols.tolist() == [1, 0, 1] and valid is None


def _toy(target: Tensor, centres: Tensor):
    """A residual function whose costly part, ``(x c - 1)^2`` where ``x c > 1``, is computed for
    its picks only (their count grows as ``x`` does): ``r = x c + relu(x c - 1)^2 - target``."""

    def fn(x: Tensor, index: Tensor):
        linear = x * centres  # (M, R)
        rows, cols, valid = pick_pairs(linear > 1.0, "toy")
        value, slope = linear, centres.expand_as(linear)
        if rows.shape[0]:
            excess = linear[rows, cols] - 1.0
            value = value.index_put((rows, cols), keep(valid, linear[rows, cols] + excess**2, value[rows, cols]))
            slope = slope.index_put((rows, cols), keep(valid, centres[0, cols] * (1 + 2 * excess), slope[rows, cols]))
        return value - target[index], slope[..., None]

    return fn


def _exact_picks(monkeypatch):
    """Every pick exact (``nonzero``), as before issue 36."""
    evaluate = Capacities.evaluate

    def exactly(self, function, *args, exact=False):
        return evaluate(self, function, *args, exact=True)

    monkeypatch.setattr(Capacities, "evaluate", exactly)


def test_the_solver_takes_the_steps_of_an_overflowed_pick_again(monkeypatch):
    centres = torch.linspace(0.1, 2.0, 40, dtype=F64)[None]
    x_true = torch.linspace(0.6, 1.8, 25, dtype=F64)[:, None]
    linear = x_true * centres
    target = linear + (linear - 1.0).clamp(min=0.0) ** 2
    x0 = torch.full_like(x_true, 0.2)  # no picks at the start: each step's count outgrows its capacity
    checks = []
    check = Capacities.check
    monkeypatch.setattr(Capacities, "check", lambda self, r: checks.append(check(self, r)) or checks[-1])
    for every in (1, 4):
        checks.clear()
        result = solve(_toy(target, centres), x0, config=LMConfig(check_every=every))
        assert any(over for _, over in checks), "no overflow: the test does not test the steps taken again"
        with monkeypatch.context() as m:
            _exact_picks(m)
            exact = solve(_toy(target, centres), x0, config=LMConfig(check_every=every))
        for name in ("params", "cost", "status", "iterations", "damping"):
            torch.testing.assert_close(getattr(result, name), getattr(exact, name), rtol=1e-13, atol=1e-15)
        torch.testing.assert_close(result.params, x_true, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("kernel", [Kernel("gaussian", sigma=0.15), Kernel("gaussian", domain="angular", sigma=0.1)])
@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_solve_under_an_extended_kernel_equals_the_one_with_exact_picks(name, kernel, monkeypatch):
    model = get_model(name)
    truth, lights = _tilted(10, 0.6), grid_lights(kernel, n=6, extent=0.9)
    quadrature = QUADRATURES["fit"]
    g = torch.Generator().manual_seed(5)
    packed = model.pack(truth)
    observed = render(model.unpack(packed, ("R", "G", "B")), lights, VIEW, quadrature=quadrature)
    observed = observed * (1.0 + 0.05 * torch.randn(observed.shape, generator=g, dtype=F64))
    weight = torch.ones(observed.shape[:2], dtype=F64)
    bounds = model.bounds(3)
    params = bounds.to_free((packed + 0.05 * torch.randn(packed.shape, generator=g, dtype=F64)).clamp(min=1e-3))
    fn = bounded(model.residuals(observed, weight, lights, VIEW, ("R", "G", "B"), quadrature=quadrature), bounds)
    config = LMConfig(max_iterations=8, check_every=2)
    counted = []
    pick = Capacities.pick

    def seen(self, mask, site):
        out = pick(self, mask, site)
        counted.append(0 if self.exact else int(out[2].sum()))  # valid pairs picked inside a step
        return out

    monkeypatch.setattr(Capacities, "pick", seen)
    results = {"capacities": solve(fn, params, config=config)}
    assert sum(counted) > 0, "no pair picked inside a step: the test does not test the capacities"
    with monkeypatch.context() as m:  # capacities that follow the last counts exactly: overflows
        m.setattr(picks, "HEADROOM", 1.0)
        m.setattr(picks, "DECAY", 0.0)
        m.setattr(picks, "SLACK", 0)
        checks, check = [], Capacities.check
        m.setattr(Capacities, "check", lambda self, running: checks.append(check(self, running)) or checks[-1])
        results["overflowing"] = solve(fn, params, config=config)
        assert any(over for _, over in checks), "no overflow: the test does not test the steps taken again"
    _exact_picks(monkeypatch)
    exact = solve(fn, params, config=config)
    for result in results.values():
        for field in ("params", "cost", "initial_cost", "status", "iterations", "damping"):
            torch.testing.assert_close(getattr(result, field), getattr(exact, field), rtol=1e-12, atol=1e-14)

