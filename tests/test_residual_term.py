"""The residual term (torchspec.residual_term): its transfer and basis against closed forms, its fit
against brute-force least squares, its choice by left-out prediction, and its maps' round trip."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.errors import TorchspecError
from torchspec.io.images import Transfer
from torchspec.lights import Kernel, Lights
from torchspec.pipeline.prediction import light_folds
from torchspec.residual_term import ResidualTerm, decode, encode, fit_term, hsh_basis

D = torch.float64


def _dome(rows: int = 5, per_row: int = 12) -> torch.Tensor:
    """``(K, 3)`` directions on rings of elevation 15-75 degrees, azimuths shifted per ring."""
    out = []
    for r, elevation in enumerate(torch.linspace(15, 75, rows, dtype=D)):
        azimuth = torch.arange(per_row, dtype=D) * 2 * math.pi / per_row + r * 0.3
        e = torch.deg2rad(elevation)
        out.append(torch.stack([e.cos() * azimuth.cos(), e.cos() * azimuth.sin(), e.sin().expand(per_row)], -1))
    return torch.cat(out)


def _lights(directions: torch.Tensor, scale: float = 1.0) -> Lights:
    k = directions.shape[0]
    return Lights(directions, Kernel("point"), torch.full((k, 1), scale, dtype=D), torch.ones(k, dtype=D))


@given(st.floats(-50, 50, allow_nan=False))
@settings(max_examples=200, deadline=None)
def test_encode_decode_are_inverse_and_monotonic(value):
    v = torch.tensor([value, value + 1e-3], dtype=D)
    assert torch.allclose(decode(encode(v)), v, rtol=1e-12, atol=1e-14)
    assert float(encode(v)[1]) > float(encode(v)[0])


def test_encode_is_srgb_on_the_unit_interval():
    v = torch.linspace(0, 1, 1001, dtype=D)
    assert torch.allclose(encode(v), Transfer("srgb").encode(v), atol=1e-12)


def test_hsh_basis_is_orthonormal_on_the_hemisphere():
    # Gauss-Legendre in cos(theta) on [0, 1], uniform in phi: exact for these polynomials.
    x, w = (torch.from_numpy(a) for a in __import__("numpy").polynomial.legendre.leggauss(40))
    t, wt = (x.to(D) + 1) / 2, w.to(D) / 2
    phi = torch.arange(64, dtype=D) * 2 * math.pi / 64
    tt, pp = torch.meshgrid(t, phi, indexing="ij")
    s = (1 - tt**2).sqrt()
    d = torch.stack([s * pp.cos(), s * pp.sin(), tt], -1).reshape(-1, 3)
    weight = (wt[:, None] * torch.full_like(phi, 2 * math.pi / 64)).reshape(-1)
    for order, count in ((2, 4), (3, 9)):
        h = hsh_basis(d, order)
        assert h.shape == (d.shape[0], count)
        gram = (h * weight[:, None]).T @ h
        assert torch.allclose(gram, torch.eye(count, dtype=D), atol=1e-10)


def test_fit_recovers_a_smooth_term_and_keeps_it():
    torch.manual_seed(0)
    directions = _dome()
    lights = _lights(directions, scale=2.0)
    n, k, c = 30, directions.shape[0], 3
    model = 2.0 * (0.05 + torch.rand(n, k, c, dtype=D) * 0.3)
    truth = torch.randn(n, 9, c, dtype=D) * 0.02
    observed = ResidualTerm(truth, torch.ones(n, dtype=torch.bool)).apply(model, lights)
    valid = torch.ones(n, k, dtype=torch.bool)
    term = fit_term(observed, valid, model, lights, light_folds(directions, 5, False))
    assert bool(term.chosen.all())
    assert torch.allclose(term.coefficients, truth, atol=1e-6)
    assert torch.allclose(term.apply(model, lights), observed, atol=1e-8)


def test_fit_matches_brute_force_least_squares_with_masked_samples():
    torch.manual_seed(1)
    directions = _dome()
    lights = _lights(directions)
    n, k, c = 6, directions.shape[0], 1
    model = 0.2 + torch.rand(n, k, c, dtype=D) * 0.3
    truth = ResidualTerm(torch.randn(n, 9, c, dtype=D) * 0.03, torch.ones(n, dtype=torch.bool))
    observed = truth.apply(model, lights) + torch.randn(n, k, c, dtype=D) * 0.002
    valid = torch.rand(n, k) > 0.2
    term = fit_term(observed, valid, model, lights, light_folds(directions, 5, False), z=0.0, ridge=0.0)
    assert bool(term.chosen.all())
    basis = hsh_basis(directions)
    target = encode(observed) - encode(model)
    for p in range(n):
        rows = valid[p]
        expected = torch.linalg.lstsq(basis[rows], target[p, rows]).solution
        assert torch.allclose(term.coefficients[p], expected, atol=1e-9)


def test_noise_alone_is_not_given_a_term():
    torch.manual_seed(2)
    directions = _dome()
    lights = _lights(directions)
    n, k, c = 400, directions.shape[0], 3
    model = 0.1 + torch.rand(n, k, c, dtype=D) * 0.5
    sigma = 0.003
    observed = model + torch.randn(n, k, c, dtype=D) * sigma
    valid = torch.ones(n, k, dtype=torch.bool)
    term = fit_term(observed, valid, model, lights, light_folds(directions, 5, False), z=3.0)
    assert float(term.chosen.double().mean()) < 0.02  # z = 3: about 0.1 % by chance


def test_map_round_trip_and_a_bad_map():
    torch.manual_seed(3)
    coefficients = torch.randn(4, 5, 9, 3, dtype=D)
    coefficients[0, 0] = 0
    term = ResidualTerm(coefficients, coefficients.ne(0).any(-1).any(-1))
    back = ResidualTerm.from_map(term.to_map(), 3)
    assert torch.equal(back.coefficients, coefficients) and torch.equal(back.chosen, term.chosen)
    assert not bool(back.chosen[0, 0])
    with pytest.raises(TorchspecError, match="residual_term.exr: 26 channels"):
        ResidualTerm.from_map(torch.zeros(4, 5, 26), 3)


def test_unchosen_pixels_are_left_alone():
    directions = _dome()
    lights = _lights(directions)
    values = torch.rand(3, directions.shape[0], 3, dtype=D)
    term = ResidualTerm(torch.ones(3, 9, 3, dtype=D), torch.tensor([False, True, False]))
    out = term.apply(values, lights)
    assert torch.equal(out[0], values[0]) and torch.equal(out[2], values[2])
    assert not torch.allclose(out[1], values[1])


def test_a_fit_with_the_term_keeps_its_maps_and_relights_a_cast_shadow(tmp_path):
    """A simulated painting whose left columns fall in a cast shadow under the lights from the
    right: the term is fitted where it predicts left-out frames, the physical maps are those of the
    fit without it, and ``torchspec render`` of the written maps predicts the frames better with it."""
    from capture_cases import write_painting

    from torchspec.io import read_capture, write_capture
    from torchspec.pipeline import FitConfig, fit, write_fit
    from torchspec.relight import render_capture

    source = read_capture(write_painting(tmp_path / "painting", size=12, seed=4, grid=7, extent=0.7))
    frames = source.read_frames(dtype=torch.float64)
    lit_from_right = source.directions()[:, 0] > 0.25
    shadow = torch.ones_like(frames[0, 0])
    shadow[:, :4] = 0.35
    frames[lit_from_right] = frames[lit_from_right] * shadow
    capture = write_capture(tmp_path / "shadowed", source, frames.float())

    plain = fit(capture, config=FitConfig(residual_term=0, compile=False))
    termed = fit(capture, config=FitConfig(residual_term=3, compile=False))
    assert plain.term is None and termed.term is not None
    assert torch.equal(plain.svbrdf.normal, termed.svbrdf.normal)
    assert torch.equal(plain.svbrdf.diffuse, termed.svbrdf.diffuse)
    # The shadowed columns carry a term (a step in the light direction that a smooth term follows
    # only in part: not every pixel's left-out prediction gains), the others none.
    assert float(termed.term.chosen[:, :4].double().mean()) > 0.5
    assert float(termed.term.chosen[:, 4:].double().mean()) < 0.05
    assert termed.stats["residual_term_pixels"] == int(termed.term.chosen.sum())

    write_fit(tmp_path / "maps", termed)
    with_term = render_capture(tmp_path / "maps", capture.root, None)
    without = render_capture(tmp_path / "maps", capture.root, None, term=False)
    assert with_term["psnr_db"] > without["psnr_db"] + 1.0
    assert (tmp_path / "maps" / "residual_term.exr").exists() and (
        tmp_path / "maps" / "residual_term_base.exr"
    ).exists()
