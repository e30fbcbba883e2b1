"""torchspec render MAPS --light X,Y,Z / --lights FILE: new lights rendered from the maps, as the
capture's own frames are (torchspec.relight.lights)."""

import json
import shutil

import numpy as np
import pytest
import torch
from capture_cases import write_relight_painting
from PIL import Image

from torchspec.cli import main
from torchspec.io import read_capture, read_exr, read_svbrdf, write_svbrdf
from torchspec.io.images import Transfer
from torchspec.pipeline import fit, write_fit
from torchspec.pipeline.assembly import scene_record
from torchspec.relight import render_capture, render_near
from torchspec.relight.lights import NewLight, RenderError, parse_light, read_new_lights, render_lights, scene_of


@pytest.fixture(scope="module")
def painting(tmp_path_factory):
    """A 10 x 8 simulated painting under 12 frames of a projected Gaussian light (irradiance 1)."""
    return write_relight_painting(tmp_path_factory.mktemp("cap") / "painting")


def _exr(folder, name="light-000.exr"):
    return torch.from_numpy(read_exr(folder / name, ["R", "G", "B"])).permute(2, 0, 1)


def _with_term(painting, folder, frames, scene=None, lights=None):
    """The truth maps of ``painting`` with a random order-2 residual term and weight, and an
    ``svbrdf.json`` whose fit names ``frames`` and records ``scene`` (and ``lights``)."""
    maps = read_svbrdf(painting / "truth")
    generator = torch.Generator().manual_seed(3)
    h, w = maps.svbrdf.shape
    term = 0.05 * torch.randn(h, w, 12, generator=generator)  # 3 channels x 4 terms, channel-major
    weight = torch.rand(h, w, generator=generator)
    fit_record = {"frames": frames, "scene": scene, "lights": lights, "capture": "elsewhere"}
    write_svbrdf(folder, maps.svbrdf, meta={**maps.meta, "fit": fit_record},
                 extra={"residual_term": term, "residual_term_weight": weight})  # fmt: skip
    return folder


def test_a_new_light_at_a_frames_direction_renders_that_frame(painting, tmp_path):
    """A new light along frame k's direction, at frame k's irradiance, is frame k as the capture's
    render predicts it: the physical model and the fit's residual term, with the scene taken from
    svbrdf.json (the capture is not needed), from the capture, or from the folder holding truth/."""
    capture = read_capture(painting)
    frames = list(range(len(capture.frames)))
    maps = _with_term(painting, tmp_path / "maps", frames, scene_record(capture, frames))
    predicted = render_capture(maps, painting, None)["predicted"]  # (K, C, H, W), with the term
    plain = render_capture(maps, painting, None, term=False)["predicted"]
    for k in (0, 5):
        light = NewLight(capture.frames[k].direction, "test")
        report = render_lights(maps, tmp_path / f"new{k}", [light], overwrite=True)
        assert report["format"] == "exr" and report["files"] == ["light-000.exr"]
        # render_capture clamps a term's values below black at 0, as the files written here are
        assert torch.allclose(report["images"][0].clamp(min=0), predicted[k], atol=1e-6, rtol=1e-5)
        assert torch.equal(_exr(tmp_path / f"new{k}"), report["images"][0].clamp(min=0))  # negative values at 0
        assert float((predicted[k] - plain[k]).abs().max()) > 1e-3  # the term is there
    alone = render_lights(maps, tmp_path / "plain", [NewLight(capture.frames[5].direction, "test")], term=False)
    assert torch.allclose(alone["images"][0], plain[5], atol=1e-6, rtol=1e-5)
    truth = render_lights(painting / "truth", tmp_path / "truth", [NewLight(capture.frames[2].direction, "t")])
    assert truth["scene"].source == str(capture.manifest)
    assert torch.allclose(truth["images"][0], render_capture(painting / "truth", painting, None)["predicted"][2],
                          atol=1e-6, rtol=1e-5)  # fmt: skip


