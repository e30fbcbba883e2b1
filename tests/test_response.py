"""The camera's response estimated from a stack (torchspec.calibration.response) and its use by the import."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from torchspec.calibration.response import (
    CONTRAST,
    GAMMA,
    OFFSET,
    ResponseCurve,
    ResponseError,
    _curve,
    describe_response,
    estimate_response,
)
from torchspec.io.images import ImageError, Transfer
from torchspec.io.rti import import_rti
from torchspec.pipeline.plan import TERM_FOR_PHOTOGRAPHS, setup


def dome(dtype=torch.float64) -> torch.Tensor:
    """``(K, 3)`` a dome of 41 lights: rings at 10-70 degrees of elevation and the zenith."""
    rows = []
    for ring, elevation in enumerate((10, 25, 40, 55, 70)):
        for j in range(8):
            azimuth, e = 2 * math.pi * j / 8 + 0.3 * ring, math.radians(elevation)
            rows.append([math.cos(e) * math.cos(azimuth), math.cos(e) * math.sin(azimuth), math.sin(e)])
    rows.append([0.0, 0.0, 1.0])
    return torch.tensor(rows, dtype=dtype)


def lambertian(n: int, *, seed: int = 0, specular: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(linear (K, 3, n), directions (K, 3))``: random normals within 35 degrees of the view and
    albedos, under :func:`dome`; ``specular`` adds a narrow lobe about the mirror direction."""
    g = torch.Generator().manual_seed(seed)
    d = dome()
    tilt = torch.rand(n, generator=g, dtype=torch.float64) * math.radians(35)
    azimuth = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    normal = torch.stack([tilt.sin() * azimuth.cos(), tilt.sin() * azimuth.sin(), tilt.cos()], -1)
    albedo = 0.15 + 0.75 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    y = (d @ normal.T).clamp(min=0)[:, None, :] * albedo.T[None] * 0.85
    if specular:
        half = torch.nn.functional.normalize(d + torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype), dim=-1)
        c = half @ normal.T
        y = y + specular * torch.exp(-(1 - c**2) / c**2 / 0.05**2)[:, None, :]
    return y, d


def _logistic_film(x: torch.Tensor) -> torch.Tensor:
    """A film-like tone curve: a logistic S curve (slope 4) of the values encoded by a power 1/2.2."""
    low, high = torch.sigmoid(torch.tensor(-2.0)), torch.sigmoid(torch.tensor(2.0))
    return (torch.sigmoid(4 * (x.clamp(min=0) ** (1 / 2.2) - 0.5)) - low) / (high - low)


ENCODINGS = {
    "srgb": Transfer("srgb").encode,
    "power 1.8": lambda x: x.clamp(min=0) ** (1 / 1.8),
    "power 2.4": lambda x: x.clamp(min=0) ** (1 / 2.4),
    "linear": lambda x: x,
    "film": _logistic_film,
}


def _true_decode(encode, grid: torch.Tensor) -> torch.Tensor:
    """The inverse of ``encode`` on ``grid``, by interpolating it on a fine grid of linear values."""
    x = torch.linspace(0, 1, 200_001, dtype=torch.float64)
    return torch.from_numpy(np.interp(grid.numpy(), encode(x).numpy(), x.numpy()))


def _codes(linear: torch.Tensor, encode) -> torch.Tensor:
    return (encode(linear.clamp(0, 1)) * 255).round() / 255


@given(
    gamma=st.floats(GAMMA[0], GAMMA[1]),
    offset=st.floats(0, OFFSET),
    contrast=st.floats(-CONTRAST, CONTRAST),
)
@settings(max_examples=40, deadline=None)
def test_every_member_is_monotone_from_0_to_1_and_encode_inverts_it(gamma, offset, contrast):
    curve = ResponseCurve((gamma,), (offset,), (contrast,))
    v = torch.linspace(0, 1, 2001, dtype=torch.float64)[:, None]
    g = curve.decode(v)[:, 0]
    assert abs(float(g[0])) < 1e-12 and abs(float(g[-1]) - 1) < 1e-12
    assert bool((g[1:] >= g[:-1] - 1e-15).all())
    inner = v[(g > 1e-9) & (g < 1 - 1e-9)]  # where the curve is not flat to float64
    assert float((curve.encode(curve.decode(inner[:, None]))[:, 0] - inner).abs().max()) < 1e-6


@pytest.mark.parametrize("params", [(2.2, 0.0, 0.0), (1.3, 0.2, 5.0), (0.7, 0.05, -6.0), (3.0, 0.4, 0.0005)])
def test_curve_slope_is_the_derivative_of_the_curve(params):
    v = torch.linspace(0.02, 0.98, 97, dtype=torch.float64, requires_grad=True)
    p = torch.tensor(params, dtype=torch.float64)
    value, slope = _curve(v, p)
    (autograd,) = torch.autograd.grad(value.sum(), v)
    torch.testing.assert_close(slope, autograd, rtol=1e-9, atol=1e-12)
    assert torch.autograd.gradcheck(lambda q: _curve(v.detach(), q)[0], (p.clone().requires_grad_(True),))


