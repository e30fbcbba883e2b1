import json
import math
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import torch
from capture_cases import write_painting
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.cli import main
from torchspec.io import read_capture, read_svbrdf
from torchspec.io.exr import read_exr, write_exr
from torchspec.model.geometry import angle
from torchspec.pipeline import (
    MODEL_CODES,
    ComputeConfig,
    FitConfig,
    LadderConfig,
    QuadratureConfig,
    StartConfig,
    fit,
    select_frames,
    smooth_choice,
    write_fit,
)


@pytest.fixture(scope="module")
def painting(tmp_path_factory):
    """A 16 x 16 simulated painting (no gilding) under 60 frames of a projected Gaussian light."""
    return write_painting(tmp_path_factory.mktemp("fit") / "painting", size=16, seed=5, grid=9, extent=0.8, radius=0.8)


def _errors(result, truth, regions):
    s, t = result.svbrdf.flatten(), truth.flatten()
    lobe = regions.reshape(-1) == 1
    matte = regions.reshape(-1) == 0
    return {
        "normal": torch.rad2deg(angle(s.normal.double(), t.normal.double())),
        "kd": ((s.diffuse.double() - t.diffuse.double()) / t.diffuse.double()).abs(),
        "ks": ((s.specular.double().mean(-1) - t.specular.double().mean(-1)) / t.specular.double().mean(-1)).abs()[
            lobe
        ],
        "alpha": ((s.roughness[:, 0].double() - t.roughness[:, 0].double()) / t.roughness[:, 0].double()).abs()[lobe],
        "matte_ks": s.specular.double().mean(-1)[matte],
    }


def test_fit_recovers_a_simulated_painting(painting):
    truth = read_svbrdf(painting / "truth")
    result = fit(painting)
    e = _errors(result, truth.svbrdf, truth.extra["regions"])
    assert e["normal"].median() < 0.05, f"median normal error {e['normal'].median():.3g} deg"
    assert e["normal"].max() < 1.0, f"max normal error {e['normal'].max():.3g} deg"
    assert e["kd"].median() < 2e-3, f"median k_d error {e['kd'].median():.3g}"
    assert e["ks"].median() < 0.02, f"median k_s error {e['ks'].median():.3g}"
    assert e["alpha"].median() < 0.02, f"median alpha error {e['alpha'].median():.3g}"
    assert torch.all(e["matte_ks"] == 0), "a matte pixel got a lobe"
    assert result.stats["status"]["diverged"] == 0
    assert result.quality.min() >= 0 and result.quality.max() <= 1
    assert result.residual.median() < 1e-3
    assert result.svbrdf.normal.dtype == torch.float32


def test_tiles_are_independent(painting):
    # A batch's size changes the rounding of its matrix products, so a pixel's solver path differs
    # by rounding and stops elsewhere within its tolerance (ftol = 1e-8 on the cost: ~1e-4 on a
    # parameter in a flat direction). float64 keeps that far below the float32 steps (~1e-3).
    whole = fit(painting, frames="::2", config=FitConfig(compute=ComputeConfig(dtype="float64")))
    tiled = fit(painting, frames="::2", config=FitConfig(compute=ComputeConfig(dtype="float64", tile=37)))
    assert tiled.stats["tile_pixels"] == 37
    for name in ("normal", "diffuse", "specular", "roughness"):
        a, b = getattr(whole.svbrdf, name), getattr(tiled.svbrdf, name)
        err = (a - b).abs().max()
        assert err < 1e-4, f"{name}: max difference {err:.3g}"


@pytest.mark.parametrize("start", [dict(init="naive"), dict(init="grid"), dict(fri_kernel="pooled")])
def test_other_starts_reach_the_same_fit(painting, start):
    truth = read_svbrdf(painting / "truth")
    result = fit(painting, frames="::2", config=FitConfig(start=StartConfig(**start)))
    e = _errors(result, truth.svbrdf, truth.extra["regions"])
    assert e["normal"].median() < 0.1, f"median normal error {e['normal'].median():.3g} deg"
    assert e["alpha"].median() < 0.05, f"median alpha error {e['alpha'].median():.3g}"


