"""The kernels that render is checked with, each as the package's :class:`Kernel`, the brute
force's description (``tests/brute_force.py``) and a width: shared by ``tests/test_render.py``
and ``experiments/render_accuracy.py``."""

from __future__ import annotations

import torch

from torchspec.model.lights import Kernel

F64 = torch.float64


def table():
    """A smooth, slightly asymmetric blob: a tabulated kernel as a calibration would give."""
    y, x = torch.meshgrid(torch.linspace(-1, 1, 24, dtype=F64), torch.linspace(-1, 1, 24, dtype=F64), indexing="ij")
    return torch.exp(-((x - 0.1) ** 2 / 0.18 + (y + 0.05) ** 2 / 0.12) * 2.0)


KERNELS = {
    "gaussian projected 0.08": (
        Kernel("gaussian", "projected", 0.08),
        dict(kind="gaussian-projected", sigma=0.08),
        0.08,
    ),
    "gaussian projected 0.02": (
        Kernel("gaussian", "projected", 0.02),
        dict(kind="gaussian-projected", sigma=0.02),
        0.02,
    ),
    "gaussian angular 0.05": (Kernel("gaussian", "angular", 0.05), dict(kind="gaussian-angular", sigma=0.05), 0.05),
    "super-Gaussian 0.035^6": (
        Kernel("supergaussian", "angular", 0.035, 6.0),
        dict(kind="supergaussian", sigma=0.035, power=6.0),
        0.035,
    ),
    "tabulated 24x24": (
        Kernel("tabulated", table=table(), extent=0.15),
        dict(kind="tabulated", table=table(), extent=0.15),
        0.15,
    ),
}
