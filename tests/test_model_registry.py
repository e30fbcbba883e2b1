"""The model registry (torchspec.model.registry.register): a model declared in one module outside the
package (tests/toy_phong.py: a Phong lobe and its parameters) and registered is fitted, taken by
the config and the command line, and its Jacobian, by forward-mode AD through the renderer, is the
derivative; the whole fit (its deviations and peak checks from the forward-mode sandwich terms,
equal to Ward's fused ones, auto's ladder, model.exr) takes it; the built-in models' declarations
give the codes, the ladder and the docs' tables."""

import re
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from pixel_cases import grid_lights
from toy_phong import PHONG

from torchspec.errors import TorchspecError
from torchspec.lm import LMConfig
from torchspec.model.brdf import SVBRDF
from torchspec.model.lights import Kernel
from torchspec.model.quadrature import QUADRATURES
from torchspec.model.registry import BUILT_IN, MODEL_CODES, MODELS, get_model, register, registered, unregister
from torchspec.model.rendering import render
from torchspec.pipeline import FitConfig, LadderConfig, QuadratureConfig
from torchspec.pipeline.samples import TileSamples
from torchspec.pipeline.settings import LADDER
from torchspec.pipeline.solver import solve_pixels

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
CHANNELS = ("R", "G", "B")


@pytest.fixture
def phong():
    with registered(PHONG) as model:
        yield model


def _truth(count: int = 6) -> SVBRDF:
    g = torch.Generator().manual_seed(3)
    tilt = 0.15 * torch.randn(count, 2, generator=g, dtype=F64)
    normal = torch.nn.functional.normalize(torch.cat([tilt, torch.ones(count, 1, dtype=F64)], -1), dim=-1)
    kd = 0.2 + 0.5 * torch.rand(count, 3, generator=g, dtype=F64)
    ks = 0.2 + 0.3 * torch.rand(count, 1, generator=g, dtype=F64)
    alpha = (0.12 + 0.1 * torch.rand(count, 1, generator=g, dtype=F64)).expand(-1, 2)
    return SVBRDF(normal, kd, ks, alpha, None, CHANNELS)


def test_the_built_in_models_keep_their_codes_and_ladder():
    assert tuple(MODEL_CODES) == BUILT_IN == ("diffuse", "ward-iso", "ward-iso-colour", "ward-aniso", "ward-dual")
    assert LADDER == ("ward-iso", "ward-iso-colour", "ward-aniso", "ward-dual")
    assert [get_model(name).size(3) for name in BUILT_IN] == [5, 7, 9, 11, 9]


def test_a_registered_model_gets_the_next_code_and_leaves_after(phong):
    assert MODEL_CODES[-1] == "phong" and MODEL_CODES.index("phong") == len(BUILT_IN)
    with pytest.raises(TorchspecError, match="registered already"):
        register(PHONG)
    with pytest.raises(TorchspecError, match="not a registered extra model"):
        unregister("ward-iso")


def test_the_registry_is_back_to_the_built_in_models_after_the_block():
    with registered(PHONG):
        assert "phong" in MODELS
    assert "phong" not in MODELS and tuple(MODEL_CODES) == BUILT_IN


def test_the_config_and_the_command_line_take_a_registered_model(phong, tmp_path):
    from torchspec.cli import build_parser

    assert FitConfig(model="phong").model == "phong"
    assert FitConfig(ladder=LadderConfig(models=("ward-iso", "phong"))).ladder.models == ("ward-iso", "phong")
    args = build_parser().parse_args(["fit", str(tmp_path), "-o", str(tmp_path / "maps"), "--model", "phong"])
    assert args.model == "phong"


def test_an_unregistered_model_is_refused():
    from torchspec.config import ConfigError

    with pytest.raises(ConfigError, match="must be one of"):
        FitConfig(model="phong")


def test_the_forward_mode_jacobian_is_the_derivative(phong):
    """gradcheck: the residual function's Jacobian (forward-mode AD through unpack and the
    renderer, on the nodes of an extended kernel) against central differences, float64."""
    lights = grid_lights(Kernel("gaussian", sigma=0.08), n=3, extent=0.3)
    truth = _truth(2)
    observed = render(truth, lights, VIEW, lobe=phong.lobe)
    weight = torch.ones(observed.shape[:2], dtype=F64)
    fn = phong.residuals(observed * 1.1, weight, lights, VIEW, CHANNELS)
    index = torch.arange(2)
    params = phong.pack(truth)
    r, jac = fn(params, index)
    assert jac.shape == (2, lights.directions.shape[0] * 3, phong.size(3))
    eps = 1e-6
    for j in range(params.shape[-1]):
        step = torch.zeros_like(params)
        step[:, j] = eps
        numeric = (fn(params + step, index)[0] - fn(params - step, index)[0]) / (2 * eps)
        torch.testing.assert_close(jac[..., j], numeric, rtol=1e-5, atol=1e-7)

    def rendered(p):
        return render(phong.unpack(p, CHANNELS), lights, VIEW, lobe=phong.lobe)

    assert torch.autograd.gradcheck(
        rendered, (params.clone().requires_grad_(),), check_forward_ad=True, check_backward_ad=False, atol=1e-6
    )