def test_a_bad_sample_is_masked_not_fitted(painting, tmp_path):
    import shutil

    copy = tmp_path / "bad"
    shutil.copytree(painting, copy)
    frame = copy / read_capture(copy).frames[3].file
    image = np.array(read_exr(frame, ["R", "G", "B"]))
    image[4, 5, :] = np.nan
    write_exr(frame, image, ["R", "G", "B"])
    with pytest.warns(UserWarning, match=r"frames\[3\].*1 pixel"):
        result = fit(copy)
    assert result.stats["masked_samples"]["nonfinite"] == 1
    truth = read_svbrdf(copy / "truth").svbrdf
    error = torch.rad2deg(angle(result.svbrdf.normal[4, 5].double(), truth.normal[4, 5].double()))
    assert error < 0.1, f"normal error at the masked pixel {error:.3g} deg"


def test_every_stage_is_a_module_and_fit_a_function():
    import importlib
    import importlib.util
    import pkgutil

    import torchspec
    from torchspec import pipeline

    assert callable(torchspec.fit) and torchspec.fit is pipeline.fit
    for gone in ("torchspec.fit", "torchspec.distributed"):
        assert importlib.util.find_spec(gone) is None, gone
    stages = [info.name for info in pkgutil.iter_modules(pipeline.__path__)]
    assert {"settings", "start", "solver", "uncertainty", "selection", "checks", "tile", "cluster"} <= set(stages)
    assert not set(stages) & set(pipeline.__all__)  # no re-exported name hides a stage
    for name in stages:
        importlib.import_module(f"torchspec.pipeline.{name}")


def test_select_frames():
    assert select_frames(None, 5) == [0, 1, 2, 3, 4]
    assert select_frames("::2", 5) == [0, 2, 4]
    assert select_frames("1::2", 5) == [1, 3]
    assert select_frames("0,2-4", 6) == [0, 2, 3, 4]
    for bad, match in [
        ("x", "SPEC must be"),
        ("7", "outside"),
        ("1,1", "twice"),
        ("3:3", "selects no frame"),
        ("::0", "SPEC must be"),
    ]:
        with pytest.raises(ValueError, match=match):
            select_frames(bad, 5)


def test_config_is_checked():
    with pytest.raises(ValueError, match="init must be one of"):
        FitConfig(start=StartConfig(init="magic"))
    with pytest.raises(ValueError, match="fri_kernel must be one of"):
        FitConfig(start=StartConfig(fri_kernel="true"))
    with pytest.raises(ValueError, match="fri_kernel 'pooled' weighs the 'coherent' method"):
        FitConfig(start=StartConfig(fri_kernel="pooled", fri_method="ls"))
    with pytest.raises(ValueError, match="select_z must be >= 0"):
        FitConfig(model="auto", ladder=LadderConfig(select_z=-1.0))
    with pytest.raises(ValueError, match="model must be one of"):
        FitConfig(model="phong")
    with pytest.raises(ValueError, match="quadrature.preset must be one of"):
        FitConfig(quadrature=QuadratureConfig(preset="rough"))
    for ladder in ((), ("ward-iso", "diffuse"), ("ward-iso", "ward-iso")):
        with pytest.raises(ValueError, match="ladder.models must name one or more models with a lobe"):
            FitConfig(ladder=LadderConfig(models=ladder))
    with pytest.raises(ValueError, match="model must be one of"):
        FitConfig(ladder=LadderConfig(models=("ward-iso", "phong")))