def test_the_default_irradiance_is_the_median_frames_and_is_recorded(painting, tmp_path):
    """Frames of irradiance 1..K (the fit's calibrated gains on top): a new light takes the median
    of exposure x irradiance x gain per channel; --irradiance replaces it; lights.json says which."""
    capture = read_capture(painting)
    frames = [0, 1, 2, 3, 4]
    scene = scene_record(capture, frames)
    scene["irradiance"] = [[1.0 + k, 2.0, 3.0] for k in frames]
    scene["exposure"] = [1.0, 1.0, 2.0, 1.0, 1.0]
    gains = [[1.0, 1.0, 0.5]] * 5
    maps = _with_term(painting, tmp_path / "maps", frames, scene, {"calibrated": ["irradiance"], "gains": gains})
    assert scene_of(read_svbrdf(maps), maps).irradiance == (4.0, 2.0, 1.5)  # 1 2 6 4 5 -> 4; 2 2 4 2 2 -> 2
    light = NewLight((0.0, 0.0, 1.0), "test")
    default = render_lights(maps, tmp_path / "default", [light], term=False)
    unit = render_lights(maps, tmp_path / "unit", [light], irradiance=[1.0], term=False)["images"][0]
    assert torch.allclose(default["images"][0], unit * torch.tensor([4.0, 2.0, 1.5])[:, None, None], rtol=1e-5)
    record = json.loads((tmp_path / "default" / "lights.json").read_text())
    assert record["irradiance"] == [4.0, 2.0, 1.5] and "median over the fit's 5 frames" in record["irradiance_chosen"]
    assert "calibrated gain" in record["irradiance_chosen"] and record["scene_from"].endswith("svbrdf.json")
    with pytest.raises(RenderError, match="--irradiance must be one number or one per channel"):
        render_lights(maps, tmp_path / "bad", [light], irradiance=[1.0, 2.0])


def test_near_lights_at_the_fits_dome_radius(painting, tmp_path):
    """A fit that calibrated a dome radius lights new directions from that radius, as the capture's
    frames are rendered (render_near)."""
    capture = read_capture(painting)
    frames = list(range(len(capture.frames)))
    dome = {"calibrated": ["radius"], "radius": 2.0}
    maps = _with_term(painting, tmp_path / "maps", frames, scene_record(capture, frames), dome)
    predicted = render_capture(maps, painting, None)["predicted"]
    report = render_lights(maps, tmp_path / "new", [NewLight(capture.frames[7].direction, "t")])
    assert report["scene"].distance == 2.0
    assert torch.allclose(report["images"][0].clamp(min=0), predicted[7], atol=1e-6, rtol=1e-5)
    view = torch.tensor(capture.view)
    lights = capture.lights(dtype=torch.float32)
    physical = render_near(read_svbrdf(maps).svbrdf, lights, 2.0 * capture.directions().float(), view)
    assert float((physical.permute(2, 3, 0, 1)[7] - predicted[7]).abs().max()) > 0  # near, and with the term


def _flat_maps(folder, photographs, transfer, kd=0.5):
    """4 x 3 flat Lambertian maps (k_d = ``kd``) whose svbrdf.json records a point light, unit
    irradiance and a capture of ``photographs`` decoded with ``transfer``."""
    from torchspec.model.brdf import SVBRDF

    h, w = 3, 4
    svbrdf = SVBRDF(
        normal=torch.tensor([0.0, 0.0, 1.0]).expand(h, w, 3).contiguous(),
        diffuse=torch.full((h, w, 3), kd),
        specular=torch.zeros(h, w, 3),
        roughness=torch.zeros(h, w, 2),
        channels=("R", "G", "B"),
    )
    scene = {"view": [0.0, 0.0, 1.0], "light": {"kernel": "point"}, "irradiance": [[1.0] * 3] * 4,
             "exposure": [1.0] * 4, "distance": None, "photographs": photographs,
             "transfer": {"transfer": transfer, "response": None} if photographs else None}  # fmt: skip
    write_svbrdf(folder, svbrdf, meta={"fit": {"frames": [0, 1, 2, 3], "scene": scene}})
    return folder


@pytest.mark.parametrize("transfer", ["srgb", "gamma:2.2"])
def test_photographs_give_8_bit_pngs_encoded_as_they_were(tmp_path, transfer):
    """A capture of photographs renders 8-bit PNGs: the linear value k_d / pi cos(theta) encoded by
    the photographs' transfer (sRGB with --srgb), above 1 shown as white and counted."""
    maps = _flat_maps(tmp_path / "maps", True, transfer)
    lights = [parse_light("0,0,1"), parse_light("0.6,0,0.8")]
    report = render_lights(maps, tmp_path / "out", lights)
    assert report["format"] == "png" and report["files"] == ["light-000.png", "light-001.png"]
    curve = Transfer.parse(transfer)
    for k, cos in enumerate((1.0, 0.8)):
        codes = np.asarray(Image.open(tmp_path / "out" / report["files"][k]))
        assert codes.shape == (3, 4, 3) and codes.dtype == np.uint8
        expected = round(255 * float(curve.encode(torch.tensor(0.5 / np.pi * cos, dtype=torch.float64))))
        assert np.all(codes == expected)
    srgb = render_lights(maps, tmp_path / "srgb", lights[:1], srgb=True, irradiance=[4.0, 8.0, 20.0])
    codes = np.asarray(Image.open(tmp_path / "srgb" / "light-000.png"))
    assert np.all(codes[..., 2] == 255) and srgb["clipped"] == [12]  # 0.5 / pi x 20 > 1
    assert np.all(codes[..., 0] == round(255 * float(Transfer("srgb").encode(torch.tensor(2 / np.pi)))))
    exr = render_lights(maps, tmp_path / "exr", lights[:1], fmt="exr")
    assert exr["format"] == "exr" and np.allclose(read_exr(tmp_path / "exr" / "light-000.exr", ["R"]), 0.5 / np.pi)


