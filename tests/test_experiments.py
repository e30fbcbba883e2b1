"""The experiment scripts run end to end on tiny configs (their full runs live in experiments/)."""

import importlib
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


def _load(name):
    """Import an experiment script as a module; spawned workers find it on the same path."""
    if str(ROOT / "experiments") not in sys.path:
        sys.path.insert(0, str(ROOT / "experiments"))
    return importlib.import_module(name)


def _main(name, tmp_path, text):
    """Run the experiment ``name`` on the config ``text``, written as ``tiny.yaml``, into ``tmp_path``."""
    config = tmp_path / "tiny.yaml"
    config.write_text(text)
    return _load(name).main(["--config", str(config), "--output", str(tmp_path)])


def test_fig2_runs(tmp_path):
    result = _main(
        "fig2_crb",
        tmp_path,
        "period: 1.0\nkernels: [{label: caption, sigma: 0.05}]\nbands: [2]\nsnr_db: [0, 30]\nrepetitions: 300\n"
        "methods: [coherent, pooled, ls]\noutlier: 0.1\nseed: 0\ntwo_d: {grid: [5, 5], snr_db: [30]}\n"
        "timing: {samples: 16, locations: 2000, slow_locations: 500, repeats: 1}\n",
    )
    saved = json.loads((tmp_path / "tiny.json").read_text())
    assert saved["one_d"][0]["points"][1]["methods"]["coherent"]["mse_over_crb"] == pytest.approx(
        result["one_d"][0]["points"][1]["methods"]["coherent"]["mse_over_crb"])
    for method in ("coherent", "pooled"):
        assert 0.7 < saved["one_d"][0]["points"][1]["methods"][method]["mse_over_crb"] < 1.4
    assert (tmp_path / "tiny.png").stat().st_size > 10000


def test_fig2_rejects_unknown_keys(tmp_path):
    config = tmp_path / "typo.yaml"
    config.write_text((ROOT / "experiments" / "configs" / "fig2.yaml").read_text() + "repetitons: 5\n")
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['repetitons'\]"):
        _load("fig2_crb").main(["--config", str(config), "--output", str(tmp_path)])


def test_bench_runs(tmp_path):
    rows = _main(
        "bench_fri",
        tmp_path,
        "samples: 16\nkernel_sigma: 0.05\nsnr_db: 20.0\nlocations: 4000\nslow_locations: 500\n"
        "scipy_locations: 20\nrepeats: 1\nseed: 0\nrows: [[coherent, float32], [pooled, float32], [ls, float64]]\n",
    )
    assert [r["method"] for r in rows] == ["coherent", "pooled", "ls", "argmax + parabola", "scipy least_squares"]
    assert all(r["locations_per_second"] > 0 and r["mse_over_crb"] > 0.5 for r in rows)
    assert (tmp_path / "bench_fri.png").exists()


def test_noise_free_runs(tmp_path):
    rows = _main(
        "noise_free",
        tmp_path,
        "kernels: [{kind: box, width: 0.3}]\nsamples: [5, 16]\ngrids: [[6, 6]]\nlocations: 50\n"
        "offset: -1.0\nseed: 0\n",
    )
    assert len(rows) == 3 * 2  # sizes x dtypes
    for row in rows:
        bound = 1e-10 if row["dtype"] == "float64" else 1e-5
        assert max(row["max_error"].values()) < bound, row
    assert (tmp_path / "noise_free.png").exists()


def test_fig3_runs(tmp_path):
    one = tmp_path / "one.yaml"
    one.write_text(
        "scene: {kind: mirror, mirror: {width: 2, height: 1, kd: [1.0], ks: [0.001], alpha: [0.008, 0.008], "
        "tilt_deg: 4.7, tilt_azimuth_deg: 38.0}}\nlight: {kernel: gaussian, domain: projected, sigma: 0.03}\n"
        "layout: {kind: line, n: 30, azimuth_deg: 38.0, theta_min_deg: -30.0, theta_max_deg: 30.0}\nchannels: [Y]\n"
    )
    two = tmp_path / "two.yaml"
    two.write_text(one.read_text().replace(
        "layout: {kind: line, n: 30, azimuth_deg: 38.0, theta_min_deg: -30.0, theta_max_deg: 30.0}",
        "layout: {kind: grid, nx: 16, ny: 16, extent: 0.5, radius: 0.75}"))
    rows = _main(
        "fig3_simulation",
        tmp_path,
        f"one_d: {one}\ntwo_d: {two}\ndense: 50\nnoisy_snr_db: [40.0]\nseed: 0\nfit: {{compute: {{dtype: float64}}}}\n"
        "compare_inits: [naive]\n",
    )
    clean = {r["experiment"]: r for r in rows if r["sample_snr_db"] is None and r["init"] == "fri"}
    assert clean["1d"]["reconstruction_snr_db"] > 60 and clean["2d"]["reconstruction_snr_db"] > 65, clean
    assert len(rows) == 6 and (tmp_path / "tiny.png").stat().st_size > 10000