def test_write_fit_and_cli(painting, tmp_path):
    out = tmp_path / "maps"
    config = tmp_path / "fit.yaml"
    config.write_text("start: {init: fri}\nlm: {max_iterations: 30}\n")
    assert main(["fit", str(painting), "-o", str(out), "--config", str(config), "--frames", "::2"]) == 0
    maps = read_svbrdf(out)
    meta = json.loads((out / "svbrdf.json").read_text())
    assert meta["fit"]["frames"] == list(range(0, len(read_capture(painting).frames), 2))
    assert meta["fit"]["settings"]["lm"]["max_iterations"] == 30
    assert set(maps.extra) >= {"residual", "quality", "status", "iterations", "model", "criterion"}
    assert meta["model_codes"] == list(MODEL_CODES)
    assert sum(meta["fit"]["models"].values()) == maps.svbrdf.shape[0] * maps.svbrdf.shape[1]
    direct = fit(painting, frames="::2", config=FitConfig(lm=FitConfig().lm.__class__(max_iterations=30)))
    err = (maps.svbrdf.normal - direct.svbrdf.normal).abs().max()
    assert err < 1e-6, f"max difference {err:.3g}"
    assert main(["fit", str(painting), "-o", str(tmp_path / "x"), "--frames", "0,1"]) == 2  # too few frames
    bad = tmp_path / "bad.yaml"
    bad.write_text("start: {inti: fri}\n")
    assert main(["fit", str(painting), "-o", str(tmp_path / "y"), "--config", str(bad)]) == 2
    assert not math.isnan(float(maps.extra["quality"].mean()))


def test_configs_fit_yaml_spells_out_the_defaults():
    from pathlib import Path

    from torchspec.config import load_config

    assert load_config(Path(__file__).parents[1] / "configs" / "fit.yaml", FitConfig) == FitConfig()


def test_the_fits_quadrature_changes_little(painting):
    """The fit's fewer nodes (``quadrature: fit``) against the renderer's rules: the same maps to
    well within their errors against the truth (test_fit_recovers_a_simulated_painting)."""
    fast = fit(painting, frames="::2", config=FitConfig(compute=ComputeConfig(dtype="float64")))
    config = FitConfig(compute=ComputeConfig(dtype="float64"), quadrature=QuadratureConfig(preset="render"))
    exact = fit(painting, frames="::2", config=config)
    normal = torch.rad2deg(angle(fast.svbrdf.normal, exact.svbrdf.normal)).max()
    assert normal < 0.01, f"normals differ by {normal:.3g} deg"
    for name in ("diffuse", "specular", "roughness"):
        a, b = getattr(fast.svbrdf, name), getattr(exact.svbrdf, name)
        err = ((a - b).abs() / b.abs().clamp(min=1e-3)).max()
        assert err < 2e-3, f"{name}: max relative difference {err:.3g}"


def _solver_module():
    import importlib

    return importlib.import_module("torchspec.pipeline.solver")


def test_a_failed_compilation_warns_and_fits_without(painting, monkeypatch):
    module = _solver_module()

    def broken(function):
        raise RuntimeError("no C++ compiler here")

    monkeypatch.setattr(__import__("importlib").import_module("torchspec.model.fusion"), "compiled", broken)
    monkeypatch.setattr(module, "_COMPILE_FAILED", [])
    with pytest.warns(UserWarning, match="torch.compile failed .*no C\\+\\+ compiler here.*fitting without it"):
        result = fit(painting, frames="::3", config=FitConfig(quadrature=QuadratureConfig(compile=True)))
    assert len(module._COMPILE_FAILED) == 1  # not tried again in this process
    plain = fit(painting, frames="::3", config=FitConfig(quadrature=QuadratureConfig(compile=False)))
    torch.testing.assert_close(result.svbrdf.normal, plain.svbrdf.normal)
    torch.testing.assert_close(result.svbrdf.roughness, plain.svbrdf.roughness)


@pytest.fixture(scope="module")
def gilded(tmp_path_factory):
    """A 24 x 24 painting with its gilded patch (a coloured anisotropic lobe), shot noise."""
    path = tmp_path_factory.mktemp("fit") / "gilded"
    return write_painting(
        path, size=24, seed=11, gilded=True, grid=10, extent=0.8, radius=0.8, photons=1e5, sensor_seed=2
    )


