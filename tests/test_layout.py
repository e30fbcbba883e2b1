"""What a layout of lights lets a fit do (torchspec.model.layout.fit_problem, coverage_warning), said by
``info`` and by ``fit`` before it starts; the fit's warning when many pixels stop at the solver's
iteration limit."""

import json

import pytest
import torch
from capture_cases import write_painting
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.cli import main
from torchspec.model.layout import coverage_warning, fit_problem
from torchspec.pipeline.assembly import stalled_warning

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def _grid(n, extent):
    ticks = torch.linspace(-extent, extent, n, dtype=F64)
    return torch.stack(torch.meshgrid(ticks, ticks, indexing="xy"), -1).reshape(-1, 2)


def test_the_minimum_frames_and_layouts():
    assert "3 frame(s): a fit needs at least 4" in fit_problem(_grid(3, 0.3)[:3], lobe=False)
    assert "4 frames on a 2 x 2 grid (rows x columns)" in fit_problem(_grid(2, 0.3))
    assert fit_problem(_grid(2, 0.3), lobe=False) is None  # the diffuse part alone: 4 frames suffice
    assert fit_problem(_grid(3, 0.3)) is None
    line = torch.stack([torch.linspace(-0.3, 0.3, 4, dtype=F64), torch.zeros(4, dtype=F64)], -1)
    assert fit_problem(line) is None  # a line of 4: 3 along its one axis
    scattered = torch.rand(8, 2, generator=torch.Generator().manual_seed(0), dtype=F64) * 0.6 - 0.3
    assert "8 frames scattered over the plane" in fit_problem(scattered)
    more = torch.rand(12, 2, generator=torch.Generator().manual_seed(0), dtype=F64) * 0.6 - 0.3
    assert fit_problem(more) is None


def test_lights_away_from_the_mirror_direction_are_named():
    assert coverage_warning(_grid(7, 0.6), VIEW) is None
    row = _grid(7, 0.6)[:7]  # the top row: 0.6 from the zenith, spacing 0.2
    assert "on a line 0.60 from the mirror direction" in coverage_warning(row, VIEW)
    corner = _grid(7, 0.6)[(_grid(7, 0.6) > 0.35).all(-1)]  # a 2 x 2 corner, 0.57 from it
    assert "with the nearest 0.57 from the mirror direction" in coverage_warning(corner, VIEW)
    oblique = torch.tensor([0.0, 0.6, 0.8], dtype=F64)  # a camera 37 deg off: peaks mirror it
    assert coverage_warning(row, oblique) is None


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    """A 6 x 6 painting under 4 lights on a 2 x 2 grid (acquire --layout grid:4x4 --radius 0.8)."""
    return write_painting(tmp_path_factory.mktemp("layout") / "square", size=6, grid=2, extent=0.27)