def test_fit_painting_runs(tmp_path, shared):
    rows = _main(
        "fit_painting",
        tmp_path,
        f"capture: {shared('painting-dev')}\nmatte_ks: 0.001\n"
        "runs: [{label: fri, frames: '::2', fit: {start: {init: fri}, model: ward-aniso}}]\n",
    )
    bound, row = rows
    assert bound["held_out_psnr_db"] > row["held_out_psnr_db"] > 40.0
    assert row["normal_deg"] < 0.5 and row["kd"] < 0.03 and row["varnished_alpha"] < 0.1
    assert row["matte_share_ks0"] > 0.95


def test_bench_fit_runs(tmp_path):
    rows = _main(
        "bench_fit",
        tmp_path,
        f"size: 12\ngrid: 8\nextent: 0.6\nkernel_sigma: 0.08\nphotons_per_unit: 100000.0\nseed: 3\nthreads: 2\n"
        f"scipy_pixels: 2\ncache: {tmp_path / 'cache'}\nfit: {{model: ward-iso}}\n",
    )
    ours, scipy = rows
    assert ours["pixels"] == 144 and ours["pixels_per_second"] > 0 and ours["peak_mb"] > 0
    assert scipy["pixels"] == 2 and scipy["seconds"] > 0
    assert ours["sampled_pixels"]["normal_deg"] < 0.5 and scipy["sampled_pixels"]["normal_deg"] < 0.5


FIG5_TINY = (
    "mirror: {width: 1, height: 1, kd: [0.02], ks: [0.8], alpha: [0.005, 0.005]}\ntilts_deg: [2.6]\n"
    "azimuth_deg: 0.0\nframes: 40\ntheta_min_deg: -15.0\ntheta_max_deg: 15.0\n"
    "lights: [{label: gauss, kernel: gaussian, domain: angular, sigma: 0.03}]\nstep: 3\n"
    "sensor: {photons_per_unit: 100.0, read_noise: 0.01}\nseeds: 2\nfri_coefficients: 2\nsource: simulate\n"
    "calibration: {size: 16, mirror_alpha: 0.005}\n"
)


def test_fig5_runs(tmp_path):
    result = _main("fig5_mirror", tmp_path, FIG5_TINY)
    saved = json.loads((tmp_path / "fig5" / "tiny.json").read_text())
    assert saved["methods"].keys() == result["methods"].keys() and saved["trials_per_method"] == 6
    fri, point = saved["methods"]["gauss: FRI (13)"], saved["methods"]["point: argmax + parabola (13)"]
    # Measured 0.010 deg against 0.64 deg: samples 2.3 deg apart bracket a 0.4 deg wide point-light peak.
    assert fri["rms_deg"] < 0.03 and point["rms_deg"] > 0.2, (fri, point)
    calibration = saved["calibration"][0]
    assert calibration["profile_relative_l2"] < 0.05, calibration["summary"]  # measured 1.5 %
    assert (tmp_path / "fig5" / "tiny.png").stat().st_size > 10000


def test_fig5_dome_frames_are_the_simulation():
    """The emulated dome (emulator, serial client, simulated camera, acquisition writing EXRs) gives
    the directly rendered frames, to float32 rounding."""
    import yaml

    from torchspec.config import from_mapping
    from torchspec.simulate import LightConfig

    fig5 = _load("fig5_mirror")
    settings = from_mapping({**yaml.safe_load(FIG5_TINY), "frames": 20, "source": "dome"}, fig5.Settings)
    centres, acquired = fig5._acquire(settings, 2.6, LightConfig(kernel="point"))
    direct = fig5._simulate(settings, 2.6, LightConfig(kernel="point"))
    error = float(((acquired - direct).abs() / direct.abs().max()).max())
    assert acquired.shape == (1, 20) and error < 1e-6, f"relative difference {error:.3g}"


