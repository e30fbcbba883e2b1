"""The residual term (torchspec.model.residual_term): its transfer and basis against closed forms, its fit
against brute-force least squares, its choice by left-out prediction, and its maps' round trip."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.calibration.response import ResponseCurve
from torchspec.errors import TorchspecError
from torchspec.io.images import Transfer
from torchspec.model.lights import Kernel, Lights
from torchspec.model.residual_term import ResidualTerm, TermDomain, blend, decode, encode, fit_term, hsh_basis
from torchspec.pipeline.prediction import light_folds

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


FILM = ResponseCurve(gamma=(1.3, 2.2, 0.8), offset=(0.0, 0.055, 0.3), contrast=(5.0, -4.0, 0.0))


@given(st.floats(-20, 20, allow_nan=False), st.integers(0, 2))
@settings(max_examples=200, deadline=None)
def test_a_response_domain_is_a_monotonic_bijection_of_the_reals(value, channel):
    domain = TermDomain(FILM)
    v = torch.zeros(2, 3, dtype=D)
    v[:, channel] = torch.tensor([value, value + 1e-3], dtype=D)
    e = domain.encode(v)
    assert torch.allclose(domain.decode(e), v, rtol=1e-9, atol=1e-11)
    assert float(e[1, channel]) > float(e[0, channel])


def test_a_response_domain_is_the_curve_inside_and_its_tangent_outside():
    domain = TermDomain(FILM)
    codes = torch.linspace(0, 1, 201, dtype=D)[:, None].expand(-1, 3)
    assert torch.allclose(domain.decode(codes), FILM.decode(codes), atol=1e-14)
    assert torch.allclose(domain.encode(FILM.decode(codes)), codes, atol=1e-9)
    # continued along the slope at code 1 (a finite difference of the curve there) and odd below 0
    h = 1e-6
    slope = (FILM.decode(torch.ones(1, 3, dtype=D)) - FILM.decode(torch.full((1, 3), 1 - h, dtype=D))) / h
    above = domain.decode(torch.full((1, 3), 1.5, dtype=D))
    assert torch.allclose(above, 1 + 0.5 * slope, rtol=1e-5)
    assert torch.allclose(domain.decode(-codes), -domain.decode(codes))
    assert torch.equal(TermDomain().encode(codes), encode(codes))  # no curve: sRGB, as before
    assert TermDomain.from_json(TermDomain(FILM).to_json()) == TermDomain(FILM)
    assert TermDomain.from_json(None) == TermDomain() == TermDomain.from_json({"transfer": "srgb"})
    with pytest.raises(TorchspecError, match="maps.json: transfer must be srgb or response; got 'gamma'"):
        TermDomain.from_json({"transfer": "gamma"}, "maps.json")


def test_a_term_in_the_photographs_encoding_is_recovered_there_and_not_in_srgb():
    """Photographs whose codes are a film curve of the values: a term added in those codes is
    fitted back exactly in them; fitted in sRGB units it is not (the slopes differ)."""
    torch.manual_seed(4)
    directions = _dome()
    lights = _lights(directions)
    n, k, c = 20, directions.shape[0], 3
    model = 0.05 + torch.rand(n, k, c, dtype=D) * 0.6
    truth = ResidualTerm(torch.randn(n, 9, c, dtype=D) * 0.02, torch.ones(n, dtype=torch.bool), domain=TermDomain(FILM))
    observed = truth.apply(model, lights)
    valid = torch.ones(n, k, dtype=torch.bool)
    folds = light_folds(directions, 5, False)
    term = fit_term(observed, valid, model, lights, folds, ridge=0.0, domain=TermDomain(FILM))
    assert bool(term.chosen.all()) and term.domain == TermDomain(FILM)
    assert torch.allclose(term.coefficients, truth.coefficients, atol=1e-6)
    assert torch.allclose(term.apply(model, lights), observed, atol=1e-8)
    in_srgb = fit_term(observed, valid, model, lights, folds)
    assert float((in_srgb.apply(model, lights) - observed).abs().max()) > 1e-3
    mapped = ResidualTerm.from_map(term.to_map()[None], c, encoding=term.description()["encoding"])  # (1, n, C J)
    assert mapped.domain == TermDomain(FILM)


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
    right, fitted on 4 of every 5 frames: the term is fitted where it predicts left-out frames, the
    physical maps are those of the fit without it, and ``torchspec render`` of the written maps
    predicts the frames left out of the fit better with it."""
    from capture_cases import write_painting

    from torchspec.io import read_capture, write_capture
    from torchspec.pipeline import FitConfig, QuadratureConfig, TermConfig, fit, write_fit
    from torchspec.relight import render_capture

    source = read_capture(write_painting(tmp_path / "painting", size=12, seed=4, grid=7, extent=0.7))
    frames = source.read_frames(dtype=torch.float64)
    lit_from_right = source.directions()[:, 0] > 0.25
    shadow = torch.ones_like(frames[0, 0])
    shadow[:, :4] = 0.35
    frames[lit_from_right] = frames[lit_from_right] * shadow
    capture = write_capture(tmp_path / "shadowed", source, frames.float())
    left_out = torch.arange(frames.shape[0]) % 5 == 2
    fitted = (~left_out).nonzero()[:, 0].tolist()

    uncompiled = QuadratureConfig(compile=False)
    plain = fit(capture, config=FitConfig(term=TermConfig(order=0), quadrature=uncompiled), frames=fitted)
    termed = fit(capture, config=FitConfig(term=TermConfig(order=3), quadrature=uncompiled), frames=fitted)
    assert plain.term is None and termed.term is not None
    assert torch.equal(plain.svbrdf.normal, termed.svbrdf.normal)
    assert torch.equal(plain.svbrdf.diffuse, termed.svbrdf.diffuse)
    # The shadowed columns carry a term (a step in the light direction that a smooth term follows
    # only in part: not every pixel's left-out prediction gains), the others none.
    assert float(termed.term.chosen[:, :4].double().mean()) > 0.5
    assert float(termed.term.chosen[:, 4:].double().mean()) < 0.05
    assert termed.stats["residual_term_pixels"] == int(termed.term.chosen.sum())

    write_fit(tmp_path / "maps", termed)
    assert (tmp_path / "maps" / "residual_term.exr").exists() and (
        tmp_path / "maps" / "residual_term_weight.exr"
    ).exists()
    with_term = render_capture(tmp_path / "maps", capture.root, None)["predicted"].double()
    without = render_capture(tmp_path / "maps", capture.root, None, term=False)["predicted"].double()

    def psnr(predicted, which):
        return -10 * math.log10(float((predicted[which] - frames[which]).pow(2).mean()) / float(frames.max()) ** 2)

    assert psnr(with_term, ~left_out) > psnr(without, ~left_out)
    # measured: 40.2 dB against 38.3 dB without the term
    assert psnr(with_term, left_out) > psnr(without, left_out) + 1.0


