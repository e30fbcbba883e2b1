import math

import pytest
import torch

from torchspec.model.geometry import angle, from_plane, normalize
from torchspec.model.lights import Kernel, Lights, diffuse_directions
from torchspec.simulate import LayoutConfig, layout
from torchspec.start.photometric import grid_layout, lowpass, photometric_stereo, sample_masks

TOL = {torch.float32: 2e-4, torch.float64: 1e-9}


def _grid(dtype=torch.float64):
    return layout(LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8)).to(dtype)


def _normals(count, max_tilt_deg, seed, dtype):
    g = torch.Generator().manual_seed(seed)
    tilt = torch.rand(count, generator=g, dtype=torch.float64) * math.radians(max_tilt_deg)
    phi = torch.rand(count, generator=g, dtype=torch.float64) * 2 * math.pi
    n = torch.stack([tilt.sin() * phi.cos(), tilt.sin() * phi.sin(), tilt.cos()], -1)
    return n.to(dtype)


def _lambertian(normal, kd, directions):
    return kd[:, None, :] / math.pi * (normal @ directions.T).clamp(min=0.0)[..., None]


def test_masks_flag_nonfinite_saturated_grown_and_shadowed():
    stack = torch.full((3, 2, 8, 8), 0.5, dtype=torch.float64)
    stack[0, 1, 2, 3] = math.nan
    stack[1, :, 5, 5] = 2.0  # clipped: the stack's maximum, shared by 16+ samples below
    stack[2, :, 0:4, 0:4] = 2.0
    stack[2, :, 7, 0] = 0.001  # a shadow: far below its pixel's median 0.5
    masks = sample_masks(stack, grow=1)
    assert masks.nonfinite[0, 2, 3] and masks.nonfinite.sum() == 1
    assert masks.saturated[1, 5, 5] and masks.saturated[1, 4, 6] and masks.saturated[1, 6, 4]  # grown by 1
    assert not masks.saturated[1, 2, 2] and masks.saturated[1].sum() == 9
    assert masks.saturated[2, 4, 4] and not masks.saturated[2, 5, 5]
    assert masks.shadowed[2, 7, 0] and masks.shadowed.sum() == 1
    assert masks.counts() == {"nonfinite": 1, "saturated": 9 + 25, "shadowed": 1}
    # Explicit level; no plateau -> nothing saturated by detection.
    assert sample_masks(stack, saturation=0.4, grow=0).saturated.sum() == 3 * 64 - 2  # all but the NaN and the shadow
    unique = torch.rand(2, 1, 5, 5, generator=torch.Generator().manual_seed(0))
    assert not sample_masks(unique).saturated.any()


def test_masks_reject_bad_shapes():
    with pytest.raises(ValueError, match=r"\(K, C, H, W\)"):
        sample_masks(torch.zeros(3, 4, 4))


def test_grid_layout_finds_clipped_grid_and_rejects_scattered():
    l = _grid()[:, :2]
    found = grid_layout(l)
    assert found is not None
    row, col, dy, dx = found.row, found.col, found.spacing_y, found.spacing_x
    assert int(row.max()) + 1 == 10 and int(col.max()) + 1 == 10  # the disk clips the outer ring
    assert dx == pytest.approx(1.6 / 11) and dy == pytest.approx(1.6 / 11)
    assert grid_layout(torch.rand(20, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)) is None
    assert grid_layout(torch.cat([l, l[:1]])) is None  # a cell twice


@pytest.mark.parametrize("scattered", [False, True])
def test_lowpass_keeps_constants_fills_gaps_and_matches_kernel_smoothing(scattered):
    l = _grid()[:, :2]
    if scattered:
        l = l + 1e-3 * torch.randn(l.shape, generator=torch.Generator().manual_seed(2), dtype=l.dtype)
    k = l.shape[0]
    samples = torch.full((4, k, 3), 0.7, dtype=torch.float64)
    valid = torch.ones(4, k, dtype=torch.bool)
    valid[0, :10] = False
    samples[0, :10] = math.nan
    out = lowpass(samples, l, sigma=0.1, valid=valid)
    err = (out - 0.7).abs().max()
    assert err < 1e-12, f"max error {err:.3g}"
    # A linear ramp: symmetric smoothing keeps it inside (away from the edges), brute force as reference.
    ramp = (l @ torch.tensor([1.0, -2.0], dtype=l.dtype))[None, :, None].expand(1, k, 1)
    smooth = lowpass(ramp, l, sigma=0.1)
    d2 = torch.cdist(l, l) ** 2
    weights = torch.exp(-0.5 * d2 / 0.01)
    if not scattered:  # kornia's kernel stops at ceil(3 sigma) cells per axis: a square window
        cells = grid_layout(l)
        index = torch.stack([cells.row, cells.col], -1)
        half = math.ceil(3 * 0.1 / cells.spacing_y)
        weights = weights * ((index[:, None] - index[None]).abs() <= half).all(-1)
    brute = (weights @ ramp[0, :, 0]) / weights.sum(-1)
    err = (smooth[0, :, 0] - brute).abs().max()
    assert err < 1e-6, f"max error {err:.3g}"
    assert torch.equal(torch.isnan(lowpass(samples, l, sigma=0.0, valid=valid)), ~valid[..., None].expand_as(samples))


