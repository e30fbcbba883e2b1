"""What a layout of lights lets a fit do (torchspec.layout.fit_problem, coverage_warning), said by
``info`` and by ``fit`` before it starts; the fit's warning when many pixels stop at the solver's
iteration limit."""

import json

import pytest
import torch
from capture_cases import write_painting

from torchspec.cli import main
from torchspec.layout import coverage_warning, fit_problem
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