def test_auto_models_no_more_than_the_scene_needs(gilded):
    truth = read_svbrdf(gilded / "truth")
    regions = truth.extra["regions"].round().long()
    auto = fit(gilded, config=FitConfig(model="auto"))
    names = [MODEL_CODES[int(code)] for code in auto.model.flatten()]
    region = regions.flatten().tolist()
    matte = [m for m, r in zip(names, region, strict=True) if r == 0]
    varnish = [m for m, r in zip(names, region, strict=True) if r == 1]
    gold = [m for m, r in zip(names, region, strict=True) if r == 2]
    assert matte.count("diffuse") >= 0.95 * len(matte), Counter(matte)
    # The gilding is coloured and anisotropic: a grey or isotropic lobe does not explain it.
    assert sum(m in ("ward-iso-colour", "ward-aniso") for m in gold) >= 0.9 * len(gold), Counter(gold)
    # Shot noise only, and the model the data were made with: the varnish needs no more than ward-iso.
    assert varnish.count("ward-iso") >= 0.9 * len(varnish), Counter(varnish)
    assert auto.stats["models"] == dict(Counter(names)) | {n: 0 for n in MODEL_CODES if n not in names}
    assert torch.equal(auto.lobe, auto.model > 0)
    # No pixel took two lobes: the maps have no second lobe, nor its deviations.
    assert auto.stats["models"]["ward-dual"] == 0
    assert auto.svbrdf.specular2 is None and "specular2" not in auto.std and "roughness2" not in auto.std
    # The criterion: the choice beats every model forced on every pixel, and is the lower of the two
    # wherever it differs from one of them.
    for name in ("diffuse", "ward-iso", "ward-iso-colour", "ward-aniso"):
        forced = fit(gilded, config=FitConfig(model=name))
        assert auto.stats["criterion"] < forced.stats["criterion"], name
        if name == "diffuse":
            assert forced.stats["lobe_pixels"] == 0 and float(forced.svbrdf.specular.abs().max()) == 0.0
    assert auto.stats["models_tried"]["ward-aniso"] < auto.stats["lobe_pixels"]  # not every pixel climbs


def test_standard_deviations_cover_the_truth(gilded):
    """The covariance at the solution, with the sensor noise fitted to the residuals, gives standard
    deviations within which the truth lies as often as for a Gaussian estimate: 95 % of the pixels
    within 2 of them (90-98 % asserted), per parameter, on the pixels of the model the data
    were made with (varnish fitted ward-iso, shot noise)."""
    truth = read_svbrdf(gilded / "truth").svbrdf.flatten()
    regions = read_svbrdf(gilded / "truth").extra["regions"].round().long().flatten()
    result = fit(gilded, config=FitConfig(model="auto"))
    s, std = result.svbrdf.flatten(), {k: v.flatten(0, 1) for k, v in result.std.items()}
    pick = (regions == 1) & (result.model.flatten() == MODEL_CODES.index("ward-iso"))
    assert int(pick.sum()) > 200
    z = {
        "k_d": ((s.diffuse - truth.diffuse) / std["diffuse"])[pick].flatten(),
        "k_s": ((s.specular[:, 0] - truth.specular.mean(-1)) / std["specular"][:, 0])[pick],
        "alpha": ((s.roughness[:, 0] - truth.roughness[:, 0]) / std["roughness"][:, 0])[pick],
    }
    for name, values in z.items():
        covered = float((values.abs() <= 2.0).double().mean())
        assert 0.90 <= covered <= 0.98, f"{name}: {covered:.3f} within 2 std"
    # The normal's angle error is 2D: with per-tilt deviations s, its std is sqrt(2) s, and an
    # isotropic Gaussian has 95 % of its mass within sqrt(2 ln 20) s = sqrt(ln 20) std.
    error = angle(s.normal.double(), truth.normal.double())[pick]
    covered = float((error <= math.sqrt(math.log(20)) * std["normal"][pick]).double().mean())
    assert 0.90 <= covered <= 0.98, f"normal: {covered:.3f}"


def test_standard_deviations_are_finite_for_the_models_parameters_only(gilded):
    result = fit(gilded, config=FitConfig(model="auto"))
    std = {k: v.flatten(0, 1) for k, v in result.std.items()}
    lobe = result.model.flatten() > 0
    assert bool(std["roughness"][lobe].isfinite().all()) and bool(std["roughness"][~lobe].isnan().all())
    assert bool(std["diffuse"].isfinite().all()) and bool(std["normal"].isfinite().all())


