"""The prediction stage (torchspec.pipeline.prediction): folds of the light domain, left-out
residuals against a brute-force refit on the other folds, and the rule that keeps a larger model."""

import dataclasses
from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from torchspec.brdf import SVBRDF
from torchspec.geometry import from_plane, normalize
from torchspec.lights import Kernel, Lights
from torchspec.lm import LMConfig
from torchspec.models import get_model
from torchspec.pipeline import FitConfig
from torchspec.pipeline.prediction import held_out, held_out_refit, light_folds, predicts_better
from torchspec.pipeline.samples import TileSamples
from torchspec.pipeline.solver import solve_pixels
from torchspec.rendering import render

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def _grid(side: int, extent: float = 0.6) -> Tensor:
    t = torch.linspace(-extent, extent, side, dtype=F64)
    gy, gx = torch.meshgrid(t, t, indexing="ij")
    return from_plane(torch.stack([gx, gy], -1).reshape(-1, 2))


@given(side=st.integers(3, 9), folds=st.integers(2, 7))
@settings(max_examples=25, deadline=None)
def test_each_frame_is_left_out_once_per_scheme(side, folds):
    directions = _grid(side)
    k = directions.shape[0]
    found = light_folds(directions, folds)
    count = max(2, min(folds, k // 2))
    assert found.shape == (2, k)
    for scheme in found:
        sizes = torch.bincount(scheme, minlength=count)
        assert sizes.numel() == count and int(sizes.min()) >= 0.5 * k / count


def test_scattered_folds_keep_neighbours_apart_and_regions_together():
    directions = _grid(8)
    scattered, sectors = light_folds(directions, 4)
    plane = directions[:, :2]
    # Each light's nearest neighbour is in another scattered fold; a sector's lights are on one side.
    distance = torch.cdist(plane, plane)
    distance.fill_diagonal_(float("inf"))
    nearest = distance.argmin(-1)
    assert bool((scattered != scattered[nearest]).float().mean() > 0.9)
    for f in range(4):
        azimuth = torch.atan2(plane[sectors == f, 1], plane[sectors == f, 0])
        spread = torch.atan2(azimuth.sin().mean(), azimuth.cos().mean())
        assert float((torch.remainder(azimuth - spread + torch.pi, 2 * torch.pi) - torch.pi).abs().max()) < 2.2


def _scene(name: str, n: int = 6, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    lights = Lights(_grid(6), Kernel("point"), torch.ones(36, 1, dtype=F64), torch.ones(36, dtype=F64))
    peaks = (torch.rand(n, 2, dtype=F64, generator=generator) - 0.5) * 0.5
    truth = SVBRDF(
        normalize(from_plane(peaks) + VIEW),
        0.3 + 0.2 * torch.rand(n, 1, dtype=F64, generator=generator),
        torch.full((n, 1), 0.1 if get_model(name).lobe else 0.0, dtype=F64),
        torch.full((n, 2), 0.25, dtype=F64),
        None,
        ("Y",),
    )
    clean = render(truth, lights, VIEW)
    observed = clean + 0.003 * torch.randn(clean.shape, dtype=F64, generator=generator)
    valid = torch.ones(observed.shape[:2], dtype=torch.bool)
    level = observed.mean((1, 2))
    data = TileSamples.of(observed, valid, level, lights, VIEW, ("Y",))
    return truth, data


@pytest.mark.parametrize("name", ["diffuse", "ward-iso"])
def test_left_out_residuals_match_a_refit_without_the_fold(name):
    """The one-step refit's prediction of each fold against the solver's own refit on the other
    folds (float64, converged): the same residuals within a small part of their size."""
    config = FitConfig(model=name, lm=LMConfig(max_iterations=200))
    truth, data = _scene(name)
    index = torch.arange(truth.shape[0])
    solved = solve_pixels(name, index, truth, data, config)
    inverse = data.valid[..., None].to(F64) / 0.003
    folds = light_folds(data.lights.directions, 4, regions=False)
    found = held_out(get_model(name), solved.svbrdf, index, data, inverse, folds, config)[:, 0]
    expected = torch.zeros_like(found)
    for f in range(4):
        keep = (folds[0] != f).to(F64)
        fold_data = dataclasses.replace(data, weight=data.weight * keep)
        refit = solve_pixels(name, index, solved.svbrdf, fold_data, config)
        predicted = render(refit.svbrdf, data.lights, VIEW)
        left = folds[0] == f
        expected[:, left] = ((predicted - data.observed) * inverse)[:, left]
    scale = expected.square().mean().sqrt()
    assert float((found - expected).square().mean().sqrt()) < 0.05 * float(scale)
    # The solver's refits of every fold in one batch (FitConfig.refit) are those refits.
    batched = held_out_refit(get_model(name), solved.svbrdf, index, data, inverse, folds, replace(config, refit=200))
    assert float((batched[:, 0] - expected).square().mean().sqrt()) < 1e-3 * float(scale)


def test_a_model_that_predicts_no_better_than_the_noise_is_not_kept():
    generator = torch.Generator().manual_seed(1)
    noise = torch.randn(200, 2, 30, 3, dtype=F64, generator=generator)
    # The candidate differs from the current model by less than the noise: not kept.
    nudge = 0.05 * torch.randn(noise.shape, dtype=F64, generator=generator)
    assert float(predicts_better(noise + nudge, noise, 3.0).double().mean()) < 0.02
    # The current model misses a structure 5x the noise on a few samples: the candidate is kept.
    missed = torch.zeros_like(noise)
    missed[..., :4, :] = 5.0
    assert bool(predicts_better(noise, noise + missed, 3.0).all())
    assert not bool(predicts_better(noise + missed, noise, 3.0).any())
