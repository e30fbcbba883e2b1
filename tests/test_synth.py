import dataclasses
import json
import math

import pytest
import torch

from torchspec.config import ConfigError, from_mapping, load_config
from torchspec.simulate.synth import (
    DUAL,
    GILDED,
    MATTE,
    VARNISHED,
    DualConfig,
    GildedConfig,
    MirrorConfig,
    PaintingConfig,
    SensorConfig,
    mirror,
    painting,
    sense,
)

F64 = torch.float64


def tilt_deg(normal):
    n = normal.to(F64)
    return torch.rad2deg(torch.atan2(torch.linalg.vector_norm(n[..., :2], dim=-1), n[..., 2]))


@pytest.fixture(scope="module")
def default_painting():
    return painting(PaintingConfig(), dtype=F64)


def test_painting_shapes_dtypes_devices(dtype, device):
    config = PaintingConfig(width=40, height=24)
    svbrdf, regions = painting(config, dtype=dtype, device=device)
    assert tuple(svbrdf.shape) == (24, 40)
    for name, tail in [("normal", 3), ("diffuse", 3), ("specular", 3), ("roughness", 2)]:
        value = getattr(svbrdf, name)
        assert tuple(value.shape) == (24, 40, tail), name
        assert value.dtype == dtype and value.device.type == device.type, name
    assert svbrdf.rotation is None and svbrdf.channels == ("R", "G", "B")
    assert regions.shape == (24, 40) and regions.dtype == torch.int64 and regions.device.type == device.type
    assert set(regions.unique().tolist()) == {MATTE, VARNISHED, GILDED}


def test_normals_unit_with_capped_tilt(dtype):
    config = PaintingConfig(seed=3)
    svbrdf, regions = painting(config, dtype=dtype)
    n = svbrdf.normal
    err = (torch.linalg.vector_norm(n, dim=-1) - 1).abs().max()
    assert err < 10 * torch.finfo(dtype).eps, f"max |n| error {err:.3g}"
    assert (n[..., 2] > 0).all()
    tilt = tilt_deg(n)
    assert tilt.max() <= config.max_tilt_deg + 1e-4, f"max tilt {tilt.max():.6f} deg"
    assert tilt[regions == GILDED].max() <= config.gilded.max_tilt_deg + 1e-4
    # Weave and strokes tilt most pixels by a few degrees, a few of them up to the cap.
    assert 1.0 < tilt.median() < 5.0, f"median tilt {tilt.median():.3g} deg"
    assert tilt.max() > 0.9 * config.max_tilt_deg


def test_region_maps(default_painting):
    svbrdf, regions = default_painting
    config = PaintingConfig()
    ks, alpha, kd = svbrdf.specular, svbrdf.roughness, svbrdf.diffuse
    matte, varnished, gilded = regions == MATTE, regions == VARNISHED, regions == GILDED
    assert (ks[matte] == 0).all() and (alpha[matte] == 0).all()

    lo, hi = config.ks_range
    assert ((ks[varnished] >= lo) & (ks[varnished] <= hi)).all()
    assert (ks[varnished] == ks[varnished][:, :1]).all(), "varnish k_s must be grey"
    a_lo, a_hi = config.alpha_range
    assert ((alpha[varnished] >= a_lo) & (alpha[varnished] <= a_hi)).all()
    assert (alpha[varnished][:, 0] == alpha[varnished][:, 1]).all(), "varnish must be isotropic"
    # Spatially smooth k_s and alpha: a spread of values, small steps between neighbours.
    assert ks[varnished].std() > 0.02 and alpha[varnished].std() > 0.01
    both = varnished[:, 1:] & varnished[:, :-1]
    step = (ks[:, 1:, 0] - ks[:, :-1, 0])[both].abs().max()
    assert step < 0.25 * (hi - lo), f"max k_s step between neighbours {step:.3g}"

    box = config.gilded
    assert (ks[gilded] == torch.tensor(box.ks, dtype=F64)).all()
    assert (alpha[gilded] == torch.tensor(box.alpha, dtype=F64)).all() and box.alpha[0] != box.alpha[1]
    assert (kd[gilded] == torch.tensor(box.kd, dtype=F64)).all()


