import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.model import geometry as g

F64 = torch.float64


def _unit(n, seed):
    v = torch.randn(n, 3, dtype=F64, generator=torch.Generator().manual_seed(seed))
    v[:, 2] = v[:, 2].abs() + 0.1
    return v / v.norm(dim=-1, keepdim=True)


def test_plane_round_trip_and_horizon():
    w = _unit(50, 0)
    torch.testing.assert_close(g.from_plane(g.to_plane(w)), w)
    beyond = g.from_plane(torch.tensor([[1.2, 0.0]], dtype=F64))
    assert beyond[0, 2].item() == 0.0


def test_reflect_and_halfway():
    n, w = _unit(20, 1), _unit(20, 2)
    w = torch.where((g.dot(w, n) > 0)[:, None], w, g.reflect(-w, n))  # in front of n
    r = g.reflect(w, n)
    torch.testing.assert_close(r.norm(dim=-1), torch.ones(20, dtype=F64))
    torch.testing.assert_close(g.dot(r, n), g.dot(w, n))  # the angle to the normal is kept
    h = g.halfway(w, r)
    torch.testing.assert_close(h, n)  # the halfway vector of a mirror pair is the normal
    assert g.halfway(n, -n).abs().sum().item() == 0.0  # opposite directions: zero, not NaN


def test_tangent_frame_orthonormal_and_rotation():
    n = _unit(30, 3)
    s, t = g.tangent_frame(n)
    eye = torch.stack([s, t, n], -1).transpose(-1, -2) @ torch.stack([s, t, n], -1)
    torch.testing.assert_close(eye, torch.eye(3, dtype=F64).expand(30, 3, 3))
    assert (s[:, 1].abs() < 1e-12).logical_or(n[:, 1].abs() > 0).all()  # s lies in the plane of x and n
    angle = torch.full((30,), 0.7, dtype=F64)
    s2, t2 = g.tangent_frame(n, angle)
    torch.testing.assert_close(g.dot(s2, s), torch.cos(angle))  # counter-clockwise about n
    torch.testing.assert_close(g.dot(s2, t), torch.sin(angle))
    torch.testing.assert_close(torch.linalg.cross(n, s2, dim=-1), t2)


def test_tangent_frame_degenerate_normal_is_finite():
    s, t = g.tangent_frame(torch.tensor([[1.0, 0.0, 0.0]], dtype=F64))
    assert torch.isfinite(s).all() and torch.isfinite(t).all() and abs(s.norm().item() - 1) < 1e-12


@settings(max_examples=50, deadline=None)
@given(a=st.floats(-1.4, 1.4), b=st.floats(-1.4, 1.4))
def test_normal_angles_round_trip(a, b):
    angles = torch.tensor([a, b], dtype=F64)
    n = g.normal_from_angles(angles)
    assert abs(n.norm().item() - 1.0) < 1e-12 and n[2] > 0
    torch.testing.assert_close(g.angles_from_normal(n), angles, atol=1e-10, rtol=0)


@settings(max_examples=50, deadline=None)
@given(a=st.floats(-1.4, 1.4), b=st.floats(-1.4, 1.4))
def test_normal_derivative_is_that_of_normal_from_angles(a, b):
    angles = torch.tensor([[a, b]], dtype=F64)
    expected = torch.autograd.functional.jacobian(g.normal_from_angles, angles)[0, :, 0]  # (3, 2)
    n = g.normal_from_angles(angles)
    found = g.normal_derivative(n)
    assert found.shape == (1, 3, 2)
    torch.testing.assert_close(found[0], expected, atol=1e-12, rtol=1e-10)
    # at the angles of n: a normal of any length gives the same (as angles_from_normal does)
    torch.testing.assert_close(g.normal_derivative(2.5 * n), found, atol=1e-12, rtol=1e-10)


def test_normal_angles_smooth_at_zenith():
    angles = torch.zeros(1, 2, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(g.normal_from_angles, (angles,))
    assert math.isclose(g.normal_from_angles(angles)[0, 2].item(), 1.0)


def test_angle_is_accurate_near_zero_and_pi():
    import math

    from torchspec.model.geometry import angle

    e = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for t in (1e-9, 1e-4, 0.5, math.pi / 2, math.pi - 1e-9):
        b = torch.tensor([math.cos(t), math.sin(t), 0.0], dtype=torch.float64)
        got = float(angle(e, b))
        assert abs(got - t) <= 1e-15 * max(t, 1.0), f"angle {t}: error {got - t:.3g}"
    batch = angle(e.expand(4, 3), torch.eye(3, dtype=torch.float64)[[0, 1, 2, 0]])
    assert torch.allclose(batch, torch.tensor([0.0, math.pi / 2, math.pi / 2, 0.0], dtype=torch.float64))