def test_the_offset_member_holds_srgb():
    v = torch.linspace(0, 1, 10001, dtype=torch.float64)[:, None]
    curve = ResponseCurve((2.4,), (0.055,), (0.0,))
    assert float((curve.decode(v) - Transfer("srgb").decode(v)).abs().max()) < 9e-4


def test_a_curve_per_channel_decodes_each_channel_and_checks_the_count():
    curve = ResponseCurve((1.0, 2.0), (0.0, 0.0), (0.0, 0.0))
    x = torch.full((4, 2), 0.5, dtype=torch.float64)
    torch.testing.assert_close(curve.decode(x)[0], torch.tensor([0.5, 0.25], dtype=torch.float64))
    with pytest.raises(ResponseError, match="2 channels"):
        curve.decode(torch.zeros(4, 3))
    with pytest.raises(ResponseError, match="gamma"):
        ResponseCurve((-1.0,), (0.0,), (0.0,))
    assert ResponseCurve.from_json(curve.to_json()) == curve


@pytest.mark.parametrize("name", list(ENCODINGS))
def test_the_curve_of_a_known_encoding_comes_back(name):
    linear, d = lambertian(512, seed=1)
    estimate = estimate_response(_codes(linear, ENCODINGS[name]), d)
    grid = torch.linspace(0, 1, 501, dtype=torch.float64)
    error = (estimate.curve.decode(grid[:, None])[:, 0] - _true_decode(ENCODINGS[name], grid)).abs().max()
    assert float(error) < 0.01, (name, estimate.family, estimate.curve)
    assert (estimate.family == "linear") == (name == "linear")
    assert max(estimate.std) < 0.01
    assert estimate.left_out_loss[estimate.family] <= min(estimate.left_out_loss.values()) * 1.05


def test_highlights_do_not_bend_the_curve():
    linear, d = lambertian(512, seed=2, specular=0.5)
    estimate = estimate_response(_codes(linear, ENCODINGS["power 2.4"]), d)
    grid = torch.linspace(0, 1, 501, dtype=torch.float64)
    assert float((estimate.curve.decode(grid[:, None])[:, 0] - grid**2.4).abs().max()) < 0.01


def test_bad_stacks_are_refused_in_words():
    linear, d = lambertian(64)
    with pytest.raises(ResponseError, match="6 frames"):
        estimate_response(linear[:5], d[:5])
    with pytest.raises(ResponseError, match="most codes"):
        estimate_response(torch.ones_like(linear), d)
    with pytest.raises(ResponseError, match=r"\(K, C, N\)"):
        estimate_response(linear[0], d)