def test_two_lobes_runs(tmp_path):
    result = _main(
        "two_lobes",
        tmp_path,
        "size: 16\nseed: 5\ngrid: 10\nkernel_sigma: 0.08\nphotons_per_unit: 100000.0\nframes: '::2'\n"
        "models: [auto, ward-iso]\nscipy_pixels: 2\n",
    )
    auto, one = result["rows"]
    box = auto["models_per_region"]["dual"]
    assert box.get("ward-dual", 0) >= 0.9 * result["dual_box_pixels"] > 0, box
    assert auto["held_out_psnr_db"]["dual_box"] > one["held_out_psnr_db"]["dual_box"] + 10
    assert auto["dual_box"]["alpha2"] < 0.05 and "alpha2" not in one["dual_box"]
    base = result["baseline"]
    assert base["scipy_pixels"] == 2 and base["scipy_ms_per_pixel"] > 0
    assert base["scipy"]["alpha2"] == pytest.approx(base["torchspec"]["alpha2"], rel=0.05, abs=1e-3)
    assert json.loads((tmp_path / "tiny.json").read_text())["coverage"].keys() == result["coverage"].keys()


def test_identical_outputs_finds_every_difference(tmp_path):
    """``experiments/identical_outputs.py``: equal saved fits compare identical (NaN equal to NaN); a
    changed tensor or number is named; timings are left out of the JSON comparison."""
    import torch

    proof = _load("identical_outputs")
    saved = {"quality": torch.tensor([0.5, float("nan")]), "stats": {"models": {"diffuse": 3}}}
    for name in ("old", "new", "changed"):
        (tmp_path / name).mkdir()
    torch.save(saved, tmp_path / "old" / "auto.pt")
    torch.save(saved, tmp_path / "new" / "auto.pt")
    torch.save({**saved, "quality": torch.tensor([0.5, 0.0])}, tmp_path / "changed" / "auto.pt")
    assert proof.compare(tmp_path / "old", tmp_path / "new") == []
    assert proof.compare(tmp_path / "old", tmp_path / "changed") == ["auto quality"]
    committed = {"rows": [{"psnr": 60.0, "seconds": 1.0, "nan": float("nan")}]}
    assert proof.numbers(committed, {"rows": [{"psnr": 60.0, "seconds": 2.0, "nan": float("nan")}]}) == []
    assert proof.numbers(committed, {"rows": [{"psnr": 61.0, "seconds": 1.0, "nan": float("nan")}]}) == [
        "/rows[0]/psnr: 60.0 against 61.0"
    ]


def _rti_folder(folder, directions, normals):
    """A Lambertian relief under point lights as an RTI capture: 8-bit sRGB PNGs and dirs.lp."""
    import numpy as np
    from PIL import Image

    folder.mkdir(parents=True)
    lines = [str(len(directions))]
    for k, d in enumerate(directions):
        linear = (normals @ np.asarray(d)).clip(0, None)[..., None] * np.array([0.7, 0.5, 0.3])
        encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        Image.fromarray((encoded.clip(0, 1) * 255).round().astype(np.uint8)).save(folder / f"image{k:02d}.png")
        lines.append(f"image{k:02d}.png {d[0]:.6f} {d[1]:.6f} {d[2]:.6f}")
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")


def _relief_normals(ax: float, ay: float):
    """``(8, 8, 3)`` the unit normals of a small periodic relief of slopes ``ax``, ``ay``."""
    import math

    import numpy as np

    y, x = np.mgrid[0:8, 0:8] / 8.0
    slope = np.stack([ax * np.sin(2 * math.pi * x), ay * np.cos(2 * math.pi * y), np.ones_like(x)], -1)
    return slope / np.linalg.norm(slope, axis=-1, keepdims=True)


def _ring(count: int, elevation: float, turn: float) -> list[tuple[float, float, float]]:
    """``count`` light directions at ``elevation`` (radians), evenly around from azimuth ``turn``."""
    import math

    import numpy as np

    return [
        (math.cos(elevation) * math.cos(a), math.cos(elevation) * math.sin(a), math.sin(elevation))
        for a in np.linspace(turn, turn + 2 * math.pi, count, endpoint=False)
    ]