@pytest.fixture(scope="module")
def dual(tmp_path_factory):
    """A 24 x 24 painting with a box of two-lobed gloss (a sharp varnish over a broad lobe), shot noise."""
    path = tmp_path_factory.mktemp("fit") / "dual"
    return write_painting(path, size=24, seed=5, dual=True, grid=10, extent=0.8, radius=0.8, photons=1e5, sensor_seed=3)


def test_auto_gives_two_lobes_only_where_the_gloss_has_two(dual, tmp_path):
    truth = read_svbrdf(dual / "truth")
    regions = truth.extra["regions"].round().long().flatten()
    auto = fit(dual, config=FitConfig(model="auto"))
    names = np.array([MODEL_CODES[int(code)] for code in auto.model.flatten()])
    two = regions == 3
    assert int(two.sum()) >= 40
    assert (names[two.numpy()] == "ward-dual").mean() >= 0.9, Counter(names[two.numpy()])
    assert (names[~two.numpy()] == "ward-dual").mean() <= 0.01, Counter(names[~two.numpy()])
    # Both lobes recovered, the sharper named first.
    s, t = auto.svbrdf.flatten(), truth.svbrdf.flatten()
    picked = two & torch.from_numpy(names == "ward-dual")
    for fitted, true in (
        (s.specular.mean(-1), t.specular.mean(-1)),
        (s.roughness[:, 0], t.roughness[:, 0]),
        (s.specular2.mean(-1), t.specular2.mean(-1)),
        (s.roughness2[:, 0], t.roughness2[:, 0]),
    ):
        error = ((fitted.double() - true.double()) / true.double()).abs()[picked]
        assert float(error.median()) < 0.02
    assert float(torch.rad2deg(angle(s.normal.double(), t.normal.double()))[picked].median()) < 0.05
    # The second lobe is 0, with no deviation, where another model was chosen.
    assert float(s.specular2[~picked].abs().max()) == 0.0
    assert bool(auto.std["specular2"].flatten()[~picked].isnan().all())
    assert bool(auto.std["specular2"].flatten()[picked].isfinite().all())
    # The choice beats one lobe forced everywhere, and two lobes forced everywhere.
    for name in ("ward-aniso", "ward-dual"):
        assert auto.stats["criterion"] < fit(dual, config=FitConfig(model=name)).stats["criterion"], name
    # A ladder without it: one lobe everywhere, no second lobe's maps.
    single = fit(dual, config=FitConfig(ladder=LadderConfig(models=("ward-iso", "ward-iso-colour", "ward-aniso"))))
    assert single.svbrdf.specular2 is None and "specular2" not in single.std
    assert single.stats["models"]["ward-dual"] == 0 and auto.stats["criterion"] < single.stats["criterion"]
    # Written and read back: the second lobe's maps and deviations.
    write_fit(tmp_path / "out", auto)
    back = read_svbrdf(tmp_path / "out")
    torch.testing.assert_close(back.svbrdf.specular2[..., 0], auto.svbrdf.specular2[..., 0].float())
    assert back.extra["std_roughness2"].shape == (24, 24, 2)


def _energy(choice, lobed, plain, weight):
    """The total smooth_choice lowers, by brute force (pairs of 4-neighbours counted once)."""
    own = torch.where(choice, lobed, plain).sum()
    pairs = (choice[1:] != choice[:-1]).sum() + (choice[:, 1:] != choice[:, :-1]).sum()
    return float(own + weight * pairs)