def test_negative_values_are_written_as_zero(tmp_path):
    """A residual term that takes a pixel below 0 gives code 0 in a PNG and 0 in an EXR."""
    maps = _flat_maps(tmp_path / "maps", True, "srgb")
    read = read_svbrdf(maps)
    term = torch.zeros(3, 4, 12)
    term[0, 0, [0, 4, 8]] = -5.0  # the constant harmonic of each channel at pixel (0, 0)
    write_svbrdf(maps, read.svbrdf, meta=read.meta, extra={"residual_term": term}, overwrite=True)
    png = render_lights(maps, tmp_path / "png", [parse_light("0,0,1")])
    assert float(png["images"][0][:, 0, 0].max()) < 0
    codes = np.asarray(Image.open(tmp_path / "png" / "light-000.png"))
    assert np.all(codes[0, 0] == 0) and np.all(codes[1:] > 0)
    render_lights(maps, tmp_path / "exr", [parse_light("0,0,1")], fmt="exr")
    values = read_exr(tmp_path / "exr" / "light-000.exr", ["R", "G", "B"])
    assert np.all(values[0, 0] == 0) and np.all(values[1:] > 0)


def test_a_fit_records_its_scene_and_the_maps_render_without_the_capture(painting, tmp_path, capsys):
    """svbrdf.json of a fit says the view, the light and the frames' irradiance: the maps, moved
    away from their capture, render a new light from the command line as they do with --capture."""
    write_fit(tmp_path / "fit", fit(painting, frames="0-9"))
    scene = json.loads((tmp_path / "fit" / "svbrdf.json").read_text())["fit"]["scene"]
    assert scene["view"] == [0.0, 0.0, 1.0] and scene["light"]["kernel"] == "gaussian" and len(scene["exposure"]) == 10
    assert scene["photographs"] is False and scene["transfer"] is None and scene["distance"] is None
    shutil.move(tmp_path / "fit", tmp_path / "moved")
    shutil.move(painting, tmp_path / "hidden")  # not where the fit read it
    try:
        assert main(["render", str(tmp_path / "moved"), "--light", "0.3,-0.2,0.93", "-o", str(tmp_path / "a")]) == 0
        out = capsys.readouterr().out
        assert "wrote 1 image(s)" in out and "EXR" in out and "irradiance 1, 1, 1: the median" in out
        given = ["--capture", str(tmp_path / "hidden")]
        again = ["render", str(tmp_path / "moved"), "--light", "0.3,-0.2,0.93", "-o", str(tmp_path / "b")]
        assert main([*again, *given]) == 0
    finally:
        shutil.move(tmp_path / "hidden", painting)
    assert torch.equal(_exr(tmp_path / "a"), _exr(tmp_path / "b"))


