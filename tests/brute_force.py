"""An independent brute-force evaluation of the measurement model, for tests only.

Shares no code with the package: the Ward BRDF is written from docs/capture-format.md with explicit
``tan(theta_h)`` and ``phi_h``, kernels from their definitions (normalisers by trapezoid on a
fine grid), and the integral is a midpoint rule on a fine Cartesian grid of the l-plane, cells
cut by the unit circle replaced by their 8 x 8 sub-cells inside it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

F64 = torch.float64


def ward_brdf(wi, wo, n, alpha_x, alpha_y, rotation):
    """Ward's specular BRDF for k_s = 1, from the format's formula."""
    ci, co = (n * wi).sum(-1), (n * wo).sum(-1)
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    s = x - (x * n).sum(-1, keepdim=True) * n
    s = s / s.norm(dim=-1, keepdim=True)
    t = torch.linalg.cross(n, s, dim=-1)
    s, t = math.cos(rotation) * s + math.sin(rotation) * t, math.cos(rotation) * t - math.sin(rotation) * s
    theta = torch.acos((h * n).sum(-1).clamp(-1.0, 1.0))
    phi = torch.atan2((h * t).sum(-1), (h * s).sum(-1))
    lobe = torch.exp(-(torch.tan(theta) ** 2) * (torch.cos(phi) ** 2 / alpha_x**2 + torch.sin(phi) ** 2 / alpha_y**2))
    value = lobe / (4.0 * math.pi * alpha_x * alpha_y * torch.sqrt((ci * co).clamp(min=1e-300)))
    return torch.where((ci > 0) & (co > 0), value, torch.zeros_like(value))


def kernel_density(kind, w, centre, *, sigma=0.0, power=2.0, table=None, extent=0.0):
    """Density per unit l-plane area at directions ``w (M, 3)`` for one frame's ``centre``."""
    if kind == "gaussian-projected":
        d2 = ((w[:, :2] - centre[:2]) ** 2).sum(-1)
        return torch.exp(-d2 / (2.0 * sigma**2)) / (2.0 * math.pi * sigma**2)
    if kind == "tabulated":
        # The cubic B-spline with the table as control points (scipy's), row 0 at +y, of unit mass.
        from scipy.ndimage import map_coordinates

        hk, wk = table.shape
        pad = 4
        padded = np.pad(table.numpy(), pad)
        fx = ((w[:, 0] - centre[0]) / extent + 1.0) * wk / 2.0 - 0.5 + pad
        fy = (1.0 - (w[:, 1] - centre[1]) / extent) * hk / 2.0 - 0.5 + pad
        value = map_coordinates(padded, [fy.numpy(), fx.numpy()], order=3, mode="constant", cval=0.0, prefilter=False)
        return torch.from_numpy(value) / (table.sum() * (2 * extent / wk) * (2 * extent / hk))
    angle = torch.acos((w * centre).sum(-1).clamp(-1.0, 1.0))
    if kind == "gaussian-angular":

        def profile(g):
            return torch.exp(-(g**2) / (2.0 * sigma**2))
    else:  # super-Gaussian, angular

        def profile(g):
            return torch.exp(-((g / sigma) ** power))

    g = torch.linspace(0.0, math.pi, 400001, dtype=F64)
    norm = 2.0 * math.pi * torch.trapezoid(profile(g) * torch.sin(g), g)
    return profile(angle) / norm / w[:, 2].clamp(min=1e-300)


def integrate(kind, centre, normal, *, k_d, k_s, alpha, rotation, box_centre, half, step, view=None, **kernel):
    """``integral D(l) [k_d / pi + k_s Ward] <n, w> dl`` over the disk (irradiance and exposure 1),
    on the square of half-size ``half`` about ``box_centre`` with spacing ``step``: (diffuse, specular)."""
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64) if view is None else view
    count = int(round(2 * half / step))
    offsets = (torch.arange(count, dtype=F64) + 0.5) * step - half
    gx, gy = torch.meshgrid(box_centre[0] + offsets, box_centre[1] + offsets, indexing="ij")
    l = torch.stack([gx, gy], -1).reshape(-1, 2)
    r = (l * l).sum(-1).sqrt()
    # Cells cut by the unit circle: replaced by their 8 x 8 sub-cells inside it (the midpoint rule
    # alone errs O(h) at that discontinuity, and so does weighting the centre by the area inside).
    edge = (r - 1.0).abs() < step
    sub = ((torch.arange(8, dtype=F64) + 0.5) / 8 - 0.5) * step
    sx, sy = torch.meshgrid(sub, sub, indexing="ij")
    fine = (l[edge][:, None, :] + torch.stack([sx, sy], -1).reshape(1, -1, 2)).reshape(-1, 2)
    points = torch.cat([l[~edge & (r < 1.0)], fine[(fine * fine).sum(-1) < 1.0]])
    area = torch.cat([torch.full((int((~edge & (r < 1.0)).sum()),), step * step, dtype=F64),
                      torch.full((int(((fine * fine).sum(-1) < 1.0).sum()),), step * step / 64, dtype=F64)])
    w = torch.cat([points, torch.sqrt((1.0 - (points * points).sum(-1)).clamp(min=0.0))[:, None]], -1)
    weight = kernel_density(kind, w, centre, **kernel) * area
    cos = (w * normal).sum(-1).clamp(min=0.0)
    diffuse = k_d / math.pi * (weight * cos).sum()
    spec = ward_brdf(w, view.expand_as(w), normal.expand_as(w), alpha[0], alpha[1], rotation)
    specular = k_s * (weight * spec * cos).sum()
    return diffuse.item(), specular.item()