def _synth_folder(folder, dome, test, normals):
    """A SynthRTI-like capture: ``Dome/`` and ``Test/`` (:func:`_rti_folder`), ``Dome/normals.png``."""
    import numpy as np
    from PIL import Image

    _rti_folder(folder / "Dome", dome, normals)
    _rti_folder(folder / "Test", test, normals)
    Image.fromarray(((normals + 1) / 2 * 255).round().astype(np.uint8)).save(folder / "Dome" / "normals.png")


def test_rti_relight_runs(tmp_path):
    """PTM, HSH and torchspec on a tiny relief, as a real capture and as a SynthRTI one (Dome/, Test/,
    normals.png): HSH and torchspec predict a Lambertian relief's left-out lights, the normals are found."""
    normals = _relief_normals(0.3, 0.2)
    dome = _ring(6, 0.5, 0.0) + _ring(6, 1.0, 0.3)
    _rti_folder(tmp_path / "data" / "real", dome, normals)
    _synth_folder(tmp_path / "data" / "synth", dome, _ring(4, 0.8, 0.7), normals)
    result = _main(
        "rti_relight",
        tmp_path,
        f"data: {tmp_path / 'data'}\ncaptures: [real, synth]\ndownsample: 1\nmodels: [auto, diffuse]\nthreads: 1\n"
        "calibrations: [auto, dome]\n",
    )
    real, synth = result["captures"]
    assert real["left_out"] == [2, 7] and real["size"] == [8, 8]
    methods = {row["method"]: row for row in real["rows"]}
    assert list(methods) == [
        "PTM",
        "HSH",
        "RBF",
        "torchspec auto",
        "torchspec auto + term",
        "torchspec auto (dome)",
        "torchspec auto (dome) + term",
        "torchspec diffuse",
        "torchspec diffuse + term",
        "torchspec diffuse (dome)",
        "torchspec diffuse (dome) + term",
    ]
    # distant lights: a dome of no radius explains them better, they stay distant
    assert methods["torchspec diffuse (dome)"]["dome_radius"] is None
    assert synth["normals"]["torchspec auto (dome)_deg"] < 3
    # a Lambertian capture: the physical model predicts it, and the term (kept only where it
    # predicts left-out frames better) costs it little
    assert methods["torchspec diffuse + term"]["psnr_db"] > methods["torchspec diffuse"]["psnr_db"] - 1.0
    assert 0 <= methods["torchspec diffuse + term"]["term_share"] <= 1
    assert methods["torchspec diffuse"]["psnr_db"] > 35 and methods["torchspec diffuse"]["lobe_share"] == 0
    assert 0.9 < methods["torchspec diffuse"]["worst_brightness_ratio"] < 1.1
    assert all(0 <= row["ssim"] <= 1 and row["fit_seconds"] >= 0 for row in real["rows"])
    assert [row["method"] for row in synth["dome_to_test"]][:3] == ["PTM", "HSH", "RBF"]
    assert real["transfer"] in ("response", "srgb")  # untagged 8-bit PNGs: the curve estimated
    assert synth["normals"]["torchspec_deg"] < 3 and synth["normals"]["least_squares_ps_deg"] < 3
    assert json.loads((tmp_path / "tiny.json").read_text())["captures"][0]["capture"] == "real"


def test_term_bases_runs(tmp_path):
    """Each basis of the term on a tiny Lambertian relief: every row scored, the maps' own residual
    (a Lambertian relief, distant lights) small, so the maps alone predict the left-out frames."""
    import math

    import numpy as np

    y, x = np.mgrid[0:8, 0:8] / 8.0
    slope = np.stack([0.3 * np.sin(2 * math.pi * x), 0.2 * np.cos(2 * math.pi * y), np.ones_like(x)], -1)
    normals = slope / np.linalg.norm(slope, axis=-1, keepdims=True)
    dome = [
        (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))
        for e, turn in ((0.5, 0.0), (0.8, 0.2), (1.1, 0.4))
        for a in np.linspace(turn, turn + 2 * math.pi, 8, endpoint=False)
    ]
    _rti_folder(tmp_path / "data" / "real", dome, normals)
    text = f"data: {tmp_path / 'data'}\ncaptures: [real]\ndownsample: 1\nthreads: 1\nsizes: [4]\n"
    result = _main("term_bases", tmp_path, text)
    (capture,) = result["captures"]
    scores = capture["psnr_db"]
    expected = ["PTM", "HSH", "RBF", "maps", "maps + HSH3", "maps + RBF", "maps + PCA 4", "maps + centres 4"]
    assert list(scores) == [*expected, "RBF + maps / 4"]
    assert all(math.isfinite(v) for v in scores.values()) and scores["maps"] > 35
    assert json.loads((tmp_path / "tiny.json").read_text())["captures"][0]["frames"] == 24