def test_the_command_line_reads_lights_from_options_and_a_light_file(painting, tmp_path, capsys):
    """--light (repeatable) and --lights FILE.lp: one image per light in that order, lights.json
    and lights.lp listing them (the .lp readable by the light-file reader)."""
    lp = tmp_path / "new.lp"
    lp.write_text("2\r\nC:\\rti\\a.jpg 0 0,6 0,8\r\nb.jpg -0.6 0 0.8  \r\n")
    args = ["render", str(painting / "truth"), "-o", str(tmp_path / "out"), "--light", "0,0,1", "--lights", str(lp)]
    assert main([*args, "--light", "1,0,1", "--format", "png"]) == 0
    out = capsys.readouterr().out
    assert "wrote 4 image(s)" in out and "light-000.png, light-001.png, light-002.png, ... light-003.png" in out
    record = json.loads((tmp_path / "out" / "lights.json").read_text())
    assert [light["given"] for light in record["lights"]] == [
        "--light 0,0,1", "--light 1,0,1", f"{lp} line 2", f"{lp} line 3"
    ]  # fmt: skip
    assert record["lights"][2]["name"] == "C:\\rti\\a.jpg" and record["lights"][2]["direction"] == [0.0, 0.6, 0.8]
    assert np.allclose(record["lights"][1]["direction"], [2**-0.5, 0, 2**-0.5])
    again, _ = read_new_lights(tmp_path / "out" / "lights.lp")
    assert [light.name for light in again] == [f"light-00{k}.png" for k in range(4)]
    assert np.allclose([light.direction for light in again], [light["direction"] for light in record["lights"]])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "light-000.png", "light-001.png", "light-002.png", "light-003.png", "lights.json", "lights.lp"
    ]  # fmt: skip
    assert main([*args, "--light", "0,0.5,1"]) == 2  # the output holds the images: --overwrite
    assert "--overwrite" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--light", "light.json"], "--light takes a direction X,Y,Z .* now given with --light-model FILE"),
        (["--light", "new.lp"], "--light takes a direction X,Y,Z .* read with --lights FILE"),
        (["--light", "0,0,-1"], "above the surface"),
        (["--light", "1,2"], "--light must be a direction X,Y,Z"),
        (["--light", "0,0,0"], "non-zero"),
        ([], "render needs --capture CAPTURE .* or new lights"),
        (["--capture", "CAPTURE", "--format", "png"], "--format, --srgb and --irradiance are for new lights"),
        (["--light", "0,0,1", "--lights", "nowhere.lp"], "nowhere.lp must be an .lp light file"),
    ],
)
def test_command_line_errors_name_the_option(painting, tmp_path, capsys, extra, message):
    (tmp_path / "light.json").write_text('{"kernel": "point"}')
    extra = [str(tmp_path / e) if e.endswith((".json", ".lp")) else e for e in extra]
    extra = [str(painting) if e == "CAPTURE" else e for e in extra]
    assert main(["render", str(painting / "truth"), "-o", str(tmp_path / "out"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("torchspec render: error:")
    assert __import__("re").search(message, err), err


def test_light_model_replaces_the_old_light_option(unknown_light_capture, tmp_path, capsys):
    """The JSON light description that was --light FILE is --light-model FILE, for the capture's
    frames and for new lights; an 'unknown' kernel without it is refused by name."""
    truth = unknown_light_capture / "truth"
    model = ["--light-model", str(truth / "light.json")]
    assert main(["render", str(truth), "--capture", str(unknown_light_capture), "-o", str(tmp_path / "a"), *model]) == 0
    assert "PSNR" in capsys.readouterr().out
    assert main(["render", str(truth), "--light", "0,0,1", "-o", str(tmp_path / "b")]) == 2
    assert "'unknown'" in capsys.readouterr().err
    assert main(["render", str(truth), "--light", "0,0,1", "-o", str(tmp_path / "b"), *model]) == 0


def test_a_tabulated_kernel_needs_its_capture(tmp_path):
    """Maps fitted under a tabulated light whose capture cannot be found are refused, naming the
    options that give the table; --light-model replaces the kernel."""
    maps = _flat_maps(tmp_path / "maps", False, None)
    read = read_svbrdf(maps)
    read.meta["fit"]["scene"]["light"] = {"kernel": "tabulated", "file": "kernel.exr", "extent": 0.1}
    write_svbrdf(maps, read.svbrdf, meta=read.meta, overwrite=True)
    with pytest.raises(RenderError, match=r"tabulated light.*pass --capture CAPTURE, or --light-model FILE"):
        render_lights(maps, tmp_path / "out", [parse_light("0,0,1")])
    (tmp_path / "point.json").write_text('{"kernel": "point"}')
    report = render_lights(maps, tmp_path / "out", [parse_light("0,0,1")], light_model=tmp_path / "point.json")
    assert torch.allclose(report["images"][0], torch.full((3, 3, 4), 0.5 / np.pi))


def test_maps_and_capture_moved_together_find_each_other(painting, tmp_path):
    """fit.capture is written as an absolute path; maps that do not record their scene, moved with
    their capture to another folder, find it by its folder's name beside them (relight.capture_places),
    as the .rti export does."""
    from torchspec.relight import capture_places

    moved = tmp_path / "elsewhere"
    shutil.copytree(painting, moved / "painting")
    folder, gone = moved / "maps", str(tmp_path / "gone" / "painting")
    write_svbrdf(folder, read_svbrdf(painting / "truth").svbrdf, meta={"fit": {"capture": gone}})
    assert capture_places(gone, folder)[-1] == moved.resolve() / "painting"
    scene = scene_of(read_svbrdf(folder), folder)  # no fit.scene: read from the capture found beside
    assert scene.source == str(read_capture(moved / "painting").manifest)
    assert scene.root == (moved / "painting").resolve()