def random_case(seed, kernel_width):
    """A random pixel and light: tilt <= 30 deg, alpha in [0.005, 0.5] (up to 10:1, rotated),
    light 0..75 deg from the zenith, every other case near the mirror direction."""
    g = torch.Generator().manual_seed(seed)

    def uniform(a, b):
        return a + (b - a) * torch.rand((), generator=g, dtype=F64).item()

    tilt, azimuth = math.radians(uniform(0, 30)), uniform(0, 2 * math.pi)
    normal = torch.tensor(
        [math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)], dtype=F64
    )
    ratio = [1.0, 3.0, 1.0, 10.0][(seed // 2) % 4]  # anisotropy, for lit and unlit cases alike
    alpha_x = math.exp(uniform(math.log(0.005 * ratio), math.log(0.5)))
    alpha = (alpha_x, alpha_x / ratio)
    rotation = uniform(0, math.pi)
    if seed % 2 == 0:  # the specular lobe lights up
        theta, phi = min(math.radians(75), 2 * tilt + uniform(-2, 2) * kernel_width), azimuth
    else:
        theta, phi = math.radians(uniform(0, 75)), uniform(0, 2 * math.pi)
    theta = abs(theta)
    centre = torch.tensor(
        [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)], dtype=F64
    )
    return normal, alpha, rotation, centre


def reference_value(kernel_args, kernel_width, normal, alpha, rotation, centre, k_d, k_s):
    """The value (irradiance 1) of one pixel under one frame, and its specular part, with boxes
    and steps chosen to resolve the narrower of kernel and lobe (and a tabulated kernel's pixels)."""
    mirror = 2.0 * normal[2] * normal - torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    lobe_width = 2.5 * max(alpha)
    common = dict(k_d=k_d, k_s=k_s, alpha=alpha, rotation=rotation, **kernel_args)
    reach = 2.0 * kernel_width if kernel_args["kind"] in ("supergaussian", "tabulated") else 7.0 * kernel_width
    kernel_step = kernel_width / 30
    if kernel_args["kind"] == "tabulated":  # the spline has a knot per pixel: six samples per pixel
        kernel_step = min(kernel_step, 2.0 * kernel_args["extent"] / max(kernel_args["table"].shape) / 6.0)
    diffuse, _ = integrate(
        centre=centre,
        normal=normal,
        box_centre=centre[:2],
        half=reach,
        step=kernel_step,
        **{**common, "k_s": 0.0},
    )
    narrow = min(alpha) / 2.0  # a fraction of the lobe's narrowest l-plane std, ~1.4 min(alpha)
    if lobe_width < kernel_width:
        box, half, step = mirror[:2], min(8.0 * lobe_width, 1.1), min(lobe_width / 30, narrow)
    else:
        box, half, step = centre[:2], reach, min(kernel_step, narrow)
    _, specular = integrate(centre=centre, normal=normal, box_centre=box, half=half, step=step, **common)
    return diffuse + specular, specular


def pixel_tensors(normal, k_d, alpha, rotation):
    """One pixel's ``normal, k_d, k_s (= 1), alpha, rotation`` as the ``(1, ...)`` tensors an SVBRDF
    takes, in float64."""
    return (
        normal[None],
        torch.tensor([[k_d]], dtype=F64),
        torch.tensor([[1.0]], dtype=F64),
        torch.tensor([alpha], dtype=F64),
        torch.tensor([rotation], dtype=F64),
    )
