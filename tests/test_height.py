"""Height from normals (torchspec.model.height): exact on planes, accurate on smooth reliefs, the
capture format's sign conventions, weights that ignore corrupted normals, shapes refused."""

import math

import pytest
import torch

from torchspec.errors import TorchspecError
from torchspec.model.height import dct, height_from_normals, idct, normals_from_height
from torchspec.simulate.relief import ReliefConfig, relief

F64 = torch.float64


def _grid(h, w):
    return torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")


def _rms(a, b):
    return float((a - a.mean() - (b - b.mean())).square().mean().sqrt())


def test_dct_round_trip_and_scipy():
    scipy_fft = pytest.importorskip("scipy.fft")
    x = torch.randn(3, 7, 5, dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(idct(dct(x, 1), 1), x, atol=1e-13)
    assert torch.allclose(dct(x), torch.from_numpy(scipy_fft.dct(x.numpy(), type=2)) / 2, atol=1e-12)


def test_plane_is_exact_and_signs_follow_the_format():
    rows, cols = _grid(9, 12)
    plane = 0.3 * cols - 0.2 * rows  # rises to the right and towards the bottom row
    n = normals_from_height(plane)
    # Surface x is the columns, y up the rows: the normal leans away from the rise.
    assert bool((n[..., 0] < 0).all()) and bool((n[..., 1] < 0).all())
    height = height_from_normals(n)
    assert torch.allclose(height, plane - plane.mean(), atol=1e-12)


def test_tilted_normal_up_the_image_means_height_falls_up_the_image():
    # A normal leaning towards +y (up the image) is a surface that descends towards row 0.
    n = torch.tensor([0.0, math.sin(0.3), math.cos(0.3)], dtype=F64).expand(6, 5, 3)
    height = height_from_normals(n)
    assert torch.allclose(height[1:] - height[:-1], torch.full((5, 5), math.tan(0.3), dtype=F64), atol=1e-12)


def test_relief_integrates_to_a_small_rms_in_pixels():
    r = relief(ReliefConfig(seed=3), 48, 56)
    height = height_from_normals(r.normal)
    assert _rms(height, r.height) < 0.02 * float(r.height.std())
    assert abs(float(height.mean())) < 1e-12


def test_pitch_scales_heights():
    r = relief(ReliefConfig(seed=1), 20, 24)
    assert torch.allclose(height_from_normals(r.normal, pitch=0.1), 0.1 * height_from_normals(r.normal), atol=1e-12)


def test_weights_ignore_corrupted_normals():
    r = relief(ReliefConfig(seed=2), 32, 32)
    g = torch.Generator().manual_seed(0)
    bad = torch.rand(32, 32, generator=g, dtype=F64) < 0.1
    noise = torch.nn.functional.normalize(torch.rand(32, 32, 3, generator=g, dtype=F64) + 0.1, dim=-1)
    corrupted = torch.where(bad[..., None], noise, r.normal)
    corrupted[0, 0] = float("nan")
    weight = (~bad).to(F64)
    plain = _rms(height_from_normals(corrupted), r.height)  # NaN pixel: weight 0 in both
    weighted = _rms(height_from_normals(corrupted, weight, iterations=40), r.height)
    clean = _rms(height_from_normals(r.normal), r.height)
    # The corrupted pixels' slopes are lost (filled flat): a small error left, far below the plain one's.
    assert weighted < 0.1 * plain and clean < weighted < 0.05 * float(r.height.std())


def test_uniform_weights_match_the_closed_form():
    r = relief(ReliefConfig(seed=4), 16, 20)
    weight = torch.full((16, 20), 3.0, dtype=F64)
    # The preconditioner is the unweighted solve: exact at once.
    assert torch.allclose(height_from_normals(r.normal, weight, iterations=3), height_from_normals(r.normal), atol=1e-9)


def test_batch_dtype_and_device_follow_the_input(device):
    r = relief(ReliefConfig(seed=5), 12, 14, dtype=torch.float32, device=device)
    batch = torch.stack([r.normal, r.normal.flip(0)])
    height = height_from_normals(batch, torch.ones(12, 14, device=device))
    assert height.shape == (2, 12, 14) and height.dtype == torch.float32 and height.device.type == device.type
    single = height_from_normals(r.normal)
    assert torch.allclose(height[0], single, atol=1e-4)


@pytest.mark.parametrize("shape", [(4, 5), (4, 5, 2), (1, 2, 4, 5, 3)])
def test_bad_shapes_name_the_shape(shape):
    with pytest.raises(TorchspecError, match=r"\(H, W, 3\).*" + r"\(" + str(shape[0])):
        height_from_normals(torch.zeros(shape))


def test_bad_weight_and_pitch_are_refused():
    n = torch.zeros(4, 5, 3)
    n[..., 2] = 1
    with pytest.raises(TorchspecError, match="weight"):
        height_from_normals(n, torch.ones(5, 4))
    with pytest.raises(TorchspecError, match="pitch"):
        height_from_normals(n, pitch=0.0)