def test_gilded_box_position():
    # Non-square, so that a swap of x and y shows: the box is (x0, y0, x1, y1) with y down the rows.
    config = PaintingConfig(width=40, height=20, gilded=GildedConfig(box=(0.5, 0.0, 1.0, 0.25)))
    _, regions = painting(config, dtype=F64)
    expected = torch.zeros(20, 40, dtype=torch.bool)
    expected[:5, 20:] = True
    assert torch.equal(regions == GILDED, expected)
    _, regions = painting(dataclasses.replace(config, gilded=None), dtype=F64)
    assert not (regions == GILDED).any()


def test_kd_within_range(default_painting):
    svbrdf, regions = default_painting
    lo, hi = PaintingConfig().kd_range
    kd = svbrdf.diffuse[regions != GILDED]
    assert kd.min() >= lo and kd.max() <= hi
    assert kd.max() - kd.min() > 0.5 * (hi - lo), "pigments should span most of kd_range"


@pytest.mark.parametrize("fraction", [0.2, 0.55, 0.8])
@pytest.mark.parametrize("seed", [1, 2])
def test_varnish_fraction(fraction, seed):
    _, regions = painting(PaintingConfig(seed=seed, varnish_fraction=fraction), dtype=F64)
    measured = (regions == VARNISHED).float().mean()
    assert abs(measured - fraction) < 0.15, f"varnished fraction {measured:.3f} for {fraction}"


def test_weave_period_and_amplitude():
    config = PaintingConfig(width=86, height=43, strokes=0, gilded=None)  # 20 and 10 weave periods
    svbrdf, _ = painting(config, dtype=F64)
    slope_x = -svbrdf.normal[..., 0] / svbrdf.normal[..., 2]
    spectrum = torch.fft.rfft2(slope_x).abs()
    peak = divmod(int(spectrum.argmax()), spectrum.shape[1])
    assert peak[1] == 20 and peak[0] in (10, 33), f"weave peak at frequency {peak}"
    expected = math.degrees(math.atan(config.weave_amp * math.tan(math.radians(config.max_tilt_deg))))
    tilt = tilt_deg(svbrdf.normal).max()
    assert abs(tilt - expected) < 0.05 * expected, f"weave tilt {tilt:.3f} deg, expected {expected:.3f}"


