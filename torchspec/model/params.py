"""The parameters a reflectance model declares (:class:`torchspec.model.registry.Model`): each a name, a
size (one, two, or one per channel), the bound the solver keeps it in and the
:class:`~torchspec.SVBRDF` field it fills. A model's packing, bounds, Jacobian columns and maps
are derived from its tuple of them.

How a parameter fills its field (:meth:`Param.fill`) and is read back from one (:meth:`Param.pack`):

==============  =====================================  ==========================================
field           filled by                              read back as
==============  =====================================  ==========================================
``normal``      two tilt angles                        :func:`torchspec.model.geometry.angles_from_normal`
                (:func:`~torchspec.model.geometry.normal_from_angles`)
``rotation``    one angle                              the rotation (0 where ``None``)
``roughness``,  ``alpha_x, alpha_y``, or one ``alpha``  themselves, or their mean
``roughness2``  for both
others          their values (one per channel, or      themselves (expanded to the channels), or
                one grey value)                        their mean (grey)
==============  =====================================  ==========================================

Example:
    >>> import torch
    >>> alpha = Param("alpha", "roughness", bound="roughness")
    >>> alpha.fill(torch.tensor([[0.2]]))  # an isotropic alpha fills alpha_x and alpha_y
    tensor([[0.2000, 0.2000]])
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import TorchspecError
from .brdf import SVBRDF
from .geometry import angles_from_normal, normal_from_angles

__all__ = ["Param", "FIELDS", "PARAM_BOUNDS", "check_params"]

FIELDS = ("normal", "diffuse", "specular", "roughness", "rotation", "specular2", "roughness2")
"""The SVBRDF fields a parameter may fill, in :mod:`torchspec.model.jacobian`'s order."""
PARAM_BOUNDS = ("free", "nonnegative", "roughness")
"""A parameter's bound: none, ``>= 0`` (softplus), or within the roughness interval
(:data:`torchspec.model.registry.ALPHA_BOUNDS`, a sigmoid; :class:`torchspec.lm.Bounds`)."""
_SIZES = {"normal": (2,), "rotation": (1,), "roughness": (1, 2), "roughness2": (1, 2)}


@dataclass(frozen=True)
class Param:
    """One parameter of a model, or one per channel.

    Attributes:
        name: its name in the docs (``k_s``, ``alpha``).
        field: the :class:`~torchspec.SVBRDF` field it fills (:data:`FIELDS`).
        size: its values per pixel (2 for the normal's angles, 1 or 2 for a roughness).
        per_channel: one value per channel (``size`` ignored).
        bound: :data:`PARAM_BOUNDS`.
    """

    name: str
    field: str
    size: int = 1
    per_channel: bool = False
    bound: str = "free"

    def __post_init__(self):
        if self.field not in FIELDS:
            raise TorchspecError(f"Param {self.name!r}: field must be one of {FIELDS}; got {self.field!r}.")
        if self.bound not in PARAM_BOUNDS:
            raise TorchspecError(f"Param {self.name!r}: bound must be one of {PARAM_BOUNDS}; got {self.bound!r}.")
        sizes = _SIZES.get(self.field)
        if sizes is not None and (self.per_channel or self.size not in sizes):
            raise TorchspecError(f"Param {self.name!r} of {self.field}: size must be one of {sizes}, not per channel.")

    def count(self, channels: int) -> int:
        """Its values per pixel for ``channels`` channels."""
        return channels if self.per_channel else self.size

    def fill(self, values: Tensor) -> Tensor:
        """Its field's value from its columns ``values (N, count)``."""
        if self.field == "normal":
            return normal_from_angles(values)
        if self.field == "rotation":
            return values[:, 0]
        if self.field in ("roughness", "roughness2") and self.size == 1:
            return values.expand(-1, 2)
        return values

    def pack(self, svbrdf: SVBRDF, model: str = "") -> Tensor:
        """Its columns ``(N, count)`` read from a flat ``svbrdf``'s field."""
        if self.field == "normal":
            return angles_from_normal(svbrdf.normal)
        if self.field == "rotation":
            rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(svbrdf.roughness[:, 0])
            return rotation[:, None]
        value = getattr(svbrdf, self.field)
        if value is None:
            raise TorchspecError(f"model {model!r} needs SVBRDF.{self.field} to start from; the SVBRDF has none.")
        if self.per_channel:
            return value.expand(-1, svbrdf.diffuse.shape[-1])
        return value if self.size == value.shape[-1] and self.size > 1 else value.mean(-1, keepdim=True)


def check_params(model: str, params: tuple[Param, ...], lobe: bool) -> None:
    """That ``params`` make a model: the normal's angles and ``k_d`` first, each field filled
    once, ``k_s`` and a roughness iff it has a ``lobe``, a second lobe's two together.

    Raises:
        TorchspecError: naming the model and what is missing or extra.
    """
    fields = [p.field for p in params]
    if fields[:2] != ["normal", "diffuse"] or not params[1].per_channel:
        raise TorchspecError(
            f"model {model!r}: its parameters must start with the normal's angles and k_d per channel."
        )
    if len(set(fields)) != len(fields):
        raise TorchspecError(f"model {model!r}: each SVBRDF field may be filled once; got {fields}.")
    if lobe != ("specular" in fields) or lobe != ("roughness" in fields):
        raise TorchspecError(f"model {model!r}: a lobe needs k_s and a roughness, and they need a lobe; got {fields}.")
    if ("specular2" in fields) != ("roughness2" in fields):
        raise TorchspecError(f"model {model!r}: a second lobe needs both k_s2 and alpha2; got {fields}.")
    if "rotation" in fields and [p.size for p in params if p.field == "roughness"] != [2]:
        raise TorchspecError(f"model {model!r}: a rotation needs alpha_x and alpha_y (a roughness of size 2).")
