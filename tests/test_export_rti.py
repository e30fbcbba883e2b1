"""Exports that the RTI world opens: an HSH .rti read back by a reader written here from the
format's description, OpenLIME's BRDF layer against its shader's formulas, the 16-bit normal
maps in both conventions, and every glTF export through the Khronos glTF-Validator."""

import contextlib
import json
import math
import struct
import warnings

import numpy as np
import pytest
import torch
from gltf_validator import validate, validator
from test_export import _maps, _png

from torchspec.cli import main
from torchspec.export import ExportError, ExportWarning, export, export_gltf, export_openlime, export_png16, export_rti
from torchspec.export.openlime import alpha_from_gloss, gloss_from_alpha
from torchspec.export.rti import fit_hsh, fit_rti, hemisphere_directions, render_display
from torchspec.export.rti import read_rti as read_rti_file
from torchspec.io import Capture, Frame, LightSpec, write_capture, write_svbrdf
from torchspec.model.brdf import SVBRDF
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render, render_image
from torchspec.model.residual_term import hsh_basis

F64 = torch.float64


# The .rti reader: written from the format's description (docs/export.md), not from the writer.


def read_rti(data: bytes) -> tuple[np.ndarray, dict]:
    """``(H, W, 3, 9)`` coefficients (row 0 at the top of the image) and the header of an HSH .rti."""
    lines, offset = [], 0
    while len(lines) < 3:
        end = data.index(b"\n", offset)
        line = data[offset:end].decode("ascii")
        offset = end + 1
        if not line.startswith("#"):
            lines.append(line)
    kind = int(lines[0])
    width, height, colours = map(int, lines[1].split())
    terms, basis_type, element = map(int, lines[2].split())
    scale = np.array(struct.unpack_from(f"<{terms}f", data, offset))
    bias = np.array(struct.unpack_from(f"<{terms}f", data, offset + 4 * terms))
    body = np.frombuffer(data, np.uint8, offset=offset + 8 * terms)
    assert body.size == width * height * colours * terms, "the file holds exactly the coefficients"
    codes = body.reshape(height, width, colours, terms)  # the file's first row is the top one
    header = {"type": kind, "size": (width, height), "colours": colours, "terms": terms, "element": element}
    header["basis_type"] = basis_type
    return codes / 255.0 * scale + bias, {**header, "scale": scale, "bias": bias}


def rtiviewer_hsh(direction: np.ndarray) -> np.ndarray:
    """RTIViewer's ``getHSH(theta, phi)`` of a unit light direction: the 9 weights."""
    theta, phi = math.acos(direction[2]), math.atan2(direction[1], direction[0])
    c = math.cos(theta)
    s = math.sqrt(c - c * c)
    return np.array(
        [
            1 / math.sqrt(2 * math.pi),
            math.sqrt(6 / math.pi) * math.cos(phi) * s,
            math.sqrt(3 / (2 * math.pi)) * (-1 + 2 * c),
            math.sqrt(6 / math.pi) * s * math.sin(phi),
            math.sqrt(30 / math.pi) * math.cos(2 * phi) * (-c + c * c),
            math.sqrt(30 / math.pi) * math.cos(phi) * (-1 + 2 * c) * s,
            math.sqrt(5 / (2 * math.pi)) * (1 - 6 * c + 6 * c * c),
            math.sqrt(30 / math.pi) * (-1 + 2 * c) * s * math.sin(phi),
            math.sqrt(30 / math.pi) * (-c + c * c) * math.sin(2 * phi),
        ]
    )


def test_hsh_basis_is_rtiviewers():
    directions = hemisphere_directions(20)
    ours = hsh_basis(directions, 3).numpy()
    theirs = np.stack([rtiviewer_hsh(d) for d in directions.numpy()])
    np.testing.assert_allclose(ours, theirs, atol=1e-12)


def test_fit_hsh_recovers_values_in_its_span():
    g = torch.Generator().manual_seed(3)
    directions = hemisphere_directions(30)
    truth = torch.randn(4, 5, 3, 9, generator=g, dtype=F64)
    values = torch.einsum("kj,...cj->...kc", hsh_basis(directions, 3), truth)
    fitted, rms = fit_hsh(values, directions)
    np.testing.assert_allclose(fitted.numpy(), truth.numpy(), atol=1e-10)
    assert float(rms.max()) < 1e-10