TINY_PAIR = """
data: {data}
models: [auto, diffuse]
timed: [diffuse]
warm_up: false
pairs:
  - {{name: absent, fitted: no-such-capture, predicted: no-such-relight}}
  - name: sim
    repeats: 2
    simulated:
      scene: {{painting: {{width: 8, height: 8, seed: 3}}}}
      fitted:
        light: {{kernel: gaussian, domain: projected, sigma: 0.08}}
        layout: {{kind: grid, nx: 8, ny: 8, extent: 0.7, radius: 0.8}}
        irradiance: [1.0, 0.8, 0.6]
        exposure: [0.5, 2.0]
      predicted:
        light: {{kernel: point}}
        layout: {{kind: scattered, n: 6, theta_max_deg: 60.0, seed: 2}}
"""


def test_relight_transfer_runs(tmp_path):
    """A noise-free Ward pair: the true maps predict the other capture best (to float32 rounding of
    the recorded frames); each fitted row says its models, times and errors; an absent shared pair
    is skipped, not an error."""
    result = _main("relight_transfer", tmp_path, TINY_PAIR.format(data=tmp_path / "no-shared-data"))
    saved = json.loads((tmp_path / "tiny.json").read_text())
    assert [p["pair"] for p in saved["pairs"]] == ["sim"] and saved["peak"] == result["peak"]
    rows = {r["row"]: r for r in result["pairs"][0]["rows"]}
    assert list(rows) == ["auto", "diffuse", "truth"]
    assert rows["truth"]["psnr_db"] > 100 and all(r["psnr_db"] < rows["truth"]["psnr_db"] for r in rows.values()
                                                  if r["row"] != "truth")
    assert rows["diffuse"]["model_share"] == {"diffuse": 1.0}
    assert rows["auto"]["psnr_db"] > rows["diffuse"]["psnr_db"], "the varnish's lobes predict the point lights"
    for row in (rows["auto"], rows["diffuse"]):
        assert sum(row["model_share"].values()) == pytest.approx(1.0)
        assert 0 <= row["relative_rms"] < 1 and row["fit_seconds"] > 0 and row["fit_cpu_seconds"] > 0
    assert len(rows["auto"]["fit_seconds_all"]) == 1 and len(rows["diffuse"]["fit_seconds_all"]) == 2
    assert result["pairs"][0]["mirror"]["pixels"] == round(64 * rows["auto"]["model_share"].get("ward-dual", 0.0))


def test_mirror_brightness_of_a_diffuse_surface():
    """Under a unit point light at the mirror direction of the view about a normal tilted by t, a
    Lambertian pixel gives k_d / pi cos t; blocks of pixels keep each pixel's own light."""
    import math

    import torch

    from torchspec.model.brdf import SVBRDF

    tilt = torch.tensor([0.0, 5.0, 10.0, 20.0, 30.0], dtype=torch.float64).deg2rad()
    normal = torch.stack([torch.sin(tilt), torch.zeros_like(tilt), torch.cos(tilt)], -1)
    kd = torch.tensor([[0.2], [0.4], [0.6], [0.8], [1.0]], dtype=torch.float64)
    maps = SVBRDF(normal, kd, torch.zeros_like(kd), torch.full((5, 2), 0.1, dtype=torch.float64))
    got = _load("relight_transfer").mirror_brightness(maps, normal, block=2)
    assert torch.allclose(got, kd[:, 0] / math.pi * torch.cos(tilt), rtol=1e-9)


