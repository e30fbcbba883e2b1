"""The model registry (torchspec.models.register): a model declared in one module outside the
package (tests/toy_phong.py: a Phong lobe and its parameters) and registered is fitted, taken by
the config and the command line, and its Jacobian, by forward-mode AD through the renderer, is the
derivative; the built-in models' declarations give the codes, the ladder and the docs' tables."""

import re
from pathlib import Path

import pytest
import torch
from pixel_cases import grid_lights
from toy_phong import PHONG

from torchspec.brdf import SVBRDF
from torchspec.errors import TorchspecError
from torchspec.lights import Kernel
from torchspec.lm import LMConfig
from torchspec.models import BUILT_IN, MODEL_CODES, MODELS, get_model, register, registered, unregister
from torchspec.pipeline import FitConfig, LadderConfig, QuadratureConfig
from torchspec.pipeline.samples import TileSamples
from torchspec.pipeline.settings import LADDER
from torchspec.pipeline.solver import solve_pixels
from torchspec.quadrature import QUADRATURES
from torchspec.rendering import render

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
    """The model tables of docs/capture-format.md and torchspec/models.py name the built-in models
    in their code order."""
    formats = (ROOT / "docs" / "capture-format.md").read_text()
    (line,) = [line for line in formats.splitlines() if line.startswith("| `model.exr`")]
    assert re.findall(r"`([a-z-]+)`", line.split("model_codes")[1]) == list(BUILT_IN)
    table = (ROOT / "torchspec" / "models.py").read_text().split('"""')[1]
    assert re.findall(r"^``([a-z-]+)`` {2,}", table, flags=re.M) == list(BUILT_IN)