def test_a_registered_model_is_fitted_by_the_pipelines_solver(phong):
    """solve_pixels (the pipeline's stage) recovers the toy model's parameters from pixels it
    rendered under point lights, from a start away from them."""
    lights = grid_lights(Kernel("point"), n=7, extent=0.7)
    truth = _truth(4)
    quadrature = QUADRATURES["fit"]
    observed = render(truth, lights, VIEW, quadrature=quadrature, lobe=phong.lobe)
    n, k = observed.shape[:2]
    valid = torch.ones(n, k, dtype=torch.bool)
    data = TileSamples.of(observed, valid, observed.mean((1, 2)), lights, VIEW, CHANNELS)
    start = SVBRDF(
        torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(n, 3),
        truth.diffuse * 0.8,
        truth.specular * 0.5,
        truth.roughness * 1.4,
        None,
        CHANNELS,
    )
    config = FitConfig(model="phong", quadrature=QuadratureConfig(compile=False), lm=LMConfig(max_iterations=60))
    solved = solve_pixels("phong", torch.arange(n), start, data, config)
    torch.testing.assert_close(solved.svbrdf.normal, truth.normal, rtol=0, atol=1e-5)
    torch.testing.assert_close(solved.svbrdf.diffuse, truth.diffuse, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(solved.svbrdf.specular, truth.specular, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(solved.svbrdf.roughness, truth.roughness, rtol=1e-4, atol=1e-6)


def test_the_docs_list_the_registered_models():
    """The model tables of docs/capture-format.md and torchspec/model/registry.py name the built-in models
    in their code order."""
    formats = (ROOT / "docs" / "capture-format.md").read_text()
    (line,) = [line for line in formats.splitlines() if line.startswith("| `model.exr`")]
    assert re.findall(r"`([a-z-]+)`", line.split("model_codes")[1]) == list(BUILT_IN)
    table = (ROOT / "torchspec" / "model" / "registry.py").read_text().split('"""')[1]
    assert re.findall(r"^``([a-z-]+)`` {2,}", table, flags=re.M) == list(BUILT_IN)


def _ward_case(name: str, kernel: Kernel, count: int = 5):
    """A Ward model's maps on ``count`` pixels, lights, samples and weights of a fit's assessment."""
    model = get_model(name)
    g = torch.Generator().manual_seed(MODEL_CODES.index(name))
    truth = _truth(count)
    if model.lobe is None:
        truth = replace(truth, specular=0 * truth.specular, roughness=0 * truth.roughness)
    if not model.grey:
        truth = replace(truth, specular=truth.specular * torch.tensor([1.0, 0.8, 0.6], dtype=F64))
    if model.anisotropic:
        roughness = truth.roughness * torch.tensor([1.0, 1.5], dtype=F64)
        truth = replace(truth, roughness=roughness, rotation=torch.rand(count, generator=g, dtype=F64))
    if model.fills("specular2"):
        truth = replace(truth, specular2=0.5 * truth.specular, roughness2=2.0 * truth.roughness)
    lights = grid_lights(kernel, n=4, extent=0.6)
    observed = 1.05 * render(truth, lights, VIEW, quadrature=QUADRATURES["fit"]) + 0.01
    noise = 1.0 / (0.01 + 0.1 * observed)
    fit = torch.rand(observed.shape, generator=g, dtype=F64)
    return model, truth, lights, observed, noise, fit


@pytest.mark.parametrize(
    ("name", "kernel", "rtol"),
    [(name, Kernel("point"), 1e-12) for name in BUILT_IN] + [("ward-iso", Kernel("gaussian", sigma=0.08), 1e-2)],
)
def test_the_forward_mode_sandwich_terms_are_the_fused_ones_for_ward(name, kernel, rtol, monkeypatch):
    """forward_sandwich_terms (forward-mode Jacobian, what a lobe without closed forms is assessed
    with) forced on a Ward model gives sandwich_terms' outputs: within float64 rounding under point
    lights (chunked over pixels), within the closed forms' quadrature error (their nodes held fixed,
    torchspec.model.jacobian) under an extended kernel."""
    import torchspec.model.forward_terms as forward_terms
    from torchspec.model.forward_terms import forward_sandwich_terms
    from torchspec.model.least_squares import sandwich_terms

    monkeypatch.setattr(forward_terms, "pixels_per_chunk", lambda frames, quadrature: 2 * get_model(name).size(3))
    model, truth, lights, observed, noise, fit = _ward_case(name, kernel)
    options = dict(quadrature=QUADRATURES["fit"], samples=True)
    select = model.selection(3, observed)
    plain = model.lobe is None
    fused = sandwich_terms(truth, lights, VIEW, observed, noise, fit, select, diffuse_only=plain, **options)
    forward = forward_sandwich_terms(model, truth, lights, VIEW, observed, noise, fit, **options)
    assert len(forward) == len(fused) == 6
    for got, want in zip(forward, fused, strict=True):  # 0.5 chi^2, A, B, z2, excess, lobe_snr
        torch.testing.assert_close(got, want, rtol=rtol, atol=rtol * float(want.abs().max()) + 1e-12)


@pytest.fixture(scope="module")
def phong_capture(tmp_path_factory):
    """A simulated 10 x 10 painting (isotropic roughness) rendered with the toy Phong lobe under a
    6 x 6 grid of point lights, recorded by the simulator's sensor (noise, clipping); its truth."""
    from torchspec.model.lights import Lights
    from torchspec.model.rendering import render_image
    from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, layout, simulate
    from torchspec.simulate import write_simulation as write
    from torchspec.simulate.synth import PaintingConfig, sense

    config = SimulationConfig(
        scene=SceneConfig(kind="painting", painting=PaintingConfig(width=10, height=10, seed=3)),
        light=LightConfig(kernel="point"),
        layout=LayoutConfig(kind="grid", nx=6, ny=6, extent=0.7, radius=1.0),
    )
    simulation = simulate(config)
    truth = simulation.truth.to(F64)
    truth = replace(truth, roughness=truth.roughness.mean(-1, keepdim=True).expand_as(truth.roughness).clone())
    centres = layout(config.layout)
    one = torch.ones(centres.shape[0], dtype=F64)
    lights = Lights(centres, Kernel("point"), one[:, None], one)
    values = render_image(truth, lights, VIEW, lobe=PHONG.lobe)  # (H, W, K, C)
    recorded, saturated = sense(values.permute(2, 3, 0, 1), config.sensor)
    simulation = replace(simulation, frames=recorded.float(), saturated=saturated, truth=truth.to(torch.float32))
    path = tmp_path_factory.mktemp("phong") / "capture"
    write(path, simulation)
    return path, truth


def test_a_registered_model_goes_through_the_whole_fit(phong, phong_capture, tmp_path):
    """torchspec.fit with model phong: its maps recovered where a lobe was fitted, its deviations
    (forward-mode sandwich terms) finite, and model.exr holding phong's code there."""
    from torchspec.io import read_svbrdf
    from torchspec.pipeline import fit, write_fit

    path, truth = phong_capture
    result = fit(path, config=FitConfig(model="phong"))
    lobe = result.lobe
    assert result.stats["models"]["phong"] == int(lobe.sum()) > 20
    ks, alpha = result.svbrdf.specular.mean(-1), result.svbrdf.roughness[..., 0]
    assert float((ks - truth.specular.mean(-1))[lobe].abs().median()) < 1e-3
    assert float((alpha - truth.roughness[..., 0])[lobe].abs().median()) < 1e-4
    assert float(torch.rad2deg((result.svbrdf.normal - truth.normal).norm(dim=-1)).median()) < 0.01
    for key in ("specular", "roughness"):
        finite = result.std[key][lobe].isfinite().all(-1)
        assert finite.float().mean() > 0.9, key
        assert bool((result.std[key][lobe][finite] > 0).all()), key
    assert result.std["normal"].isfinite().float().mean() > 0.9
    write_fit(tmp_path / "maps", result)
    maps = read_svbrdf(tmp_path / "maps")
    code = maps.extra["model"].reshape(lobe.shape).round().long()
    assert bool((code[lobe] == MODEL_CODES.index("phong")).all()) and bool((code[~lobe] == 0).all())


def test_auto_chooses_a_registered_model_where_it_rendered_the_pixels(phong, phong_capture):
    """auto with the ladder (ward-iso, phong) on pixels the Phong lobe rendered: the fit runs with
    both models assessed, and phong is chosen on most lobed pixels."""
    from torchspec.pipeline import fit

    path, _ = phong_capture
    result = fit(path, config=FitConfig(model="auto", ladder=LadderConfig(models=("ward-iso", "phong"))))
    models = result.stats["models"]
    assert set(models) >= {"diffuse", "ward-iso", "phong"}
    assert models["phong"] > models["ward-iso"] and models["phong"] > 20
    chosen = result.model == MODEL_CODES.index("phong")
    assert bool(result.std["roughness"][chosen].isfinite().any())