def _write_stack(folder, codes: torch.Tensor, directions: torch.Tensor, **save) -> None:
    """``codes (K, 3, N)`` as K 8-bit PNGs of ``sqrt(N)`` squared pixels and a ``dirs.lp``."""
    folder.mkdir(parents=True, exist_ok=True)
    side = int(math.isqrt(codes.shape[-1]))
    lines = [str(codes.shape[0])]
    for k in range(codes.shape[0]):
        array = (codes[k].reshape(3, side, side).permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
        Image.fromarray(array).save(folder / f"f{k:02d}.png", **save)
        x, y, z = directions[k].tolist()
        lines.append(f"f{k:02d}.png {x:.6f} {y:.6f} {z:.6f}")
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")


def test_import_estimates_the_curve_of_untagged_photographs(tmp_path):
    linear, d = lambertian(576, seed=3)
    codes = _codes(linear, ENCODINGS["power 1.8"])
    _write_stack(tmp_path / "rti", codes, d)
    imported = import_rti(tmp_path / "rti", tmp_path / "capture")
    assert imported.transfer.name == "response" and imported.response is not None
    source = json.loads((tmp_path / "capture" / "capture.json").read_text())["source"]
    assert source["transfer"] == "response" and source["response"]["family"] == imported.response.family
    assert Transfer.of_source(source).curve == imported.transfer.curve
    frames = imported.capture.read_frames(dtype=torch.float64)  # (K, C, H, W), decoded by the estimate
    truth = codes.reshape(frames.shape) ** 1.8
    assert float((frames - truth).abs().max()) < 0.01
    words = describe_response(source["response"])
    assert "camera response estimated" in words and "in linear units" in words


def test_an_encoding_that_is_said_is_used_as_said(tmp_path):
    from PIL import ImageCms

    linear, d = lambertian(256, seed=4)
    codes = _codes(linear, ENCODINGS["power 1.8"])
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    _write_stack(tmp_path / "tagged", codes, d, icc_profile=srgb)
    tagged = import_rti(tmp_path / "tagged", tmp_path / "a")
    assert str(tagged.transfer) == "srgb" and tagged.response is None
    _write_stack(tmp_path / "plain", codes, d)
    given_srgb = import_rti(tmp_path / "plain", tmp_path / "b", transfer="srgb")
    assert str(given_srgb.transfer) == "srgb" and given_srgb.response is None
    a = tagged.capture.read_frames(dtype=torch.float64)
    b = given_srgb.capture.read_frames(dtype=torch.float64)
    assert torch.equal(a, b)  # both decoded exactly as sRGB
    torch.testing.assert_close(a, Transfer("srgb").decode(codes.reshape(a.shape)).float().double())


def test_untagged_frames_after_a_tagged_first_one_decode_as_srgb(tmp_path):
    """The first frame says sRGB (an ICC profile), the others say nothing: one transfer for the
    stack, sRGB, as before the response was estimated (not an estimate for some frames)."""
    from PIL import ImageCms

    linear, d = lambertian(256, seed=8)
    codes = _codes(linear, ENCODINGS["srgb"])
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    _write_stack(tmp_path / "plain", codes, d)
    first = tmp_path / "plain" / "f00.png"
    Image.open(first).save(first, icc_profile=srgb)
    imported = import_rti(tmp_path / "plain", tmp_path / "out")
    assert str(imported.transfer) == "srgb" and imported.response is None
    frames = imported.capture.read_frames(dtype=torch.float64)
    torch.testing.assert_close(frames, Transfer("srgb").decode(codes.reshape(frames.shape)).float().double())


def test_auto_is_refused_for_linear_photographs(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    linear, d = lambertian(64, seed=5)
    folder = tmp_path / "float"
    folder.mkdir()
    lines = [str(len(d))]
    for k in range(len(d)):
        tifffile.imwrite(folder / f"f{k}.tif", linear[k].reshape(3, 8, 8).permute(1, 2, 0).float().numpy())
        lines.append(f"f{k}.tif {' '.join(f'{x:.6f}' for x in d[k].tolist())}")
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")
    assert str(import_rti(folder, tmp_path / "linear").transfer) == "linear"  # the default: untouched
    with pytest.raises(ImageError, match="--transfer auto is for 8 or 16-bit"):
        import_rti(folder, tmp_path / "auto", transfer="auto")


def test_the_residual_term_is_on_by_default_for_photographs_only(tmp_path):
    linear, d = lambertian(256, seed=6)
    _write_stack(tmp_path / "rti", _codes(linear, ENCODINGS["srgb"]), d)
    imported = import_rti(tmp_path / "rti", tmp_path / "capture")
    assert setup(imported.capture, None, None).config.term.order == TERM_FOR_PHOTOGRAPHS
    plain = imported.capture
    from dataclasses import replace

    simulated = replace(plain, extra={key: value for key, value in plain.extra.items() if key != "source"})
    assert setup(simulated, None, None).config.term.order == 0


def test_the_fit_judges_the_true_curve_best():
    from torchspec.calibration.response_judge import judge_curves

    linear, d = lambertian(256, seed=7)
    codes = _codes(linear, ENCODINGS["power 2.4"]).reshape(len(d), 3, 16, 16)
    scores = judge_curves(
        codes, d, {"true": Transfer("gamma", 2.4), "linear": Transfer("linear"), "srgb": Transfer("srgb")}, size=16
    )
    assert set(scores) == {"true", "linear", "srgb"}
    assert scores["true"] > scores["srgb"] > scores["linear"]
    assert scores["true"] > 40  # the 8-bit rounding of a Lambertian stack: ~50 dB


def test_the_term_of_a_fit_of_photographs_is_in_their_estimated_encoding(tmp_path):
    """Imported with an estimated curve, the fit's residual term is fitted in the photographs'
    codes (that curve), recorded in svbrdf.json, and render applies it there; a capture that says
    sRGB keeps the sRGB term."""
    import torchspec
    from torchspec.model.residual_term import TermDomain
    from torchspec.relight import render_capture

    linear, d = lambertian(256, seed=9)
    _write_stack(tmp_path / "rti", _codes(linear, ENCODINGS["power 1.8"]), d)
    imported = import_rti(tmp_path / "rti", tmp_path / "capture")
    job = setup(imported.capture, None, None)
    assert job.domain == TermDomain(imported.transfer.curve)
    config = torchspec.FitConfig.from_dict(
        {"model": "diffuse", "calibrate": "none", "term": {"order": 2}, "quadrature": {"compile": False}}
    )
    fit = torchspec.fit(imported.capture, config=config)
    assert fit.term is not None and fit.term.domain == job.domain
    torchspec.write_fit(tmp_path / "maps", fit)
    record = json.loads((tmp_path / "maps" / "svbrdf.json").read_text())["residual_term"]["encoding"]
    assert record == {"transfer": "response", "response": imported.transfer.curve.to_json()}
    rendered = render_capture(tmp_path / "maps", tmp_path / "capture", None, dtype=torch.float64)["predicted"]
    physical = render_capture(tmp_path / "maps", tmp_path / "capture", None, dtype=torch.float64, term=False)
    lights = imported.capture.lights(dtype=torch.float64)
    expected = fit.term.apply(physical["predicted"].double().permute(2, 3, 0, 1), lights)
    torch.testing.assert_close(rendered.double(), expected.permute(2, 3, 0, 1), rtol=1e-5, atol=1e-6)
    given = import_rti(tmp_path / "rti", tmp_path / "srgb", transfer="srgb")
    assert setup(given.capture, None, None).domain == TermDomain()
