import pytest
import torch
from pixel_cases import grid_lights, random_svbrdf

from torchspec.model.lights import Kernel
from torchspec.model.quadrature import Quadrature
from torchspec.model.registry import MODELS, get_model
from torchspec.model.rendering import render

VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _svbrdf(count=5, seed=0):
    return random_svbrdf(count, torch.Generator().manual_seed(seed))


def _lights():
    return grid_lights(Kernel("gaussian", sigma=0.08))


@pytest.mark.parametrize("name", sorted(MODELS))
def test_pack_unpack_round_trip_and_sizes(name):
    model = get_model(name)
    svbrdf = _svbrdf()
    params = model.pack(svbrdf)
    assert params.shape == (5, model.size(3))
    assert len(model.bounds(3).kinds) == model.size(3)
    back = model.unpack(params, ("R", "G", "B"))
    assert torch.allclose(back.normal, svbrdf.normal, atol=1e-12)
    assert torch.allclose(back.diffuse, svbrdf.diffuse)
    assert torch.allclose(model.pack(back), params, atol=1e-12)
    if not model.lobe:
        assert torch.all(back.specular == 0) and torch.all(back.roughness == 0)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_residual_jacobian_matches_central_differences(name):
    model = get_model(name)
    lights = _lights()
    svbrdf = _svbrdf(count=3, seed=1)
    k = lights.directions.shape[0]
    observed = torch.rand(3, k, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    weight = torch.ones(3, k, dtype=torch.float64)
    weight[:, 0] = 0.0
    fn = model.residuals(observed, weight, lights, VIEW, ("R", "G", "B"))
    params = model.pack(svbrdf)
    index = torch.arange(3)
    r, jac = fn(params, index)
    assert r.shape == (3, k * 3) and jac.shape == (3, k * 3, model.size(3))
    assert torch.all(r[:, :3] == 0)  # the weight-0 frame
    step = 1e-6
    for j in range(params.shape[1]):
        e = torch.zeros_like(params)
        e[:, j] = step
        numeric = (fn(params + e, index)[0] - fn(params - e, index)[0]) / (2 * step)
        err = (numeric - jac[..., j]).abs().max() / numeric.abs().max().clamp(min=1e-6)
        assert err < 2e-3, f"column {j}: relative error {err:.3g}"


def test_unknown_model_is_named():
    with pytest.raises(ValueError, match="model must be one of"):
        get_model("phong")


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("grey_weight", [True, False])
def test_normal_equations_are_those_of_the_residuals(name, grey_weight):
    """``normal=True``: the cost, ``J^T J`` and ``J^T r`` of the same residuals and Jacobian, to
    rounding, with weights per frame or per channel, and for a subset of the rows."""
    model = get_model(name)
    lights = _lights()
    svbrdf = _svbrdf(count=4, seed=3)
    k = lights.directions.shape[0]
    g = torch.Generator().manual_seed(4)
    observed = torch.rand(4, k, 3, generator=g, dtype=torch.float64)
    weight = (
        torch.rand(4, k, generator=g, dtype=torch.float64)
        if grey_weight
        else torch.rand(4, k, 3, generator=g, dtype=torch.float64)
    )
    params = model.pack(svbrdf)[[3, 1]]
    index = torch.tensor([3, 1])
    r, jac = model.residuals(observed, weight, lights, VIEW, ("R", "G", "B"))(params, index)
    ne = model.residuals(observed, weight, lights, VIEW, ("R", "G", "B"), normal=True)(params, index)
    torch.testing.assert_close(ne.cost, 0.5 * (r * r).sum(-1), rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(ne.hess, jac.transpose(1, 2) @ jac, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(ne.grad, (jac.transpose(1, 2) @ r[..., None])[..., 0], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_sandwich_terms_are_those_of_the_jacobian(name):
    """``sandwich_terms``: ``0.5 chi^2``, ``A = J^T W^2 J`` and ``B = J^T W^2 S W^2 J`` of the dense
    Jacobian (brute force, float64), with noise weights per sample and channel (some 0) and fit
    weights per pixel; with ``W`` the noise weights, ``A = B``: the Fisher information. With
    ``samples``, the same three, and the per-sample terms of the sums over the dense Jacobian (one
    lobe is summed from Gram matrices, never that Jacobian)."""
    from torchspec.model.least_squares import _contract, _sandwich_samples, sandwich_terms

    model = get_model(name)
    lights = _lights()
    svbrdf = _svbrdf(count=4, seed=5)
    k = lights.directions.shape[0]
    g = torch.Generator().manual_seed(6)
    observed = torch.rand(4, k, 3, generator=g, dtype=torch.float64)
    noise = torch.rand(4, k, 3, generator=g, dtype=torch.float64) + 0.5
    noise[:, 1] = 0.0
    fit = (torch.rand(4, 1, 1, generator=g, dtype=torch.float64) + 0.5).expand(-1, k, 3) * (noise > 0)
    params = model.pack(svbrdf)
    r, jac = model.residuals(observed, torch.ones(4, k), lights, VIEW, ("R", "G", "B"))(params, torch.arange(4))
    jac = jac.reshape(4, k, 3, -1)
    variance = torch.where(noise > 0, 1.0 / noise.clamp(min=1e-300) ** 2, torch.zeros_like(noise))
    half_chi2 = 0.5 * ((r.reshape(4, k, 3) * noise) ** 2).sum((1, 2))
    a = torch.einsum("nkcp,nkc,nkcq->npq", jac, fit**2, jac)
    b = torch.einsum("nkcp,nkc,nkcq->npq", jac, fit**4 * variance, jac)
    select = model.selection(3, observed)
    args = (model.unpack(params, ("R", "G", "B")), lights, VIEW, observed)
    cost, bread, meat = sandwich_terms(*args, noise, fit.contiguous(), select, diffuse_only=not model.lobe)
    torch.testing.assert_close(cost, half_chi2, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(bread, a, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(meat, b, rtol=1e-12, atol=1e-15)
    options = dict(diffuse_only=not model.lobe)
    full = sandwich_terms(*args, noise, fit.contiguous(), select, samples=True, **options)
    dense = _contract(_sandwich_samples, *args, (noise, fit.contiguous()), select, quadrature=Quadrature(), **options)
    for got, expected in zip(full, (half_chi2, a, b, *dense[3:]), strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-15)
    _, bread, meat = sandwich_terms(*args, noise, noise, select, diffuse_only=not model.lobe)
    torch.testing.assert_close(bread, meat, rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match=rf"fit_weight must have shape \(4, {k}, 3\)"):
        sandwich_terms(*args, noise, fit[..., 0], select)


def test_normal_equations_check_their_inputs():
    from torchspec.model.least_squares import normal_equations
    from torchspec.model.quadrature import Quadrature

    lights = _lights()
    svbrdf = _svbrdf(count=2)
    k = lights.directions.shape[0]
    select = get_model("ward-aniso").selection(3, svbrdf.diffuse)
    good = torch.ones(2, k, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=rf"weight must have shape \(2, {k}, 3\); got \(2, {k}\)"):
        normal_equations(svbrdf, lights, VIEW, good, good[..., 0], select)
    with pytest.raises(ValueError, match="clamp must be one of"):
        normal_equations(svbrdf, lights, VIEW, good, good, select, quadrature=Quadrature(clamp="rough"))


def test_ward_dual_starts_either_side_of_one_lobe_and_names_the_sharper_first():
    model = get_model("ward-dual")
    one = _svbrdf()
    params = model.pack(one)  # a smaller model's fit: the lobes start at alpha / 2 and 2 alpha, half k_s each
    assert params.shape == (5, 3 + 6) and model.size(3) == 9
    ks, alpha = one.specular.mean(-1), one.roughness.mean(-1)
    torch.testing.assert_close(params[:, 5], 0.5 * ks)
    torch.testing.assert_close(params[:, 7], 0.5 * ks)
    torch.testing.assert_close(params[:, 6], 0.5 * alpha)
    torch.testing.assert_close(params[:, 8], 2.0 * alpha)
    swapped = params[:, [0, 1, 2, 3, 4, 7, 8, 5, 6]]  # the broad lobe first, as a solver may leave it
    ordered = model.unpack(swapped, ("R", "G", "B"), order=True)
    torch.testing.assert_close(ordered.roughness[:, 0], 0.5 * alpha)
    torch.testing.assert_close(ordered.roughness2[:, 1], 2.0 * alpha)
    as_is = model.unpack(swapped, ("R", "G", "B"))
    torch.testing.assert_close(as_is.roughness2[:, 0], 0.5 * alpha)
    # Either order renders the same.
    lights = _lights()
    torch.testing.assert_close(render(ordered, lights, VIEW), render(as_is, lights, VIEW))


def test_ward_dual_selection_sums_each_lobes_two_roughness_columns():
    model = get_model("ward-dual")
    full = torch.arange(3 * 12, dtype=torch.float64).reshape(3, 12)  # 2 + C + 1 + 3 + 1 + 2 columns, C = 3
    picked = model.select(full, 3)
    assert picked.shape == (3, 9)
    torch.testing.assert_close(picked[:, :6], full[:, :6])
    torch.testing.assert_close(picked[:, 6], full[:, 6] + full[:, 7])  # alpha: alpha_x + alpha_y
    torch.testing.assert_close(picked[:, 7], full[:, 9])  # k_s2 (the rotation, column 8, is shared and not fitted)
    torch.testing.assert_close(picked[:, 8], full[:, 10] + full[:, 11])
    torch.testing.assert_close(full @ model.selection(3, full), picked)