def test_broad_lobes_measures_what_it_says():
    """``measure`` on a made-up fit: normals off by known angles, qualities and models."""
    import math
    from types import SimpleNamespace

    import torch

    from torchspec.pipeline import MODEL_CODES
    from torchspec.pipeline.flags import FLAGS, bit

    broad = _load("broad_lobes")
    off_deg = torch.tensor([0.0, 1.0, 3.0, 10.0, 0.5, 4.0], dtype=torch.float64)
    tilt = off_deg.deg2rad()
    fitted = torch.stack([torch.sin(tilt), torch.zeros_like(tilt), torch.cos(tilt)], -1)
    truth = SimpleNamespace(normal=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(6, 3))
    regions = torch.tensor([1, 1, 1, 1, 0, 0])  # varnished x 4, matte x 2
    d, w = MODEL_CODES.index("diffuse"), MODEL_CODES.index("ward-iso")
    result = SimpleNamespace(
        svbrdf=SimpleNamespace(normal=fitted.reshape(2, 3, 3)),
        quality=torch.tensor([[1.0, 1.0, 1.0], [0.0, 1.0, 0.2]]),
        model=torch.tensor([[w, w, d], [d, d, d]], dtype=torch.int8),
        flags=torch.tensor([[0, 0, bit("misfit")], [bit("misfit") | bit("astray"), 0, 0]], dtype=torch.int16),
    )
    m = broad.measure(result, truth, regions, broad.Settings(scene=None, lighting=None))
    assert (m["trusted"], m["trusted_off"]) == (4, 1)  # quality >= 0.5: 0, 1, 3, 0.5 deg; 3 deg is off
    assert m["trusted_off_by_model"] == {"diffuse": 1} and m["trusted_off_varnished"] == 1
    assert m["trusted_off_share"] == pytest.approx(0.25) and m["trusted_off_share_of_all"] == pytest.approx(1 / 6)
    assert m["normal"]["median_deg"] == pytest.approx(2.0) and m["normal_varnished"]["median_deg"] == pytest.approx(
        2.0)
    assert m["models_varnished"] == {"ward-iso": 2, "diffuse": 2} and m["models_matte"] == {"diffuse": 2}
    missed = m["varnished_diffuse"]
    assert missed["pixels"] == 2 and missed["normal_max_deg"] == pytest.approx(10.0)
    assert missed["quality_at_least_min"] == 1 and missed["flags"] == {
        name: {"misfit": 2, "astray": 1}.get(name, 0) for name in FLAGS}
    assert math.isfinite(missed["quality_median"])


def test_broad_lobes_runs(tmp_path):
    result = _main(
        "broad_lobes",
        tmp_path,
        "scene: {painting: {width: 8, height: 8, seed: 11, ks_range: [0.2, 0.4], alpha_range: [0.2, 0.3], "
        "gilded: null}}\nlighting: {light: {kernel: gaussian, domain: angular, sigma: 0.06}, "
        "layout: {kind: grid, nx: 6, ny: 6, extent: 0.6, radius: 0.9}, irradiance: [1.0, 0.85, 0.7], "
        "exposure: [0.5, 2.0]}\nwarm_up: false\n",
    )
    (row,) = result["rows"]
    assert json.loads((tmp_path / "tiny.json").read_text())["rows"][0].keys() == row.keys()
    assert row["pixels"] == 64 == row["varnished_pixels"] + row["matte_pixels"] and row["varnished_pixels"] > 0
    assert sum(row["models_varnished"].values()) == row["varnished_pixels"]
    assert row["varnished_diffuse"]["pixels"] == row["models_varnished"].get("diffuse", 0)
    assert 0 <= row["trusted_off"] <= row["trusted"] <= 64 and 0 <= row["trusted_off_share"] <= 1
    for spread in (row["normal"], row["normal_matte"]):
        assert 0 <= spread["median_deg"] <= spread["p90_deg"] < 45


def test_auto_gives_broad_strong_lobes_a_lobe_and_trusts_no_wrong_normal(tmp_path):
    """Broad, strong lobes (alpha 0.2-0.3, k_s 0.2-0.4) under an angular Gaussian light on an 8 x 8
    grid, per-channel irradiance and exposure, leave no peak to detect (a tilted normal absorbs
    them): auto climbs from the misfit of the fit without a lobe; a trusted normal is right."""
    result = _main(
        "broad_lobes",
        tmp_path,
        "scene: {painting: {width: 24, height: 24, seed: 11, ks_range: [0.2, 0.4], alpha_range: [0.2, 0.3], "
        "gilded: null}}\nlighting: {light: {kernel: gaussian, domain: angular, sigma: 0.06}, "
        "layout: {kind: grid, nx: 8, ny: 8, extent: 0.6, radius: 0.9}, sensor: {photons_per_unit: 100000.0, "
        "seed: 3}, irradiance: [1.0, 0.85, 0.7], exposure: [0.5, 2.0], seed: 4}\nwarm_up: false\n",
    )
    m = result["rows"][0] if "rows" in result else result
    varnished = m["models_varnished"]
    assert varnished.get("diffuse", 0) <= 0.05 * sum(varnished.values()), varnished
    assert m["trusted_off_share"] <= 0.01, m["trusted_off_by_model"]