def test_blend_weight_is_the_least_squares_mix_of_the_left_out_errors():
    """Against brute force: the model's weight minimises the blend's left-out squared error over a
    fine grid of [0, 1]; the coefficients mix alike; a pixel where the two predict alike keeps 1."""
    g = torch.Generator().manual_seed(5)
    n, s, k, c, j = 6, 1, 40, 3, 9
    shared = torch.randn(n, s, k, c, generator=g, dtype=D)
    model = shared + 2.0 * torch.randn(n, s, k, c, generator=g, dtype=D)
    alone = shared + 2.0 * torch.randn(n, s, k, c, generator=g, dtype=D)
    alone[0] = model[0]  # alike: w = 1
    alone[1] = 0.1 * model[1]  # the term alone predicts far better: w near 0
    one = torch.tensor(1.0, dtype=D)
    cm, ca = torch.randn(n, j, c, generator=g, dtype=D), torch.randn(n, j, c, generator=g, dtype=D)
    blended = blend(
        ResidualTerm(cm, torch.ones(n, dtype=torch.bool), left_out=model, noise=one),
        ResidualTerm(ca, torch.ones(n, dtype=torch.bool), left_out=alone, noise=one),
        z=0.0,
    )
    grid = torch.linspace(0, 1, 100001, dtype=D)
    error = (grid[:, None, None, None, None] * model + (1 - grid[:, None, None, None, None]) * alone).pow(2)
    best = grid[error.flatten(2).sum(-1).argmin(0)]
    best[0] = 1.0
    # where the blend does not predict better than the model (z = 0: any gain), the model is kept
    keep = blended.weight < 1
    torch.testing.assert_close(blended.weight[keep], best[keep], atol=2e-5, rtol=0)
    assert bool(blended.weight[0] == 1) and float(blended.weight[1]) < 0.2
    w = blended.weight[:, None, None]
    torch.testing.assert_close(blended.coefficients, w * cm + (1 - w) * ca)


def test_blend_keeps_the_model_where_noise_alone_favours_the_term():
    """The term alone adds only an error of its own to the model's left-out errors (the best
    weight is 1): the least-squares weight falls below 1 by chance at about half the pixels, and
    the margin z keeps w = 1 there."""
    g = torch.Generator().manual_seed(6)
    n, k, c = 500, 48, 3
    model = torch.randn(n, 1, k, c, generator=g, dtype=D)
    alone = model + 0.3 * torch.randn(n, 1, k, c, generator=g, dtype=D)
    one = torch.tensor(1.0, dtype=D)
    zero = torch.zeros(n, 9, c, dtype=D)
    chosen = torch.zeros(n, dtype=torch.bool)
    blended = blend(
        ResidualTerm(zero, chosen, left_out=model, noise=one), ResidualTerm(zero, chosen, left_out=alone, noise=one)
    )
    assert float((blended.weight < 1).double().mean()) < 0.02


def test_the_weight_mixes_model_and_term_in_the_encoded_domain_and_is_checked():
    directions = _dome()
    lights = _lights(directions, scale=2.0)
    values = 0.05 + torch.rand(2, directions.shape[0], 3, dtype=D)
    coefficients = 0.1 * torch.ones(2, 9, 3, dtype=D)
    weight = torch.tensor([0.0, 0.25], dtype=D)
    out = ResidualTerm(coefficients, torch.ones(2, dtype=torch.bool), weight=weight).apply(values, lights)
    term = torch.einsum("kj,njc->nkc", hsh_basis(directions), coefficients)
    expected = decode(weight[:, None, None] * encode(values / 2.0) + term) * 2.0
    torch.testing.assert_close(out, expected)
    image = ResidualTerm(coefficients.reshape(1, 2, 9, 3), torch.ones(1, 2, dtype=torch.bool)).to_map()
    back = ResidualTerm.from_map(image, 3, weight=torch.tensor([[[1.0], [0.5]]]))
    assert back.weight.shape == (1, 2) and bool(back.chosen.all())
    with pytest.raises(TorchspecError, match=r"weight map \(residual_term_weight.exr\) must be in \[0, 1\].*\(0, 1\)"):
        ResidualTerm.from_map(image, 3, "maps/residual_term.exr", weight=torch.tensor([[[1.0], [1.5]]]))