def _tilted_maps() -> SVBRDF:
    """_maps, with pixel (0, 0) bright and its normal tilted towards +x: it marks the top-left
    corner and the light's x axis."""
    maps = _maps(height=6, width=9)
    normal, diffuse = maps.normal.clone(), maps.diffuse.clone()
    normal[0, 0] = torch.tensor([math.sin(0.5), 0.0, math.cos(0.5)], dtype=F64)
    diffuse[0, 0] = 0.9
    return SVBRDF(normal, diffuse, maps.specular, maps.roughness)


def test_rti_read_back_against_the_fit_and_the_renders(tmp_path):
    maps = _tilted_maps()
    manifest = json.loads(export_rti(maps, tmp_path).read_text())
    data = (tmp_path / manifest["file"]).read_bytes()
    assert data.startswith(b"#HSH1.2\n3\n9 6 3\n9 2 1\n")
    coefficients, header = read_rti(data)
    assert header["type"] == 3 and header["size"] == (9, 6) and header["terms"] == 9 and header["element"] == 1
    np.testing.assert_array_equal(read_rti_file(tmp_path / "image.rti")[0], coefficients)  # torchspec's reader

    fit = fit_rti(maps)  # the float fit before quantisation
    held_out = hemisphere_directions(20, 70.0) @ torch.tensor(
        [[0.6, -0.8, 0], [0.8, 0.6, 0], [0, 0, 1]], dtype=F64
    )  # 20 other lights, turned about z
    weights = np.stack([rtiviewer_hsh(d) for d in held_out.numpy()])  # (K, 9)
    relit = np.einsum("kj,hwcj->hwkc", weights, coefficients)  # what RTIViewer shows / 255
    floating = np.einsum("kj,hwcj->hwkc", weights, fit.coefficients)
    quantisation = np.abs(weights) @ (header["scale"] / 510) + 1e-6  # (K,): half a code per coefficient
    assert (np.abs(relit - floating) <= quantisation[:, None]).all(), "the file holds the fit to half a code"

    renders = render_display(maps, held_out, math.pi).numpy()
    file_error = np.abs(np.clip(relit, 0, 1) - renders)
    float_error = np.abs(np.clip(floating, 0, 1) - renders)
    print(
        f"rti read back vs renders, 20 held-out lights: RMS {np.sqrt((file_error**2).mean()) * 255:.2f}/255, "
        f"max {file_error.max() * 255:.1f}/255 (float fit: RMS {np.sqrt((float_error**2).mean()) * 255:.2f}/255)"
    )
    assert (file_error <= float_error + quantisation[:, None]).all()
    # The marked pixel: at the top-left, and brighter under a light from +x than from -x.
    assert np.abs(coefficients[0, 0] - fit.coefficients[0, 0]).max() <= header["scale"].max() / 510 + 1e-6
    side = np.stack([rtiviewer_hsh(np.array([s * math.sin(1.0), 0, math.cos(1.0)])) for s in (1, -1)])
    from_plus_x, from_minus_x = side @ coefficients[0, 0, 0]
    assert from_plus_x > from_minus_x + 0.1