def _lights(kernel, dtype):
    centres = _grid(dtype)
    k = centres.shape[0]
    return Lights(centres, kernel, torch.ones(k, 1, dtype=dtype), torch.ones(k, dtype=dtype))


@pytest.mark.parametrize("kernel", [Kernel("point"), Kernel("gaussian", sigma=0.08)], ids=["point", "gaussian"])
def test_photometric_stereo_recovers_planted_lambertian(kernel, dtype):
    lights = _lights(kernel, torch.float64)
    d = diffuse_directions(lights)
    normal = _normals(64, 12.0, 0, torch.float64)
    kd = torch.rand(64, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.8 + 0.05
    samples = _lambertian(normal, kd, d).to(dtype)
    fit = photometric_stereo(samples, d.to(dtype))
    error = torch.rad2deg(angle(fit.normal.double(), normal.double())).max()
    kd_err = ((fit.diffuse.double() - kd).abs() / kd).max()
    assert error < (1e-6 if dtype == torch.float64 else 0.05), f"max normal error {error:.3g} deg"
    assert kd_err < TOL[dtype], f"max k_d relative error {kd_err:.3g}"
    assert fit.normal.dtype == dtype and fit.quality.min() > 0.9
    assert fit.inliers.all()


def test_photometric_stereo_drops_a_specular_peak_and_masked_samples():
    lights = _lights(Kernel("gaussian", sigma=0.08), torch.float64)
    d = diffuse_directions(lights)
    normal = _normals(32, 10.0, 4, torch.float64)
    kd = torch.full((32, 3), 0.4, dtype=torch.float64)
    samples = _lambertian(normal, kd, d)
    # A bright peak around each pixel's mirror direction, as a lobe adds it.
    mirror = (2 * normal[:, 2:] * normal)[:, :2]
    l = lights.directions[:, :2]
    peak = 2.0 * torch.exp(-((l[None] - mirror[:, None]) ** 2).sum(-1) / (2 * 0.12**2))
    samples = samples + peak[..., None]
    valid = torch.ones(32, l.shape[0], dtype=torch.bool)
    valid[:, 5] = False
    samples[:, 5] = math.nan
    fit = photometric_stereo(samples, d, valid=valid)
    error = torch.rad2deg(angle(fit.normal.double(), normal.double())).max()
    assert error < 0.05, f"max normal error {error:.3g} deg"
    kd_err = ((fit.diffuse - kd).abs() / kd).max()
    assert kd_err < 5e-3, f"max k_d relative error {kd_err:.3g}"
    assert not fit.inliers[:, 5].any()
    hot = peak > 0.01 * 0.4 / math.pi
    assert not (fit.inliers & hot).any(), "a sample of the peak was kept"


def test_photometric_stereo_line_layout_gives_minimum_norm_normal():
    theta = torch.linspace(-0.5, 0.5, 21, dtype=torch.float64)
    axis = torch.tensor([math.cos(0.7), math.sin(0.7)], dtype=torch.float64)
    d = from_plane(theta[:, None] * axis)
    across = torch.tensor([-axis[1], axis[0]], dtype=torch.float64)
    truth = normalize(torch.tensor([[0.05 * axis[0], 0.05 * axis[1], 1.0]], dtype=torch.float64))
    samples = _lambertian(truth, torch.ones(1, 1, dtype=torch.float64), d)
    fit = photometric_stereo(samples, d)
    assert abs(float(fit.normal[0, :2] @ across)) < 1e-9
    assert float((fit.normal * truth).sum()) > 1 - 1e-9


def test_photometric_stereo_bad_shapes():
    d = torch.eye(3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"\(N, K, C\)"):
        photometric_stereo(torch.zeros(3, 3), d)
    with pytest.raises(ValueError, match=r"directions must have shape \(4, 3\)"):
        photometric_stereo(torch.zeros(2, 4, 1), d)
    with pytest.raises(ValueError, match="trim"):
        photometric_stereo(torch.zeros(2, 3, 1), d, trim=1.0)


def test_masks_in_bands_equal_masks_at_once(monkeypatch):
    import torchspec.start.photometric as photometric

    g = torch.Generator().manual_seed(7)
    stack = torch.rand(5, 3, 13, 9, generator=g, dtype=torch.float64)
    stack[2, :, 4:6, 3:5] = 1.0
    stack[:, :, 0, 0] = 1.0  # a clipped plateau of 16+ samples
    stack[1, 0, 7, 7] = math.inf
    stack[3, :, 11, 2] = 1e-4
    whole = sample_masks(stack, grow=2)
    monkeypatch.setattr(photometric, "BAND_ELEMENTS", 5 * 3 * 9 * 2)  # two rows per band
    banded = sample_masks(stack, grow=2)
    for name in ("nonfinite", "saturated", "shadowed"):
        assert torch.equal(getattr(whole, name), getattr(banded, name)), name
    assert whole.saturated.any() and whole.nonfinite.any() and whole.shadowed.any()