def test_deterministic_and_seed_dependent():
    a, ra = painting(PaintingConfig(seed=5), dtype=torch.float32)
    b, rb = painting(PaintingConfig(seed=5), dtype=torch.float32)
    c, rc = painting(PaintingConfig(seed=6), dtype=torch.float32)
    for name in ("normal", "diffuse", "specular", "roughness"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert not torch.equal(getattr(a, name), getattr(c, name)), name
    assert torch.equal(ra, rb) and not torch.equal(ra, rc)


def test_layers_are_independent_streams():
    a, ra = painting(PaintingConfig(strokes=20), dtype=F64)
    b, rb = painting(PaintingConfig(strokes=5), dtype=F64)
    assert torch.equal(ra, rb) and torch.equal(a.specular, b.specular) and torch.equal(a.roughness, b.roughness)


def test_float32_matches_float64():
    s32, r32 = painting(PaintingConfig(seed=11), dtype=torch.float32)
    s64, r64 = painting(PaintingConfig(seed=11), dtype=F64)
    assert torch.equal(r32, r64)
    for name in ("normal", "diffuse", "specular", "roughness"):
        err = (getattr(s32, name).to(F64) - getattr(s64, name)).abs().max()
        assert err < 1e-6, f"{name}: max error {err:.3g}"


@pytest.mark.parametrize(
    "change,match",
    [
        ({"varnish_fraction": 1.5}, "varnish_fraction"),
        ({"kd_range": (0.5, 0.1)}, "kd_range"),
        ({"max_tilt_deg": 95.0}, "max_tilt_deg"),
        ({"gilded": GildedConfig(box=(0.5, 0.1, 0.2, 0.9))}, "gilded.box"),
        ({"gilded": GildedConfig(box=(0.1, 0.2, 0.3))}, "gilded.box"),
        ({"stroke_width": (0.0, 2.0)}, "stroke_width"),
        ({"dual": DualConfig(box=(0.5, 0.1, 0.2, 0.9))}, "dual.box"),
        ({"dual": DualConfig(ks2=-0.1)}, "dual.ks and dual.ks2"),
        ({"dual": DualConfig(alpha2=0.0)}, "dual.alpha and dual.alpha2"),
    ],
)
def test_painting_rejects_bad_settings(change, match):
    with pytest.raises(ValueError, match=match):
        painting(dataclasses.replace(PaintingConfig(), **change), dtype=F64)


@pytest.mark.parametrize("tilt,azimuth", [(3.0, -20.0), (10.0, 135.0), (1.0, -110.0), (0.0, 0.0)])
def test_mirror_tilt_and_azimuth(dtype, device, tilt, azimuth):
    config = MirrorConfig(width=5, height=3, tilt_deg=tilt, tilt_azimuth_deg=azimuth)
    svbrdf, regions = mirror(config, dtype=dtype, device=device)
    assert tuple(svbrdf.shape) == (3, 5) and svbrdf.normal.dtype == dtype and svbrdf.normal.device.type == device.type
    assert (regions == 1).all() and regions.dtype == torch.int64
    n = svbrdf.normal.to(F64)
    assert (n == n[0, 0]).all() and (svbrdf.specular == svbrdf.specular[0, 0]).all()
    err_tilt = (tilt_deg(n) - tilt).abs().max()
    assert err_tilt < 1e-6, f"tilt error {err_tilt:.3g} deg"
    if tilt > 0:
        err_azimuth = (torch.rad2deg(torch.atan2(n[..., 1], n[..., 0])) - azimuth).abs().max()
        assert err_azimuth < 1e-6, f"azimuth error {err_azimuth:.3g} deg"
    assert torch.equal(svbrdf.roughness[0, 0], torch.tensor(config.alpha, dtype=dtype, device=device))


def test_mirror_grey_specular():
    svbrdf, _ = mirror(MirrorConfig(ks=(0.5,)), dtype=F64)
    assert svbrdf.specular.shape == (16, 16, 1)


def test_sense_without_noise_is_exposure(dtype, device):
    values = torch.rand(4, 5, 3, dtype=dtype, device=device)
    recorded, saturated = sense(values, SensorConfig(exposure=2.5))
    assert recorded.dtype == dtype and recorded.device.type == device.type
    assert torch.equal(recorded, 2.5 * values)
    assert saturated.dtype == torch.bool and not saturated.any()


def test_sense_read_noise_std():
    values = torch.full((100_000,), 0.1, dtype=F64)
    recorded, _ = sense(values, SensorConfig(read_noise=0.02, seed=1))
    std = (recorded - values).std()
    assert abs(std / 0.02 - 1) < 0.05, f"read noise std {std:.4g}, expected 0.02"
    assert abs((recorded - values).mean()) < 4 * 0.02 / math.sqrt(values.numel())
    dark, _ = sense(torch.zeros(1000, dtype=F64), SensorConfig(read_noise=0.02, seed=1))
    assert (dark < 0).any(), "read noise must not be clipped at 0"


@pytest.mark.parametrize("value,photons_per_unit", [(0.5, 100.0), (2.0, 5000.0)])  # Poisson and Gaussian regimes
def test_sense_shot_noise_variance(value, photons_per_unit):
    values = torch.full((100_000,), value, dtype=F64)
    recorded, _ = sense(values, SensorConfig(photons_per_unit=photons_per_unit, seed=2))
    expected = value / photons_per_unit
    variance = recorded.var()
    assert abs(variance / expected - 1) < 0.05, f"shot variance {variance:.4g}, expected {expected:.4g}"
    assert abs(recorded.mean() - value) < 4 * math.sqrt(expected / values.numel())
    if value * photons_per_unit < 1000:  # whole photons
        photons = recorded * photons_per_unit
        assert (photons - photons.round()).abs().max() < 1e-9


def test_sense_saturation_clips_and_flags():
    values = torch.tensor([0.0, 0.5, 0.999, 1.0, 1.001, 7.0], dtype=F64)
    recorded, saturated = sense(values, SensorConfig(exposure=2.0, saturation=2.0))
    assert recorded.tolist() == [0.0, 1.0, 1.998, 2.0, 2.0, 2.0]
    assert saturated.tolist() == [False, False, False, True, True, True]
    noisy, flags = sense(torch.linspace(0, 3, 1000, dtype=F64), SensorConfig(read_noise=0.1, saturation=2.0))
    assert noisy.max() == 2.0 and torch.equal(flags, noisy == 2.0)


def test_sense_deterministic(dtype):
    config = SensorConfig(exposure=1.5, photons_per_unit=50.0, read_noise=0.01, seed=9)
    values = torch.rand(1000, dtype=F64)
    a, _ = sense(values.to(dtype), config)
    b, _ = sense(values.to(dtype), config)
    c, _ = sense(values.to(dtype), dataclasses.replace(config, seed=10))
    d, _ = sense(values, config)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert (a.to(F64) - d).abs().max() < 1e-5, "the noise must not depend on the dtype"
    e, _ = sense(values.to(dtype), config, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a, e)


def test_sense_rejects_negative_settings():
    with pytest.raises(ValueError, match="read_noise"):
        sense(torch.ones(3), SensorConfig(read_noise=-1.0))


def test_yaml_configs(tmp_path):
    good = tmp_path / "painting.yaml"
    good.write_text("width: 32\nseed: 4\ngilded: {box: [0.0, 0.0, 0.5, 0.5], max_tilt_deg: 1.0}\n")
    config = load_config(good, PaintingConfig)
    assert config.width == 32 and config.gilded == GildedConfig(box=(0.0, 0.0, 0.5, 0.5), max_tilt_deg=1.0)
    none = tmp_path / "plain.yaml"
    none.write_text("gilded: null\n")
    assert load_config(none, PaintingConfig) == PaintingConfig(gilded=None)

    for text, cls, key in [
        ("width: 32\nvarnish_fractoin: 0.3\n", PaintingConfig, "varnish_fractoin"),
        ("gilded: {alpah: [0.1, 0.1]}\n", PaintingConfig, "alpah"),
        ("tilt: 3\n", MirrorConfig, "tilt"),
        ("read_nosie: 0.1\n", SensorConfig, "read_nosie"),
    ]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=key):
            load_config(bad, cls)


