"""Cast shadows in the fit (torchspec.pipeline.shadows, FitConfig.shadows): the visibility's data
transform is exact, V = 1 is today's fit bitwise, a relief is fitted better with shadows, a flat
painting keeps today's fit, ``torchspec render`` multiplies by the visibility of height.exr, the
CLI flag."""

from dataclasses import fields, replace

import pytest
import torch

from torchspec.config import ConfigError
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import from_plane
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render
from torchspec.model.visibility import sky_view
from torchspec.pipeline import ComputeConfig, FitConfig, TermConfig, fit, write_fit
from torchspec.pipeline.shadows import DEPTHS, SOFTNESSES_DEG, shadows_tried
from torchspec.pipeline.start import light_context
from torchspec.pipeline.tile import EXPLAINED, VISIBLE, FitInputs, TileInputs, fit_tile, seen_through
from torchspec.simulate import LayoutConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.relief import ReliefConfig
from torchspec.simulate.synth import PaintingConfig
from torchspec.start.photometric import Masks

F64 = torch.float64


def _lights(side: int = 6, extent: float = 0.6) -> Lights:
    t = torch.linspace(-extent, extent, side, dtype=F64)
    gy, gx = torch.meshgrid(t, t, indexing="ij")
    d = from_plane(torch.stack([gx, gy], -1).reshape(-1, 2))
    k = d.shape[0]
    return Lights(d, Kernel("point"), torch.ones(k, 1, dtype=F64), torch.ones(k, dtype=F64))