def test_rti_of_a_matte_flat_surface_is_close(tmp_path):
    """Lambert under a point light, sRGB-encoded, is smooth: 9 HSH terms hold it within a code."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(2, 3, 3)
    maps = SVBRDF(n, torch.full((2, 3, 1), 0.6, dtype=F64), torch.zeros(2, 3, 1, dtype=F64), torch.zeros(2, 3, 2))
    fit = fit_rti(maps)
    print(f"matte flat surface: HSH fit RMS {fit.rms.max() * 255:.2f}/255 over the fitted lights")
    assert fit.rms.max() * 255 < 1, "finer than the 8-bit codes RTIViewer shows"


def test_rti_refuses_bad_options(tmp_path):
    from torchspec.export import ExportError

    export_rti(_maps(), tmp_path / "ok")
    data = (tmp_path / "ok" / "image.rti").read_bytes()
    (tmp_path / "cut.rti").write_bytes(data[:-5])
    with pytest.raises(ExportError, match=r"cut.rti: 940 coefficient bytes, 945 expected"):
        read_rti_file(tmp_path / "cut.rti")
    (tmp_path / "ptm.rti").write_bytes(data.replace(b"#HSH1.2\n3\n", b"#PTM1.2\n1\n", 1))
    with pytest.raises(ExportError, match="only HSH"):
        read_rti_file(tmp_path / "ptm.rti")

    with pytest.raises(ExportError, match="at least 9 lights"):
        hemisphere_directions(5)
    with pytest.raises(ExportError, match="irradiance must be a positive"):
        export_rti(_maps(), tmp_path / "a", irradiance=-1.0)
    with pytest.raises(ExportError, match="one irradiance"):
        export(_maps(), tmp_path / "b", to="rti", irradiance=[1.0, 2.0])
    with pytest.raises(ExportError, match="unit vectors above the horizon"):
        export_rti(_maps(), tmp_path / "c", directions=torch.tensor([[0.0, 0.0, -1.0]] * 9))


# The .rti as bright as the photographs ------------------------------------------------------------

EXPOSURE = [1.0, 2.0, 0.5, 1.0, 4.0, 100.0]  # frame 5 is not fitted (fit.frames): its 100 is left out
IRRADIANCE = [1.28, 0.8, 1.6, 2.4, 0.8, 1.0]
GAINS = [[1.25] * 3, [0.9, 1.0, 1.1], [2.0] * 3, [0.5] * 3, [1.0] * 3]  # the fit's, frames 0 .. 4
RESPONSE = {"gamma": [1.3], "offset": [0.0], "contrast": [0.0]}  # linear = code^1.3


def _fitted(tmp_path, calibrated=True):
    """Matte maps (``_maps``' row 0 repeated: tilted normals, no lobe) fitted from an imported
    capture ``cap`` beside them: 6 frames at the exposures and irradiances above, frames 0 .. 4
    fitted with the gains above (frame 0, at the zenith, lit as the median: 1.6), photographs
    encoded by a camera response of gamma 1.3 and rendered from the maps as the fit models them."""
    base = _maps(height=6, width=9)
    matte = SVBRDF(base.normal, base.diffuse, base.specular * 0, base.roughness * 0)
    directions = torch.tensor(
        [[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8], [0, -0.6, 0.8], [0.3, 0.3, 0.9055385]], dtype=F64
    )
    gains = torch.tensor(GAINS + [[1.0] * 3], dtype=F64) if calibrated else torch.ones(6, 3, dtype=F64)
    scale = torch.tensor(EXPOSURE, dtype=F64)[:, None] * torch.tensor(IRRADIANCE, dtype=F64)[:, None] * gains
    lights = Lights(directions, Kernel("point"), scale, torch.ones(6, dtype=F64))
    frames = render_image(matte, lights, torch.tensor([0.0, 0.0, 1.0], dtype=F64)).permute(2, 3, 0, 1)
    entries = [Frame(f"f{k}.exr", tuple(directions[k].tolist()), IRRADIANCE[k], EXPOSURE[k]) for k in range(6)]
    source = {"transfer": "response", "response": RESPONSE}
    capture = Capture(tmp_path / "cap", 9, 6, ("R", "G", "B"), (0.0, 0.0, 1.0), LightSpec("point"), entries,
                      extra={"source": source})  # fmt: skip
    write_capture(capture.root, capture, frames.float())
    lights = {"calibrated": ["irradiance"], "gains": GAINS} if calibrated else {"calibrated": []}
    fit = {"capture": "cap", "frames": [0, 1, 2, 3, 4], "lights": lights}
    write_svbrdf(tmp_path / "maps", matte, meta={"fit": fit})
    return tmp_path / "maps", frames


def test_rti_of_a_fitted_capture_is_as_bright_as_its_photographs(tmp_path, monkeypatch):
    """Issue 37: the .rti of an imported capture showed it 3 times too bright (lit at pi, sRGB).
    By default it is lit as the photographs were: the median exposure times irradiance times the
    fit's gains of the frames fitted, encoded by the photographs' camera response."""
    maps, frames = _fitted(tmp_path)
    products = np.array(EXPOSURE[:5])[:, None] * np.array(IRRADIANCE[:5])[:, None] * np.array(GAINS)
    assert np.median(products) == pytest.approx(1.6)  # frame 0's: 1.0 * 1.28 * 1.25
    monkeypatch.chdir(tmp_path / "cap")  # fit.capture, "cap", is found beside the maps
    record = json.loads(export_rti(maps, tmp_path / "rti").read_text())
    assert record["irradiance"] == pytest.approx(1.6, rel=1e-12)
    assert "5 frames of" in record["irradiance_from"] and "gains the fit calibrated" in record["irradiance_from"]
    assert record["encoding"] == {"transfer": "response", "response": RESPONSE}
    coefficients, _, _ = read_rti_file(tmp_path / "rti" / "image.rti")
    shown = np.clip(coefficients @ rtiviewer_hsh(np.array([0.0, 0.0, 1.0])), 0, 1)  # RTIViewer at the zenith / 255
    photograph = frames[0].permute(1, 2, 0).clamp(0, 1).numpy() ** (1 / 1.3)  # frame 0 as its camera encoded it
    print(f"zenith: .rti mean {shown.mean():.4f}, photograph {photograph.mean():.4f}")
    assert np.abs(shown - photograph).max() < 1.5 / 255  # the HSH fit of a matte surface, quantised

    before = json.loads(export_rti(maps, tmp_path / "pi", irradiance=math.pi).read_text())  # the old default
    assert before["irradiance"] == math.pi and before["irradiance_from"] == "given (--irradiance)"
    coefficients, _, _ = read_rti_file(tmp_path / "pi" / "image.rti")
    too_bright = np.clip(coefficients @ rtiviewer_hsh(np.array([0.0, 0.0, 1.0])), 0, 1)
    assert too_bright.mean() > 1.35 * photograph.mean()  # (pi / 1.6)^(1 / 1.3) = 1.68, less what clips


def test_rti_irradiance_without_gains_and_without_the_capture(tmp_path, capsys):
    maps, _ = _fitted(tmp_path, calibrated=False)
    products = np.array(EXPOSURE[:5]) * np.array(IRRADIANCE[:5])  # 1.28, 1.6, 0.8, 2.4, 3.2
    argv = ["export", str(maps), "--to", "rti", "-o", str(tmp_path / "a")]
    assert main(argv) == 0
    assert json.loads((tmp_path / "a" / "rti.json").read_text())["irradiance"] == pytest.approx(np.median(products))
    out = capsys.readouterr().out
    assert "lit by irradiance 1.6 (the median exposure times irradiance of the 5 frames of" in out
    assert "encoded as the photographs' camera response" in out
    (tmp_path / "cap").rename(tmp_path / "moved")  # svbrdf.json's capture is gone: pi, with a warning
    with pytest.warns(ExportWarning, match=r"fit.capture: cap\) cannot be read .* irradiance pi"):
        record = json.loads(export_rti(maps, tmp_path / "b").read_text())
    assert record["irradiance"] == math.pi and record["encoding"] == {"transfer": "srgb"}
    assert main(argv[:-1] + [str(tmp_path / "c"), "--capture", str(tmp_path / "moved")]) == 0  # given: found
    assert json.loads((tmp_path / "c" / "rti.json").read_text())["irradiance"] == pytest.approx(1.6)
    with pytest.raises(ExportError, match="is 9x6 but the maps are 7x5"):
        export_rti(_maps(), tmp_path / "d", capture=tmp_path / "moved")


# OpenLIME's BRDF layer ----------------------------------------------------------------------------


def shaderbrdf(kd, ks, normal, gloss, limits, light):
    """OpenLIME ShaderBRDF's linear colour without its ambient term, written from its source:
    ``(kd / pi + ks ward) NdotL`` with the isotropic Ward lobe and alpha from gloss."""
    min_gloss, max_gloss = 1 - limits[1] ** 0.25, 1 - limits[0] ** 0.25
    alpha = (1 - gloss * (max_gloss - min_gloss) - min_gloss) ** 4
    view = np.array([0.0, 0.0, 1.0])
    h = (light + view) / np.linalg.norm(light + view)
    hn, ln, nv = normal @ h, normal @ light, normal @ view
    tan2 = (1 - hn**2) / hn**2
    spec = np.exp(-tan2 / alpha**2) / (4 * math.pi * alpha**2 * np.sqrt(ln * nv))
    spec = np.where((alpha * hn) ** 2 < 1e-5, 0.0, spec)
    return (kd / math.pi + ks * spec[..., None]) * np.maximum(ln, 0)[..., None]


def test_gloss_is_alpha_exactly():
    alpha = np.geomspace(0.004, 0.8, 50)
    limits = (0.004, 0.8)
    np.testing.assert_allclose(alpha_from_gloss(gloss_from_alpha(alpha, limits), limits), alpha, rtol=1e-12)
    assert gloss_from_alpha(np.array([0.8, 0.004]), limits) == pytest.approx([0.0, 1.0])


def test_openlime_layer_renders_the_maps(tmp_path):
    maps = _maps(height=6, width=9)
    iso = SVBRDF(maps.normal, maps.diffuse, maps.specular, maps.roughness[..., :1].expand(-1, -1, 2))
    info = json.loads(export_openlime(iso, tmp_path).read_text())
    assert info["type"] == "brdf" and info["colorspaces"] == {"kd": "linear", "ks": "linear"}
    files = {name: _png(tmp_path / file) / 255.0 for name, file in info["channels"].items()}
    limits = tuple(info["alphaLimits"])
    kd, ks = iso.diffuse.numpy(), iso.specular.numpy()
    normal = files["normals"] * 2 - 1
    assert np.abs(files["kd"] - kd).max() <= 0.5 / 255 + 1e-9 and np.abs(files["ks"] - ks).max() <= 0.5 / 255 + 1e-9
    assert np.abs(normal - iso.normal.numpy()).max() <= 1 / 255 + 1e-9
    alpha = iso.roughness[..., 0].numpy()
    lobe = ks.max(-1) > 0
    decoded = alpha_from_gloss(files["gloss"][..., 0], limits)
    bound = 4 * alpha**0.75 * (limits[1] ** 0.25 - limits[0] ** 0.25) / 510 * 1.01
    assert (np.abs(decoded - alpha)[lobe] <= bound[lobe]).all(), "alpha to half a gloss code"

    # The shader on exact (unquantised) values is torchspec's render: the conversion loses nothing.
    light = np.array([0.3, -0.2, 0.9327379053])
    unit = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    exact = gloss_from_alpha(np.where(lobe, alpha, limits[1]), limits)
    shader = shaderbrdf(kd, ks, iso.normal.numpy(), exact, limits, light)
    one = torch.ones(1, 1, dtype=F64)
    lights = Lights(torch.from_numpy(light[None]), Kernel("point"), one, one[0])
    ours = render(iso, lights, torch.tensor([0.0, 0, 1], dtype=F64))[..., 0, :].numpy()
    np.testing.assert_allclose(shader, ours, rtol=1e-9, atol=1e-12)
    quantised = shaderbrdf(files["kd"], files["ks"], unit, files["gloss"][..., 0], limits, light)
    print(
        "openlime 8-bit maps vs torchspec render: max error "
        f"{np.abs(quantised - ours).max() / ours.max():.4f} of the peak"
    )


def test_openlime_warns_what_the_layer_cannot_hold(tmp_path):
    maps = _maps()
    with pytest.warns(ExportWarning, match=r"anisotropic lobe \(exported isotropic.*at \d+ pixel"):
        export_openlime(maps, tmp_path)


# Normal maps in both conventions --------------------------------------------------------------------


def test_png16_normals_in_both_conventions(tmp_path):
    maps = _maps()
    meta = json.loads(export_png16(maps, tmp_path).read_text())
    opengl, directx = meta["maps"]["normal"], meta["maps"]["normal_directx"]
    assert (opengl["file"], directx["file"]) == ("normal_opengl.png", "normal_directx.png")
    up, down = _png(tmp_path / "normal_opengl.png"), _png(tmp_path / "normal_directx.png")
    assert (up[..., [0, 2]] == down[..., [0, 2]]).all()
    assert np.abs(up[..., 1] + down[..., 1] - 65535).max() <= 1, "green flipped: +y up against +y down"
    for entry, code in ((opengl, up), (directx, down)):
        decoded = np.asarray(entry["offset"]) + np.asarray(entry["scale"]) * code / 65535
        assert np.abs(decoded - maps.normal.numpy()).max() <= 2 / 131070 + 1e-12


# The command ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("to", "manifest"), [("rti", "rti.json"), ("openlime", "info.json")])
def test_command_exports_for_rti_tools(tmp_path, capsys, to, manifest):
    write_svbrdf(tmp_path / "maps", _maps())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExportWarning)  # openlime: the anisotropic lobes, tested above
        assert main(["export", str(tmp_path / "maps"), "--to", to, "-o", str(tmp_path / "out")]) == 0
    assert f"wrote {tmp_path / 'out' / manifest}" in capsys.readouterr().out
    if to == "rti":
        argv = ["export", str(tmp_path / "maps"), "--to", "rti", "-o", str(tmp_path / "e"), "--irradiance", "1.5"]
        assert main(argv) == 0
        assert json.loads((tmp_path / "e" / "rti.json").read_text())["irradiance"] == 1.5
    assert main(["export", str(tmp_path / "maps"), "--to", "openlime", "-o", str(tmp_path / "x"), "--irradiance", "2"])
    assert "mitsuba or rti export" in capsys.readouterr().err


def _no_warning():
    return contextlib.nullcontext()


# glTF-Validator -------------------------------------------------------------------------------------


def test_gltf_exports_pass_the_khronos_validator(tmp_path):
    node, modules, reason = validator()
    if modules is None:
        pytest.skip(reason)
    grey = _maps(channels=1)
    isotropic = SVBRDF(grey.normal, grey.diffuse, grey.specular, grey.roughness[..., :1].expand(-1, -1, 2))
    cases = {
        "anisotropic": _maps(rotation=torch.full((5, 7), 0.3, dtype=F64)),
        "grey-isotropic": isotropic,
        "clipped": SVBRDF(grey.normal, grey.diffuse * 3, grey.specular * 3, grey.roughness * 4),
        "one-pixel": _maps(height=1, width=1),
    }
    files = []
    for name, maps in cases.items():
        with pytest.warns(ExportWarning) if name == "clipped" else _no_warning():
            files.append(export_gltf(maps, tmp_path / name))
    reports = validate(files)
    for report in reports:
        print(
            f"{report['file']}: {report['numErrors']} errors, {report['numWarnings']} warnings, "
            f"{report['numInfos']} infos, {report['numHints']} hints"
        )
    assert [r["numErrors"] for r in reports] == [0] * len(files), reports
    assert [r["numWarnings"] for r in reports] == [0] * len(files), reports


def test_export_rti_experiment_runs(tmp_path):
    """experiments/export_rti.py on small maps (its full run, on the demo's fit: experiments/results)."""
    import importlib
    import sys
    from pathlib import Path

    root = Path(__file__).parents[1]
    if str(root / "experiments") not in sys.path:
        sys.path.insert(0, str(root / "experiments"))
    write_svbrdf(tmp_path / "maps", _maps())
    config = tmp_path / "tiny.yaml"
    config.write_text(f"maps: {tmp_path / 'maps'}\nfit_lights: 20\nheld_out_lights: 9\n")
    result = importlib.import_module("export_rti").main(["--config", str(config), "--output", str(tmp_path)])
    saved = json.loads((tmp_path / "tiny.json").read_text())
    held = saved["rti"]["held_out_lights"]
    assert held["count"] == 9 and held["file_vs_float_fit"]["max"] < 1.0, "quantisation: under a code"
    assert held["file_vs_render"]["rms"] == pytest.approx(result["rti"]["held_out_lights"]["file_vs_render"]["rms"])
    assert saved["openlime"]["alpha_relative_error"]["max"] < 0.05