def test_defaults_match_painting_dev_scene(shared):
    material = json.loads(shared("painting-dev/truth/scene.json").read_text())["material"]
    material.pop("generator")
    assert from_mapping(material, PaintingConfig) == PaintingConfig()


def test_defaults_match_mirror_dev_scene(shared):
    material = json.loads(shared("mirror-dev-1d/truth/scene.json").read_text())["material"]
    material.pop("generator")
    assert from_mapping(material, MirrorConfig) == MirrorConfig()


def test_the_dual_box_has_two_lobes_and_the_gilding_stays_on_top():
    config = PaintingConfig(
        width=40, height=20, gilded=GildedConfig(box=(0.0, 0.0, 0.6, 0.5)), dual=DualConfig(box=(0.5, 0.0, 1.0, 0.5))
    )
    svbrdf, regions = painting(config, dtype=F64)
    cols = torch.arange(40, dtype=F64)[None, :].expand(20, 40) + 0.5
    rows = torch.arange(20, dtype=F64)[:, None].expand(20, 40) + 0.5
    in_dual = (cols / 40 >= 0.5) & (rows / 20 <= 0.5)
    in_gilding = (cols / 40 <= 0.6) & (rows / 20 <= 0.5)
    assert torch.equal(regions == DUAL, in_dual & ~in_gilding) and torch.equal(regions == GILDED, in_gilding)
    dual = regions == DUAL
    assert (svbrdf.specular[dual] == config.dual.ks).all() and (svbrdf.roughness[dual] == config.dual.alpha).all()
    assert (svbrdf.specular2[dual] == config.dual.ks2).all() and (svbrdf.roughness2[dual] == config.dual.alpha2).all()
    assert (svbrdf.specular2[~dual] == 0).all() and (svbrdf.roughness2[~dual] == 0).all()
    assert painting(PaintingConfig(width=8, height=8), dtype=F64)[0].specular2 is None
