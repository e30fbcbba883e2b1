import math

import pytest
import torch
from capture_cases import write_relight_painting

from torchspec.cli import main
from torchspec.io import CaptureError, read_capture
from torchspec.relight import psnr, render_capture
from torchspec.simulate import LayoutConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.synth import PaintingConfig


@pytest.fixture(scope="module")
def painting(tmp_path_factory):
    return write_relight_painting(tmp_path_factory.mktemp("cap") / "painting")


def test_render_reproduces_a_simulated_capture(painting, tmp_path):
    report = render_capture(painting / "truth", painting, tmp_path / "out")
    assert report["frames"] == 12 and report["psnr_db"] > 100 and report["relative_rms"] < 1e-5
    written = read_capture(tmp_path / "out")
    assert [f.file for f in written.frames] == [f.file for f in read_capture(painting).frames]


def test_psnr():
    a = torch.tensor([1.0, 0.0], dtype=torch.float64)
    assert psnr(a, a) == math.inf
    assert abs(psnr(a + 0.1, a) - 20.0) < 1e-9


def test_unknown_light_needs_a_light_file(unknown_light_capture):
    with pytest.raises(CaptureError, match="'unknown'.*--light"):
        render_capture(unknown_light_capture / "truth", unknown_light_capture, None)
    truth = unknown_light_capture / "truth"
    report = render_capture(truth, unknown_light_capture, None, light=truth / "light.json")
    assert report["psnr_db"] > 90


def test_capture_lights(painting, unknown_light_capture):
    capture = read_capture(painting)
    lights = capture.lights(dtype=torch.float32)
    assert lights.directions.shape == (len(capture.frames), 3) and lights.directions.dtype == torch.float32
    assert torch.equal(lights.exposure, capture.exposure().float())
    unknown = read_capture(unknown_light_capture)
    with pytest.raises(CaptureError, match="'unknown'.*--light"):
        unknown.lights()
    with pytest.raises(CaptureError, match="nope.json must exist.*light description"):
        unknown.lights(light=unknown_light_capture / "nope.json")
    given = unknown.lights(light=unknown_light_capture / "truth" / "light.json")
    assert given.kernel.kind != "unknown"


def test_size_mismatch_is_named(painting, tmp_path):
    config = SimulationConfig(
        scene=SceneConfig(kind="painting", painting=PaintingConfig(width=6, height=6, strokes=2)),
        layout=LayoutConfig(kind="grid", nx=4, ny=4, extent=0.5, radius=0.6),
    )
    write_simulation(tmp_path / "small", simulate(config))
    with pytest.raises(CaptureError, match="maps are 6x6 but .* is 10x8"):
        render_capture(tmp_path / "small" / "truth", painting, None)


def test_cli_simulate_and_render(tmp_path, capsys):
    config = tmp_path / "sim.yaml"
    config.write_text(
        "scene: {kind: painting, painting: {width: 8, height: 8, strokes: 2}}\n"
        "layout: {kind: grid, nx: 3, ny: 3, extent: 0.4, radius: 0.6}\n"
    )
    assert main(["simulate", str(config), "-o", str(tmp_path / "cap")]) == 0
    assert (
        main(
            ["render", str(tmp_path / "cap" / "truth"), "--capture", str(tmp_path / "cap"), "-o", str(tmp_path / "out")]
        )
        == 0
    )
    assert "PSNR" in capsys.readouterr().out
    assert main(["render", str(tmp_path / "nope"), "--capture", str(tmp_path / "cap"), "-o", str(tmp_path / "x")]) == 2
    assert "torchspec render: error:" in capsys.readouterr().err


def test_render_takes_the_dome_radius_or_positions_the_fit_calibrated(painting, tmp_path):
    """A fit that calibrated a dome radius (svbrdf.json's fit.lights) is rendered under near lights
    at that radius along the capture's directions, as render_near renders them; calibrated positions
    replace the fitted frames' own; a record that does not match the capture is refused by name."""
    from torchspec.errors import TorchspecError
    from torchspec.io import read_svbrdf, write_svbrdf
    from torchspec.relight import render_near

    maps = read_svbrdf(painting / "truth")
    capture = read_capture(painting)
    lights = capture.lights(dtype=torch.float32)
    view = torch.tensor(capture.view)
    distant = render_capture(painting / "truth", painting, None)["predicted"]
    dome = {"frames": list(range(12)), "lights": {"calibrated": ["irradiance", "radius"], "radius": 2.0}}
    write_svbrdf(tmp_path / "dome", maps, meta={**maps.meta, "fit": dome})
    near = render_capture(tmp_path / "dome", painting, None)["predicted"]
    expected = render_near(maps.svbrdf, lights, 2.0 * capture.directions().float(), view).permute(2, 3, 0, 1)
    assert torch.allclose(near, expected) and float((near - distant).abs().max()) > 1e-3
    found = 1.5 * capture.directions()[::3]
    placed = {"frames": list(range(0, 12, 3)), "lights": {"calibrated": ["irradiance", "position"],
                                                          "positions": found.tolist()}}  # fmt: skip
    write_svbrdf(tmp_path / "placed", maps, meta={**maps.meta, "fit": placed})
    shown = render_capture(tmp_path / "placed", painting, None)["predicted"]
    positions = (found.norm(dim=-1).median() * capture.directions()).index_put((torch.arange(0, 12, 3),), found)
    expected = render_near(maps.svbrdf, lights, positions.float(), view).permute(2, 3, 0, 1)
    assert torch.allclose(shown, expected)
    placed["frames"] = [0, 3, 6, 12]  # frame 12: not the capture's
    write_svbrdf(tmp_path / "wrong", maps, meta={**maps.meta, "fit": placed})
    with pytest.raises(TorchspecError, match=r"fit\.lights\.positions"):
        render_capture(tmp_path / "wrong", painting, None)


def test_a_render_with_a_residual_term_below_black_is_a_capture_info_reads(painting, tmp_path):
    """A residual term that dips below black at a pixel (as a smooth term does in a cast shadow):
    the rendered frames are clamped at 0, so ``info`` and ``read_capture`` read the toolkit's own
    render; elsewhere the frames are the maps' prediction."""
    from torchspec.io import read_svbrdf, write_svbrdf
    from torchspec.model.residual_term import MAP_NAME, ResidualTerm

    truth = read_svbrdf(painting / "truth")
    height, width = truth.svbrdf.shape
    channels = len(truth.svbrdf.channels)
    coefficients = torch.zeros(height, width, 9, channels)
    coefficients[2, 3, 0] = -5.0  # the constant harmonic: far below black under every light
    term = ResidualTerm(coefficients, coefficients.ne(0).any(-1).any(-1))
    write_svbrdf(tmp_path / "maps", truth.svbrdf, meta=truth.meta, extra={MAP_NAME: term.to_map()})
    out = tmp_path / "out"
    assert main(["render", str(tmp_path / "maps"), "--capture", str(painting), "-o", str(out), "--quiet"]) == 0
    frames = read_capture(out).read_frames(dtype=torch.float64)  # refused before: negative pixels
    assert float(frames.min()) == 0.0 and bool((frames[:, :, 2, 3] == 0).all())
    physical = render_capture(painting / "truth", painting, None)["predicted"].double()
    mask = torch.ones(height, width, dtype=torch.bool)
    mask[2, 3] = False
    assert torch.equal(frames[..., mask], physical[..., mask].float().double())
    assert main(["info", str(out), "--quiet"]) == 0