def _pixels(n: int = 12, seed: int = 0) -> SVBRDF:
    g = torch.Generator().manual_seed(seed)
    tilt = 0.3 * (torch.rand(n, 2, generator=g, dtype=F64) - 0.5)
    normal = torch.cat([tilt, torch.ones(n, 1, dtype=F64)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    diffuse = 0.2 + 0.6 * torch.rand(n, 3, generator=g, dtype=F64)
    roughness = torch.full((n, 2), 0.2, dtype=F64)
    return SVBRDF(normal, diffuse, torch.zeros(n, 1, dtype=F64), roughness, None, ("R", "G", "B"))


def _tile(y: torch.Tensor, lights: Lights, visibility=None) -> TileInputs:
    n, k = y.shape[:2]
    none = torch.zeros(k, n, dtype=torch.bool)
    masks = Masks(nonfinite=none, saturated=none, shadowed=none)
    return TileInputs(first=0, values=y.permute(1, 2, 0), masks=masks, lights=lights, ctx=light_context(lights),
                      visibility=visibility)  # fmt: skip


def _shared(lights: Lights, config: FitConfig) -> FitInputs:
    return FitInputs(view=torch.tensor([0.0, 0.0, 1.0], dtype=F64), channels=("R", "G", "B"), config=config)


def test_fixed_visibility_recovers_the_truth_and_unit_visibility_is_bitwise_today():
    lights, truth = _lights(), _pixels()
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    g = torch.Generator().manual_seed(1)
    partial = 0.25 + 0.5 * torch.rand(12, 36, generator=g, dtype=F64)
    v = torch.where(torch.rand(12, 36, generator=g, dtype=F64) < 0.3, partial, 1.0)
    y = render(truth, lights, view) * v[..., None]  # (n, K, C): partly shadowed, noise-free
    config = FitConfig(
        model="diffuse", compute=ComputeConfig(dtype="float64", threads=1), term=TermConfig(order=0)
    )
    shared = _shared(lights, config)
    seen = fit_tile(_tile(y, lights, v.T), shared)
    angle = torch.rad2deg(torch.acos((seen.svbrdf.normal * truth.normal).sum(-1).clamp(-1, 1)))
    assert float(angle.max()) < 0.05
    assert torch.allclose(seen.svbrdf.diffuse, truth.diffuse, rtol=1e-4)
    blind = fit_tile(_tile(y, lights), shared)  # the shadows explained by the wrong maps
    wrong = torch.rad2deg(torch.acos((blind.svbrdf.normal * truth.normal).sum(-1).clamp(-1, 1)))
    assert float(wrong.max()) > 10 * float(angle.max())
    # V = 1 everywhere: today's fit, bitwise.
    ones = fit_tile(_tile(y, lights, torch.ones(36, 12, dtype=F64)), shared)
    for name in ("normal", "diffuse", "specular", "roughness"):
        assert torch.equal(getattr(ones.svbrdf, name), getattr(blind.svbrdf, name))
    assert torch.equal(ones.criterion, blind.criterion) and torch.equal(ones.residual, blind.residual)


def test_seen_through_leaves_out_hidden_samples_and_uses_explained_shadows():
    y = torch.ones(1, 5, 1, dtype=F64)
    shadowed = torch.tensor([[True], [True], [True], [False], [False]])
    none = torch.zeros(5, 1, dtype=torch.bool)
    low, edge = VISIBLE / 2, VISIBLE + 0.5 * (1 - VISIBLE)
    explained = min(max(VISIBLE, EXPLAINED - 1e-3), 1.0)  # seen, and dark enough to explain a shadow if any is
    v = torch.tensor([[low, explained, 1.0, low, edge]], dtype=F64)
    values, valid, kept = seen_through(y, Masks(nonfinite=none, saturated=none, shadowed=shadowed), v)
    # hidden: out of both; a shadow V explains (V < EXPLAINED): in; one it does not: out of the fit
    assert valid.tolist() == [[False, explained < EXPLAINED, False, False, True]]
    assert kept.tolist() == [[True] * 5]  # the term's samples: every finite one (fitted on y against V r)
    seen = v[0] >= VISIBLE
    assert torch.allclose(values[0, seen, 0], 1.0 / v[0, seen]) and torch.equal(values[0, ~seen, 0], y[0, ~seen, 0])


def _simulation(relief, size=24, side=6):
    return SimulationConfig(
        name="shadows",
        scene=SceneConfig(painting=PaintingConfig(width=size, height=size, strokes=3), relief=relief),
        layout=LayoutConfig(kind="grid", nx=side, ny=side, extent=0.95, radius=1.0),
    )


def _angle(fitted, truth):
    return torch.rad2deg(torch.acos((fitted.double() * truth.double()).sum(-1).clamp(-1, 1)))


@pytest.mark.slow  # four fits of a 24 x 24 relief: a minute on two cores
def test_relief_is_fitted_better_with_shadows(tmp_path):
    sim = simulate(_simulation(ReliefConfig(seed=2, bumps=3, bump_height=(4.0, 6.0), ridge_height=0.0)))
    capture = write_simulation(tmp_path / "relief", sim)
    config = FitConfig(model="diffuse", compute=ComputeConfig(threads=1))
    plain = fit(capture, config=replace(config, shadows="off"))
    shadowed = fit(capture, config=replace(config, shadows="on"))
    record = shadowed.stats["shadows"]
    assert record["used"] and shadowed.height is not None, record
    assert record["rounds"][0]["rms"] < record["plain_rms"]  # the left-out frames predicted better
    assert float(_angle(shadowed.svbrdf.normal, sim.truth.normal).mean()) < float(
        _angle(plain.svbrdf.normal, sim.truth.normal).mean()
    )
    assert plain.height is None and "shadows" not in plain.stats
    write_fit(tmp_path / "maps", shadowed)
    from torchspec.io import read_svbrdf

    maps = read_svbrdf(tmp_path / "maps")
    assert torch.equal(maps.extra["height"], shadowed.height.float()) and maps.meta["height"]["unit"] == "pixel"
    assert maps.meta["height"]["softness_deg"] in SOFTNESSES_DEG  # the penumbra the left-out frames chose
    assert maps.meta["height"]["depth"] in DEPTHS  # and the depth
    # this relief reflects no light into its shadows: no indirect light, or little, within the hidden sky
    if shadowed.indirect is None:
        assert "indirect" not in maps.extra and record["indirect"]["p99"] == 0.0
    else:
        assert torch.equal(maps.extra["indirect"], shadowed.indirect.float())
        hidden = 1.0 - sky_view(shadowed.height.double())
        assert bool((shadowed.indirect.double() <= hidden + 1e-6).all()) and float(shadowed.indirect.mean()) < 0.05


def test_flat_painting_keeps_todays_fit(tmp_path):
    sim = simulate(_simulation(None, size=16, side=5))
    capture = write_simulation(tmp_path / "flat", sim)
    found = fit(capture, config=FitConfig(model="diffuse", compute=ComputeConfig(threads=1)))
    assert found.height is None and "shadows" not in found.stats
    none = torch.zeros(25, 16, 16, dtype=torch.bool)
    few = torch.zeros(8, 16, 16, dtype=torch.bool)
    assert not shadows_tried(FitConfig(), Masks(nonfinite=few, saturated=few, shadowed=~few), imported=True)
    assert not shadows_tried(FitConfig(), Masks(nonfinite=none, saturated=none, shadowed=none))
    assert shadows_tried(FitConfig(shadows="on"), Masks(nonfinite=none, saturated=none, shadowed=none))
    assert not shadows_tried(FitConfig(shadows="off"), Masks(nonfinite=none, saturated=none, shadowed=~none))
    assert shadows_tried(FitConfig(), Masks(nonfinite=none, saturated=none, shadowed=none), imported=True)
    assert shadows_tried(FitConfig(), Masks(nonfinite=none, saturated=none, shadowed=~none))


def test_render_multiplies_by_the_visibility_of_height_exr(tmp_path):
    from torchspec.io import read_capture, write_svbrdf
    from torchspec.model.visibility import frame_visibility
    from torchspec.relight import render_capture

    sim = simulate(_simulation(ReliefConfig(seed=2, bumps=3), size=16, side=4))
    write_simulation(tmp_path / "relief", sim)
    truth = sim.truth.to(torch.float32)
    write_svbrdf(tmp_path / "plain", truth)
    write_svbrdf(tmp_path / "shadowed", truth, extra={"height": sim.height.float()})
    plain = render_capture(tmp_path / "plain", tmp_path / "relief", None)["predicted"]
    shadowed = render_capture(tmp_path / "shadowed", tmp_path / "relief", None)["predicted"]
    lights = read_capture(tmp_path / "relief").lights(dtype=torch.float32)
    seen = frame_visibility(sim.height.float(), lights).permute(2, 0, 1)[:, None]
    assert float(seen.min()) < 0.9  # the relief shadows some pixel
    assert torch.allclose(shadowed, plain * seen, atol=1e-6)
    off = render_capture(tmp_path / "shadowed", tmp_path / "relief", None, shadows=False)["predicted"]
    assert torch.equal(off, plain)


def test_shadows_setting_and_cli_flag():
    with pytest.raises(ConfigError, match="shadows"):
        FitConfig(shadows="sometimes")
    assert "shadows" in {f.name for f in fields(FitConfig)}
    from torchspec.cli.parser import build_parser

    args = build_parser().parse_args(["fit", "capture", "-o", "out", "--shadows", "on"])
    assert args.shadows == "on"


def test_residual_term_with_a_visibility_is_fitted_on_the_recorded_values_against_the_shadowed_model():
    """With V = 1 the term is today's, bitwise; with a visibility it is fitted on the recorded
    values, the hidden samples too, against the maps' rendering times V (as shaded_render applies it)."""
    lights, truth = _lights(), _pixels()
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    g = torch.Generator().manual_seed(2)
    v = torch.where(torch.rand(12, 36, generator=g, dtype=F64) < 0.3, 0.1, 1.0)
    glow = 0.02 * (1 + lights.directions[:, 0])[None, :, None]  # what no map explains: smooth in the light
    y = render(truth, lights, view) * v[..., None] + glow
    config = FitConfig(model="diffuse", compute=ComputeConfig(dtype="float64", threads=1), term=TermConfig(order=3))
    shared = _shared(lights, config)
    blind = fit_tile(_tile(y, lights), shared)
    ones = fit_tile(_tile(y, lights, torch.ones(36, 12, dtype=F64)), shared)
    assert torch.equal(ones.term.coefficients, blind.term.coefficients)
    assert torch.equal(ones.term.chosen, blind.term.chosen)
    seen = fit_tile(_tile(y, lights, v.T), shared)
    term = seen.term
    assert bool(term.chosen.any())
    shadowed = render(seen.svbrdf, lights, view) * v[..., None]
    predicted = term.apply(shadowed, lights)
    # the term brings the shadowed prediction to the recorded values, hidden samples included
    hidden = v < VISIBLE
    before = (shadowed - y).abs()[hidden].mean()
    after = (predicted - y).abs()[hidden].mean()
    assert float(after) < 0.5 * float(before)


def test_shaded_render_applies_the_term_after_the_visibility_and_adds_the_indirect_light():
    from torchspec.model.residual_term import ResidualTerm
    from torchspec.relight import render_near, shaded_render

    lights = _lights(4)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    maps = _pixels(12).reshape(3, 4)
    g = torch.Generator().manual_seed(3)
    k = lights.directions.shape[0]
    seen = torch.rand(3, 4, k, 1, generator=g, dtype=F64)
    bounce = 0.01 * torch.rand(3, 4, k, 3, generator=g, dtype=F64)
    term = ResidualTerm(coefficients=0.01 * torch.randn(3, 4, 9, 3, generator=g, dtype=F64),
                        chosen=torch.rand(3, 4, generator=g) < 0.7)  # fmt: skip
    plain = shaded_render(maps, lights, view)
    got = shaded_render(maps, lights, view, seen=seen, bounce=bounce, term=term)
    assert torch.allclose(got, term.apply(plain * seen, lights) + bounce, atol=1e-12)
    positions = 3.0 * lights.directions  # near lights: block by block, the visibility before the term
    near = render_near(maps, lights, positions, view)
    assert torch.allclose(shaded_render(maps, lights, view, positions, seen=seen), near * seen, atol=1e-12)
    with_term = shaded_render(maps, lights, view, positions, seen=seen, bounce=bounce, term=term)
    blocks = render_near(maps, lights, positions, view, term=term, seen=seen)
    assert torch.allclose(with_term - bounce, blocks, atol=1e-12)