def test_light_calibration_runs(tmp_path):
    """A tiny simulated dome (no real captures): the per-pixel near-light renderer agrees with
    render_image for distant lights, and the calibration recovers gains and positions."""
    result = _main(
        "light_calibration",
        tmp_path,
        "data: ../shared/data/rti\nsimulated: {size: 24, rings: [[20, 6], [45, 6], [70, 4]], radius: 3.0,\n"
        "  gain_spread: 0.3, seed: 1, sensor: {photons_per_unit: 1.0e+6}, iterations: 8}\n"
        "real: []\ndownsample: 4\niterations: 8\nthreads: 1\n",
    )
    sim = result["simulated"]
    assert sim["renderer_check"] < 1e-7  # 1 / R of the radius 1e9 stand-in for distant lights
    assert sim["gain_rel_error"]["max"] < 0.05 and sim["position_rel_error"]["max"] < 0.1
    assert json.loads((tmp_path / "light_calibration.json").read_text())["simulated"]["frames"] == 16


def test_left_out_brightness_finds_each_frames_own_gain(tmp_path):
    """A Lambertian relief relit with HSH: its left-out frames' brightness is predicted (within the
    issue's 10 %) until each photograph gets its own flash intensity; then the misses follow those
    intensities, which the nearest lights' errors do not predict."""
    import math

    import numpy as np
    from PIL import Image

    y, x = np.mgrid[0:8, 0:8] / 8.0
    slope = np.stack([0.3 * np.sin(2 * math.pi * x), 0.2 * np.cos(2 * math.pi * y), np.ones_like(x)], -1)
    normals = slope / np.linalg.norm(slope, axis=-1, keepdims=True)
    dome = [
        (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))
        for e, turn in ((0.6, 0.0), (0.85, 0.2), (1.1, 0.4), (1.35, 0.6))
        for a in np.linspace(turn, turn + 2 * math.pi, 10, endpoint=False)
    ]
    _rti_folder(tmp_path / "data" / "plain", dome, normals)
    gains = np.random.default_rng(4).uniform(0.7, 1.3, len(dome))
    folder = tmp_path / "data" / "flashes"
    _rti_folder(folder, dome, normals)
    for k, gain in enumerate(gains):  # each photograph brighter or darker by its gain (linear values)
        path = folder / f"image{k:02d}.png"
        code = np.asarray(Image.open(path)).astype(np.float64) / 255
        linear = np.where(code <= 0.04045, code / 12.92, ((code + 0.055) / 1.055) ** 2.4) * gain
        encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        Image.fromarray((encoded.clip(0, 1) * 255).round().astype(np.uint8)).save(path)
    result = _main(
        "left_out_brightness",
        tmp_path,
        f"data: {tmp_path / 'data'}\ncaptures: [plain, flashes]\ndownsample: 1\nneighbours: [1, 3]\nthreads: 1\n",
    )
    plain, flashes = result["captures"]
    assert plain["left_out"] == list(range(2, 40, 5)) and len(plain["elevation_deg"]) == 8
    assert plain["HSH"]["as fitted"]["off"] == 0 and abs(plain["HSH"]["as fitted"]["worst_ratio"] - 1) < 0.1
    found = np.log(flashes["HSH"]["as fitted"]["ratios"])
    assert flashes["HSH"]["as fitted"]["off"] >= 3
    # the misses are the frames' own gains: log ratio against -log gain
    assert np.corrcoef(found, -np.log(gains[plain["left_out"]]))[0, 1] > 0.8
    for label in ("corrected, 1 nearest", "corrected, 3 nearest"):
        assert flashes["HSH"][label]["off"] >= 3
    assert json.loads((tmp_path / "tiny.json").read_text())["captures"][1]["capture"] == "flashes"