def test_two_by_two_lights_are_refused_before_the_fit_and_named_by_info(square, tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["fit", str(square), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "4 frames on a 2 x 2 grid" in err and "needs at least 3 lights along each axis" in err, err
    assert "model: diffuse" in err and "Traceback" not in err and not out.exists()
    assert main(["info", str(square), "--quiet", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["verdict"] == "usable with warnings"
    assert any("refuses these frames: 4 frames on a 2 x 2 grid" in w for w in report["warnings"]), report
    assert main(["fit", str(square), "-o", str(out), "--quiet", "--model", "diffuse"]) == 0


def test_a_row_of_lights_and_a_stalled_solver_are_warned_about(tmp_path, capsys):
    capture = write_painting(tmp_path / "rows", size=5, grid=7, extent=0.6)
    settings = tmp_path / "fit.yaml"
    settings.write_text("lm: {max_iterations: 1}\n")
    out = tmp_path / "maps"
    assert main(["fit", str(capture), "-o", str(out), "--quiet", "--frames", "0:7", "--config", str(settings)]) == 0
    err = capsys.readouterr().err
    assert "torchspec fit: warning: " in err and "on a line 0.60 from the mirror direction" in err, err
    assert "pixels (" in err and "stopped at the solver's iteration limit (1)" in err, err
    stats = json.loads((out / "svbrdf.json").read_text())["fit"]
    assert len(stats["warnings"]) == 2 and stats["warnings"][1] == stalled_warning(stats)


def test_the_stalled_share():
    stats = {"status": {"max iterations": 10}, "pixels": 100, "frames": [0, 1, 2, 3], "settings": {"lm": {}}}
    assert stalled_warning(stats) is None  # 10 %: not above the share
    stats["status"]["max iterations"] = 11
    stats["settings"]["lm"]["max_iterations"] = 50
    assert stalled_warning(stats).startswith("11 of 100 pixels (11 %) stopped at the solver's iteration limit (50)")


def _lights_at(plane):
    """Point lights at l-plane positions ``plane (K, 2)``, irradiance 1."""
    from torchspec.model.lights import Kernel, Lights

    d = torch.cat([plane, (1 - plane.pow(2).sum(-1, keepdim=True)).sqrt()], -1)
    k = d.shape[0]
    return Lights(d, Kernel("point"), torch.ones(k, 1, dtype=F64), torch.ones(k, dtype=F64))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_lobe_support_is_the_ward_shape_at_the_best_light(seed):
    """Against brute force: ward_cosine without its factors ``sqrt(<n,wi>/<n,wo>) / (4 pi ax ay)``
    is ``exp(E)``; the support is its largest value over the lights (the sharper of two lobes)."""
    from torchspec.model.brdf import SVBRDF, ward_cosine
    from torchspec.model.layout import lobe_support

    g = torch.Generator().manual_seed(seed)
    n_px, k = 7, 9
    plane = (torch.rand(k, 2, generator=g, dtype=F64) - 0.5) * 1.2
    lights = _lights_at(plane)
    tilt = (torch.rand(n_px, 2, generator=g, dtype=F64) - 0.5) * 0.4
    normal = torch.cat([tilt, torch.ones(n_px, 1, dtype=F64)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    alpha = 0.02 + 0.3 * torch.rand(n_px, 2, generator=g, dtype=F64)
    alpha2 = 0.02 + 0.3 * torch.rand(n_px, 2, generator=g, dtype=F64)
    rotation = torch.rand(n_px, generator=g, dtype=F64) * 3
    ks = torch.rand(n_px, 1, generator=g, dtype=F64)
    ks[0] = 0  # no lobe: support 1 (nothing to determine)
    kd = torch.full((n_px, 1), 0.5, dtype=F64)
    svbrdf = SVBRDF(normal, kd, ks, alpha, rotation, ("Y",), ks, alpha2)

    def brute(a):
        wi, wo, nn = lights.directions[None], VIEW.expand(1, k, 3), normal[:, None]
        ci, co = (nn * wi).sum(-1), (nn * wo).sum(-1)
        value = ward_cosine(wi, wo, nn, a[:, None].expand(-1, k, -1), rotation[:, None].expand(-1, k))
        shape = value * 4 * torch.pi * a[:, None, 0] * a[:, None, 1] / (ci / co).clamp(min=1e-300).sqrt()
        return shape.amax(-1)

    expected = torch.minimum(brute(alpha), brute(alpha2))
    expected[0] = 1.0
    torch.testing.assert_close(lobe_support(svbrdf, lights, VIEW), expected, rtol=1e-10, atol=1e-12)


def test_a_lobe_between_the_lights_is_not_supported():
    """A lobe whose peak (the half vector n) sits midway between grid lights, narrower than their
    spacing, is not seen within its half maximum; the same lobe at a light is, as is a broad one."""
    from torchspec.model.brdf import SVBRDF
    from torchspec.model.layout import lobe_support

    lights = _lights_at(_grid(5, 0.6))  # l-plane spacing 0.3: half vectors ~0.15 apart
    # n mirrors the view to l-plane point (0.15, 0.15) (midway) or (0, 0) (on a light)
    between = torch.tensor([0.15, 0.15, (1 - 2 * 0.15**2) ** 0.5], dtype=F64)
    normal = torch.stack([(between + VIEW) / (between + VIEW).norm(), VIEW])
    one = torch.ones(2, 1, dtype=F64)
    sharp = SVBRDF(normal, one, one, torch.full((2, 2), 0.04, dtype=F64))
    support = lobe_support(sharp, lights, VIEW)
    assert support[0] < 0.5 < support[1]
    assert support[1] == pytest.approx(1.0)
    broad = SVBRDF(normal, one, one, torch.full((2, 2), 0.3, dtype=F64))
    assert bool((lobe_support(broad, lights, VIEW) > 0.5).all())