def test_smooth_choice_by_hand():
    inf = math.inf
    plain = torch.zeros(5, 5, dtype=torch.float64)
    lobed = torch.full((5, 5), inf, dtype=torch.float64)  # a matte field: no lobed fit
    lobed[2, 2] = -30.0  # one pixel whose lobe lowers its criterion by 30
    assert torch.equal(smooth_choice(lobed, plain, 0.0), lobed < plain)
    assert not smooth_choice(lobed, plain, 8.0)[2, 2]  # 4 neighbours x 8 = 32 > 30: it joins the field
    assert smooth_choice(lobed, plain, 7.0)[2, 2]  # 28 < 30: its lobe stays
    lobed[0, 0] = -15.0  # a corner has 2 neighbours
    assert not smooth_choice(lobed, plain, 8.0)[0, 0] and smooth_choice(lobed, plain, 7.0)[0, 0]
    # A region keeps its shape: a 3 x 3 block of lobes, each worth 10, is not eaten at weight 4 (its
    # corners have 2 outside neighbours: 8 < 10), and its interior never has an outside one.
    lobed = torch.full((7, 7), inf, dtype=torch.float64)
    lobed[2:5, 2:5] = -10.0
    plain = torch.zeros(7, 7, dtype=torch.float64)
    assert torch.equal(smooth_choice(lobed, plain, 4.0), lobed < plain)
    with pytest.raises(ValueError, match=r"must be \(H, W\) alike"):
        smooth_choice(lobed, plain[:3], 1.0)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 6),
    st.integers(1, 6),
    st.floats(0.0, 20.0),
    st.integers(0, 2**31 - 1),
)
def test_smooth_choice_lowers_the_total_to_a_local_minimum(h, w, weight, seed):
    g = torch.Generator().manual_seed(seed)
    lobed = 20 * torch.randn(h, w, generator=g, dtype=torch.float64)
    plain = 20 * torch.randn(h, w, generator=g, dtype=torch.float64)
    plain[torch.rand(h, w, generator=g) < 0.2] = math.inf  # pixels with one of the two fits only
    choice = smooth_choice(lobed, plain, weight)
    start = lobed < plain
    assert _energy(choice, lobed, plain, weight) <= _energy(start, lobed, plain, weight) + 1e-9
    assert bool(choice[plain == math.inf].all())
    for i in range(h):  # no single pixel's change lowers the total
        for j in range(w):
            other = choice.clone()
            other[i, j] = ~other[i, j]
            assert _energy(other, lobed, plain, weight) >= _energy(choice, lobed, plain, weight) - 1e-9


def test_smoothing_takes_lobes_only_where_the_neighbours_outweigh_them(dual, tmp_path):
    with pytest.raises(ValueError, match="smooth must be >= 0"):
        FitConfig(ladder=LadderConfig(smooth=-1.0))
    with pytest.raises(ValueError, match="smooth regularises auto's choice"):
        FitConfig(model="ward-iso", ladder=LadderConfig(smooth=1.0))
    regions = read_svbrdf(dual / "truth").extra["regions"].round().long()
    # predict_z = 0: each pixel's choice alone keeps any lobe that predicts better at all, so the
    # peaks detected in the matte region's noise keep lobes for smoothing to take away.
    config = FitConfig(ladder=LadderConfig(predict_z=0.0), compute=ComputeConfig(tile=150))
    plain = fit(dual, config=config, frames="::2")
    smooth = fit(dual, config=replace(config, ladder=LadderConfig(predict_z=0.0, smooth=20.0)), frames="::2")
    assert plain.stats["smoothed"] is None
    dropped = (plain.model > 0) & (smooth.model == 0)
    assert smooth.stats["smoothed"] == int(dropped.sum()) and not bool(((plain.model == 0) & (smooth.model > 0)).any())
    # The lobes a matte region had lose them; the varnish, gilding and two-lobed box keep theirs.
    assert bool((smooth.model[regions == 0] == 0).all()) and int(dropped[regions == 0].sum()) > 0
    assert int(dropped[regions > 0].sum()) <= 0.01 * int((regions > 0).sum())
    # A dropped lobe leaves no trace: the fit without one, its criterion, deviations and flags.
    s = smooth.svbrdf
    assert float(s.specular[dropped].abs().max()) == 0.0 and float(s.roughness[dropped].abs().max()) == 0.0
    assert bool(smooth.std["specular"][dropped].isnan().all()) and bool(smooth.std["diffuse"][dropped].isfinite().all())
    assert not bool(smooth.lobe[dropped].any()) and bool(smooth.checks["astray"][dropped].isnan().all())
    kept = ~dropped
    torch.testing.assert_close(s.normal[kept], plain.svbrdf.normal[kept], rtol=1e-4, atol=1e-4)
    write_fit(tmp_path / "smooth", smooth)
    assert read_svbrdf(tmp_path / "smooth").extra["model"][dropped].eq(0).all()
