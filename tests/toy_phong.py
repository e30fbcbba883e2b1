"""A toy reflectance model added from outside the package, as a user would: a normalised Phong
lobe ``(m + 2) / (2 pi) <r, w_i>^m <n, w_i>`` about the view's mirror direction ``r``, its exponent
from the roughness (``m = 2 / alpha^2 - 2``, Beckmann's width), and a model ``phong`` using it.

It is the whole of what a new model needs (tests/test_model_registry.py): the lobe's value at
directions (the renderer integrates it, forward-mode AD gives the fit its Jacobian), the model's
parameters declared once, and one registration (``register(PHONG)`` or ``with registered(PHONG)``).
"""

import math
from dataclasses import dataclass

import torch

from torchspec.model.lobes import Lobe
from torchspec.model.registry import ALPHA, DIFFUSE, GREY, NORMAL, Model


@dataclass(frozen=True)
class PhongLobe(Lobe):
    name: str = "phong"

    def cosine(self, wi, wo, n, alpha, rotation=None):
        ci, co = (n * wi).sum(-1), (n * wo).sum(-1)
        a = alpha[..., 0]
        front = (ci > 0) & (co > 0) & (a > 0)
        a = torch.where(front, a, torch.ones_like(a))
        exponent = 2.0 / a**2 - 2.0
        mirror = 2.0 * co[..., None] * n - wo
        c = (mirror * wi).sum(-1)
        lit = front & (c > 0)
        c = torch.where(lit, c, torch.ones_like(c)).clamp(max=1.0)
        value = (exponent + 2.0) / (2.0 * math.pi) * torch.exp(exponent * torch.log(c)) * ci
        return torch.where(lit, value, torch.zeros_like(value))


PHONG = Model("phong", (NORMAL, DIFFUSE, GREY, ALPHA), PhongLobe())