def test_neighbour_correction_is_the_weighted_mean_of_the_nearest_errors():
    import torch

    correction = _load("left_out_brightness").neighbour_correction
    angles = torch.tensor([0.1, 0.2, 0.4, 1.0, 1.4], dtype=torch.float64)
    directions = torch.stack([torch.sin(angles), torch.zeros_like(angles), torch.cos(angles)], -1)
    directions = torch.cat([directions, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)])  # frame 5
    own = torch.tensor([1.2, 0.8, 2.0, 0.5, 3.0], dtype=torch.float64)
    fitted, predicted = [0, 1, 2, 3, 4], [5]
    assert float(correction(directions, fitted, own, predicted, 1)) == pytest.approx(1.2)
    weights = 1 / angles[:2]
    expected = torch.exp((weights * own[:2].log()).sum() / weights.sum())
    assert float(correction(directions, fitted, own, predicted, 2)) == pytest.approx(float(expected))
    flat = torch.full_like(own, 0.9)
    assert float(correction(directions, fitted, flat, predicted, 5)) == pytest.approx(0.9)


def test_bench_gpu_runs(tmp_path):
    """On the CPU at a tiny size: every part runs and the two fits of one capture agree exactly."""
    out = _main(
        "bench_gpu",
        tmp_path,
        f"size: 10\ngrid: 6\nextent: 0.6\ncache: {tmp_path / 'cache'}\ndevice: cpu\ncpu_threads: 2\n"
        "large_width: 24\nlarge_height: 16\nlarge_frames: 12\nbudget_s: 400\n",
    )
    for label in ("default cold", "default warm", "ward-iso cold", "ward-iso warm", "default cpu"):
        row = out["fits"][label]
        assert row["pixels_per_second"] > 0 and row["peak_mb"] > 0 and row["device"] == "cpu", label
    agreement = out["agreement"]
    assert agreement["same_model"] == 1 and agreement["normal_deg_p99"] == 0 and agreement["untrusted_only_one"] == 0
    large = out["large"]
    assert large["frames"] == 12 and large["pixels"] == 24 * 16
    assert large["import_note"] == "" and large["fit_note"] == "", large
    assert large["jpegs_to_maps_seconds"] > 0 and "total" in large["fit_stage_seconds"]
    assert json.loads((tmp_path / "tiny.json").read_text())["large"]["frames"] == 12


def test_shadows_synthetic_runs(tmp_path):
    result = _main(
        "shadows_synthetic",
        tmp_path,
        "size: 24\nlights: 3\nbrute_step: 0.125\nrelief: {bumps: 3, seed: 1}\n",
    )
    saved = json.loads((tmp_path / "shadows_synthetic.json").read_text())
    exact = saved["height"]["exact_unweighted"]["rms_px"]
    assert exact == pytest.approx(result["height"]["exact_unweighted"]["rms_px"])
    assert saved["height"]["noisy_weighted"]["rms_px"] < saved["height"]["noisy_unweighted"]["rms_px"]
    assert saved["shadows"]["agreement"] > 0.95


def test_shadow_depth_runs(tmp_path):
    """The depth study on a SynthRTI-like relief of true normals (Dome/, Test/, normals.png): a
    shallow Lambertian relief casts no shadow at these elevations, so Lambert with the true normals
    predicts the Test lights alike at every depth, to the precision of normals.png's 8-bit codes
    (measured 38.4 dB)."""
    normals = _relief_normals(0.2, 0.1)
    _synth_folder(tmp_path / "data" / "synth", _ring(6, 0.7, 0.0) + _ring(6, 1.1, 0.3), _ring(4, 0.9, 0.7), normals)
    result = _main(
        "shadow_depth", tmp_path, f"data: {tmp_path / 'data'}\ncaptures: [synth]\ndownsample: 1\ndepths: [1.0, 2.0]\n"
    )
    (synth,) = result["captures"]
    assert synth["size"] == [8, 8] and list(synth["depths"]) == ["1.0", "2.0"]
    assert min(synth["depths"].values()) > 35.0 and synth["full_resolution_height_psnr_db"] > 35.0
    assert abs(synth["depths"]["1.0"] - synth["depths"]["2.0"]) < 0.01  # no shadow: the depth changes nothing
