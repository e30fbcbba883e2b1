"""The residual term: a smooth per-pixel function of the light direction that carries what the
physical model cannot predict (cast shadows, interreflections, a near light's falloff), kept apart
from the physical maps so that normal, diffuse, specular and roughness stay physical.

Per pixel and channel, hemispherical harmonics of the light direction (the RTI fitters' HSH basis,
:func:`hsh_basis`: order 2, 4 terms, or order 3, 9 terms) added to the physical prediction in the
encoded domain of its value at unit light, where the photographs were recorded and are judged:

    value_k = scale_k decode(w encode(model_k / scale_k) + sum_j c_j H_j(l_k))

with ``scale_k`` the frame's exposure times irradiance, ``l_k`` its light's (effective) direction,
``w`` in ``[0, 1]`` the physical model's weight (1 but where the term alone predicts better), and
``encode`` the photographs' own encoding (:class:`TermDomain`): for a capture imported from
photographs whose camera response was estimated (``source.transfer: response``), that response
curve (:mod:`torchspec.calibration.response`), so that the term is fitted in the codes the photographs hold;
otherwise the sRGB transfer extended to every real value (:func:`encode`, :func:`decode`). A term
fitted in sRGB units on photographs whose codes are nearly linear weighs their dark values by the
wrong slope: on RealRTI item7 it predicted left-out photographs worse than the maps alone.

:func:`fit_term` fits the coefficients by least squares on a fit's valid samples and keeps them
only at the pixels where they predict frames left out of their fit better than the physical model
alone (:func:`torchspec.statistics.predicts_better`, the same rule that chooses models):
a term that only fits the frames it saw is not kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..calibration.response import ResponseCurve
from ..errors import TorchspecError
from ..io.images import Transfer
from ..start.photometric import MAD_SCALE
from ..statistics import predicts_better  # the selection rule of the fit's models
from .lights import Lights, diffuse_directions

__all__ = [
    "MAP_NAME",
    "WEIGHT_MAP",
    "TERMS",
    "ResidualTerm",
    "TermDomain",
    "hsh_basis",
    "encode",
    "decode",
    "term_directions",
    "fit_term",
    "blend",
]

TERMS = {2: 4, 3: 9}
"""Coefficients per channel of each order of the basis."""

MAP_NAME = "residual_term"
"""The term's map in an SVBRDF folder (``residual_term.exr``) and its key in ``svbrdf.json``."""
WEIGHT_MAP = "residual_term_weight"
"""The map of :attr:`ResidualTerm.weight` (``residual_term_weight.exr``): the physical model's
weight ``w`` in ``[0, 1]`` under the term (1: the model and the term; 0: the term alone, the RTI
fitters' HSH of the photographs)."""

_A = 0.055
_KNEE = 0.0031308


def encode(linear: Tensor) -> Tensor:
    """The sRGB transfer (IEC 61966-2-1), extended to every real value: odd (``-encode(-v)`` below
    0) and continued as ``1.055 v^(1/2.4) - 0.055`` above 1; a monotonic bijection of the reals."""
    size = linear.abs()
    curve = (1 + _A) * size.clamp(min=_KNEE).pow(1 / 2.4) - _A
    return torch.sign(linear) * torch.where(size <= _KNEE, 12.92 * size, curve)


def decode(encoded: Tensor) -> Tensor:
    """The inverse of :func:`encode`."""
    size = encoded.abs()
    curve = ((size.clamp(min=12.92 * _KNEE) + _A) / (1 + _A)).pow(2.4)
    return torch.sign(encoded) * torch.where(size <= 12.92 * _KNEE, size / 12.92, curve)


@dataclass(frozen=True)
class TermDomain:
    """The encoded domain a residual term is added in (module docstring): ``curve`` ``None``, the
    sRGB transfer extended to every real value (:func:`encode`); else a camera response
    (:class:`~torchspec.calibration.response.ResponseCurve`, codes to linear values), continued past its
    ends as :func:`encode` is: odd below 0 and along its slope at code 1 above 1, a monotonic
    bijection of the reals (a model brighter than white, or a term below black, stays defined).
    Values are channels last.

    Example:
        >>> domain = TermDomain(ResponseCurve(gamma=(2.0,), offset=(0.0,), contrast=(0.0,)))
        >>> domain.encode(torch.tensor([0.25, -0.25, 3.0])).tolist()  # 2 g'(1) = 2: 1 + 2 / 2
        [0.5, -0.5, 2.0]
    """

    curve: ResponseCurve | None = None

    def encode(self, linear: Tensor) -> Tensor:
        """Linear values to the domain's codes."""
        if self.curve is None:
            return encode(linear)
        size = linear.abs()
        slope = self.curve.slope_at_one(size)
        return torch.sign(linear) * torch.where(size > 1, 1 + (size - 1) / slope, self.curve.encode(size))

    def decode(self, encoded: Tensor) -> Tensor:
        """The inverse of :meth:`encode`."""
        if self.curve is None:
            return decode(encoded)
        size = encoded.abs()
        slope = self.curve.slope_at_one(size)
        return torch.sign(encoded) * torch.where(size > 1, 1 + (size - 1) * slope, self.curve.decode(size))

    def to_json(self) -> dict:
        """What ``svbrdf.json`` records under the term's ``encoding``."""
        if self.curve is None:
            return {"transfer": "srgb"}
        return {"transfer": "response", "response": self.curve.to_json()}

    @classmethod
    def from_json(cls, record: dict | None, where: str = "residual_term.encoding") -> TermDomain:
        """The domain of :meth:`to_json`; ``None`` (maps written before the record): sRGB.

        Raises:
            TorchspecError: an unknown transfer or a malformed curve, naming ``where``."""
        if record is None or record.get("transfer") == "srgb":
            return cls()
        if record.get("transfer") != "response":
            raise TorchspecError(f"{where}: transfer must be srgb or response; got {record.get('transfer')!r}.")
        return cls(ResponseCurve.from_json(record.get("response") or {}, f"{where}.response"))

    @classmethod
    def of_source(cls, source: dict | None) -> TermDomain:
        """The domain of a capture's ``source`` record (``capture.json``): its estimated camera
        response where the import estimated one (read by
        :meth:`torchspec.io.images.Transfer.of_source`), else sRGB."""
        transfer = Transfer.of_source(source)
        return cls(transfer.curve if transfer is not None and transfer.name == "response" else None)


def hsh_basis(directions: Tensor, order: int = 3) -> Tensor:
    """``(*, J)`` hemispherical harmonics (Gautron et al. 2004, as RTI fitters use them) of unit
    directions ``(*, 3)``: ``J = 4`` for order 2, ``9`` for order 3."""
    if order not in TERMS:
        raise TorchspecError(f"the residual term's order must be one of {sorted(TERMS)}; got {order}.")
    t = directions[..., 2].clamp(0, 1)
    phi = torch.atan2(directions[..., 1], directions[..., 0])
    s = (t - t * t).clamp(min=0).sqrt()
    terms = [
        torch.full_like(t, 1 / math.sqrt(2 * math.pi)),
        math.sqrt(6 / math.pi) * torch.cos(phi) * s,
        math.sqrt(3 / (2 * math.pi)) * (2 * t - 1),
        math.sqrt(6 / math.pi) * torch.sin(phi) * s,
    ]
    if order == 3:
        terms += [
            math.sqrt(30 / math.pi) * torch.cos(2 * phi) * (t * t - t),
            math.sqrt(30 / math.pi) * torch.cos(phi) * (2 * t - 1) * s,
            math.sqrt(5 / (2 * math.pi)) * (6 * t * t - 6 * t + 1),
            math.sqrt(30 / math.pi) * torch.sin(phi) * (2 * t - 1) * s,
            math.sqrt(30 / math.pi) * torch.sin(2 * phi) * (t * t - t),
        ]
    return torch.stack(terms, -1)


def term_directions(lights: Lights) -> Tensor:
    """``(K, 3)`` the direction the term is a function of: the light's for point lights, the
    kernel's effective (diffuse) direction for extended ones."""
    return lights.directions if lights.kernel.kind == "point" else diffuse_directions(lights)


@dataclass(frozen=True)
class ResidualTerm:
    """Each pixel's residual term.

    Attributes:
        coefficients: ``(*, J, C)`` per pixel, basis function and channel (0 where not chosen).
        chosen: ``(*,)`` bool, the pixels that carry a term.
        weight: ``(*,)`` the physical model's weight ``w`` in ``[0, 1]`` (module docstring), or
            ``None`` (1 everywhere): where the term alone (``w = 0``, an HSH of the
            photographs) predicts left-out frames better than the model with its term (``w = 1``),
            the blend of the two that predicts them best. The physical maps are unchanged.
        left_out: ``(*, S, K, C)`` the left-out prediction's errors (encoded units) of what is
            kept, per fold scheme, frame and channel, and ``noise`` (0-dim) the encoded noise level
            they were judged in: what :func:`fit_term` knows of its choice (not saved with the maps;
            ``None`` otherwise).
        domain: the encoded domain the term is added in (:class:`TermDomain`; ``None``: sRGB).
    """

    coefficients: Tensor
    chosen: Tensor
    weight: Tensor | None = None
    left_out: Tensor | None = None
    noise: Tensor | None = None
    domain: TermDomain | None = None

    @property
    def encoding(self) -> TermDomain:
        """:attr:`domain`, sRGB where it is ``None``."""
        return self.domain or TermDomain()

    @property
    def order(self) -> int:
        """The basis' order (from ``J``)."""
        count = self.coefficients.shape[-2]
        for order, terms in TERMS.items():
            if terms == count:
                return order
        raise TorchspecError(
            f"a residual term has {count} coefficients per channel; expected one of {list(TERMS.values())}."
        )

    def to_map(self) -> Tensor:
        """``(*, C J)`` the coefficients channel-major (channel ``c``'s term ``j`` at ``c J + j``),
        as ``residual_term.exr`` holds them (0 at pixels without a term)."""
        moved = self.coefficients.transpose(-1, -2)
        return moved.reshape(*moved.shape[:-2], -1)

    def description(self) -> dict:
        """What ``svbrdf.json`` records of the term under :data:`MAP_NAME`."""
        return {
            "basis": f"hemispherical harmonics of order {self.order} of the light direction (Gautron et al. 2004)",
            "terms": self.coefficients.shape[-2],
            "layout": "channel-major: channel c's coefficient j in EXR channel C{c*terms+j}",
            "domain": "value = scale * decode(w * encode(model / scale) + sum_j c_j H_j(l)), encode the transfer of "
            "'encoding' (srgb, or the capture's estimated camera response) extended to all reals, "
            "scale = exposure * irradiance",
            "encoding": self.encoding.to_json(),
            "pixels": int(self.chosen.sum()),
            "weight": f"{WEIGHT_MAP}.exr: the physical model's weight w in [0, 1]",
            "weight_pixels": self._weights(),
        }

    def _weights(self) -> dict:
        w = torch.ones_like(self.chosen, dtype=torch.float32) if self.weight is None else self.weight
        return {
            "model (w = 1)": int((w == 1).sum()),
            "term alone (w = 0)": int((w == 0).sum()),
            "blend (0 < w < 1)": int(((w > 0) & (w < 1)).sum()),
        }

    @staticmethod
    def from_map(
        image: Tensor,
        channels: int,
        source: str = "residual_term.exr",
        weight: Tensor | None = None,
        encoding: dict | None = None,
    ) -> ResidualTerm:
        """The term of a ``(*, C J)`` map (:meth:`to_map`) of ``channels`` channels, the
        :attr:`weight` map ``(*,)`` or ``(*, 1)`` when given, in the domain of ``encoding``
        (:meth:`TermDomain.to_json`, ``svbrdf.json``'s record of the term; ``None``: sRGB).

        Raises:
            TorchspecError: the map's channel count is not ``channels`` times a basis' size, or the
                weight is not in ``[0, 1]`` everywhere, naming ``source``.
        """
        count = image.shape[-1] if image.dim() >= 3 else 1
        if count % channels or count // channels not in TERMS.values():
            raise TorchspecError(
                f"{source}: {count} channels is not {channels} channels times one of {sorted(TERMS.values())} "
                "coefficients of a residual term."
            )
        coefficients = image.reshape(*image.shape[:-1], channels, count // channels).transpose(-1, -2)
        chosen = coefficients.ne(0).any(-1).any(-1)
        if weight is not None:
            weight = weight.to(image.device, image.dtype).reshape(chosen.shape)
            bad = ~((weight >= 0) & (weight <= 1))
            if bool(bad.any()):
                where = tuple(int(i) for i in bad.nonzero()[0])
                raise TorchspecError(
                    f"{source}: its weight map ({WEIGHT_MAP}.exr) must be in [0, 1]; it holds "
                    f"{float(weight[where])} at pixel (row, column) {where} and {int(bad.sum())} such value(s) in all."
                )
            chosen = chosen | (weight < 1)
        domain = TermDomain.from_json(encoding, f"{source}: svbrdf.json's {MAP_NAME}.encoding")
        return ResidualTerm(coefficients=coefficients, chosen=chosen, weight=weight, domain=domain)

    def apply(self, values: Tensor, lights: Lights) -> Tensor:
        """The physical prediction ``values (*, K, C)`` of the maps as they are, with the term
        added (and the model weighed by :attr:`weight`) at chosen pixels."""
        lights = lights.to(dtype=values.dtype, device=values.device)
        basis = hsh_basis(term_directions(lights), self.order)  # (K, J)
        coefficients = self.coefficients.to(values)
        if values.shape[:-2] != coefficients.shape[:-2] or values.shape[-1] != coefficients.shape[-1]:
            raise TorchspecError(
                f"a residual term of shape {tuple(coefficients.shape)} (pixels, terms, channels) does not match "
                f"values of shape {tuple(values.shape)} (pixels, frames, channels)."
            )
        scale = lights.scale
        term = torch.einsum("kj,...jc->...kc", basis, coefficients)
        weight = 1.0 if self.weight is None else self.weight.to(values)[..., None, None]
        domain = self.encoding
        added = domain.decode(weight * domain.encode(values / scale) + term) * scale
        return torch.where(self.chosen.to(values.device)[..., None, None], added, values)


def fit_term(
    observed: Tensor,
    valid: Tensor,
    model: Tensor,
    lights: Lights,
    folds: Tensor,
    *,
    order: int = 3,
    z: float = 3.0,
    ridge: float = 1e-6,
    held_out: Tensor | None = None,
    domain: TermDomain | None = None,
) -> ResidualTerm:
    """Fit the term on top of a physical prediction and keep it where it predicts left-out frames.

    Args:
        observed: ``(n, K, C)`` recorded values.
        valid: ``(n, K)`` bool, the samples to fit.
        model: ``(n, K, C)`` the physical model's prediction of them.
        lights: the ``K`` frames' lights (the directions and scales).
        folds: ``(S, K)`` each frame's fold per scheme
            (:func:`torchspec.pipeline.prediction.light_folds`).
        order: the basis' order (:data:`TERMS`).
        z: the margin of :func:`~torchspec.statistics.predicts_better`.
        ridge: Tikhonov damping relative to each pixel's mean diagonal (a pixel whose valid frames
            leave a coefficient undetermined gets it near 0 rather than a wild value).
        held_out: ``(n, S, K, C)`` the physical model's prediction of each sample from a fit
            without the sample's fold (:func:`torchspec.pipeline.prediction.held_out`), used for
            the left-out frames' errors; default ``model`` (a model that did not see the frames,
            or none). A model fitted on every frame predicts its own frames too well: judged on
            them, the term would look worse than it is, and the model better.
        domain: the encoded domain the term is fitted and judged in (default sRGB).

    Returns:
        a :class:`ResidualTerm` of ``n`` pixels, fitted on all valid samples where chosen.
    """
    dtype = observed.dtype
    lights = lights.to(dtype=dtype, device=observed.device)
    scale = lights.scale[None]  # (1, K, C or 1)
    to_codes = (domain or TermDomain()).encode
    recorded = to_codes(observed / scale)
    target = recorded - to_codes(model / scale)  # (n, K, C)
    weight = valid.to(dtype)
    target = target * weight[..., None]
    basis = hsh_basis(term_directions(lights), order)  # (K, J)
    outer = basis[:, :, None] * basis[:, None, :]  # (K, J, J)
    normal = torch.einsum("nk,kij->nij", weight, outer)
    right = torch.einsum("kj,nkc->njc", basis, target)
    coefficients = _solve(normal, right, ridge)
    count = int(folds.max()) + 1 if folds.numel() else 0
    schemes, plain = [], []
    for s, scheme in enumerate(folds):  # a handful of folds: each a batched solve over every pixel
        # what the model fitted without each fold leaves of it (default: the model's own residual)
        left_target = target if held_out is None else (recorded - to_codes(held_out[:, s] / scale)) * weight[..., None]
        errors = torch.zeros_like(target)
        for fold in range(count):
            out = scheme == fold
            held = torch.einsum("nk,kij->nij", weight[:, out], outer[out])
            partial = _solve(normal - held, right - torch.einsum("kj,nkc->njc", basis[out], target[:, out]), ridge)
            predicted = torch.einsum("kj,njc->nkc", basis[out], partial) * weight[:, out, None]
            errors[:, out] = left_target[:, out] - predicted
        schemes.append(errors)
        plain.append(left_target)
    # In the encoded domain, where the term is fitted and the photographs are judged, the samples'
    # noise is taken as one level: the robust spread of what the term leaves on the fitted frames.
    left = (target - torch.einsum("kj,njc->nkc", basis, coefficients) * weight[..., None])[valid]
    sigma = (MAD_SCALE * left.abs().median()).clamp(min=1e-4) if left.numel() else target.new_tensor(1.0)
    candidate, current = torch.stack(schemes, 1), torch.stack(plain, 1)  # (n, S, K, C), encoded units
    chosen = predicts_better(candidate / sigma, current / sigma, z)
    coefficients = torch.where(chosen[:, None, None], coefficients, torch.zeros_like(coefficients))
    kept = torch.where(chosen[:, None, None, None], candidate, current)
    return ResidualTerm(coefficients=coefficients, chosen=chosen, left_out=kept, noise=sigma, domain=domain)


def _solve(normal: Tensor, right: Tensor, ridge: float) -> Tensor:
    size = normal.shape[-1]
    damping = ridge * normal.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(min=1e-12)
    eye = torch.eye(size, dtype=normal.dtype, device=normal.device)
    return torch.linalg.solve(normal + damping[..., None, None] * eye, right)


def blend(with_model: ResidualTerm, alone: ResidualTerm, z: float = 3.0) -> ResidualTerm:
    """The two terms of :func:`fit_term` of a set of pixels, on the physical model (``with_model``)
    and on nothing (``alone``), blended per pixel by the model's weight ``w`` in ``[0, 1]`` that
    predicts the left-out frames best (both terms' :attr:`~ResidualTerm.left_out` errors; a
    stacking of the two predictors, Breiman 1996): in the encoded domain the blend's error is
    ``w e_model + (1 - w) e_alone``, least in square at

        w = <e_alone, e_alone - e_model> / |e_alone - e_model|^2, clipped to [0, 1]

    (1 where the two predict alike). ``w < 1`` is kept only where the blend predicts the left-out
    frames better than the model with its term by ``z``
    (:func:`~torchspec.statistics.predicts_better`, in ``with_model``'s noise units):
    the model is not given up for what noise would make look better. Its coefficients are
    ``w c_model + (1 - w) c_alone`` (:attr:`ResidualTerm.weight` ``= w``)."""
    model, other = with_model.left_out, alone.left_out
    if model is None or other is None:
        raise TorchspecError("blend needs the left-out errors of both terms (fit_term's left_out).")
    gap = other - model
    square = gap.pow(2).flatten(1).sum(1)
    agree = square <= torch.finfo(square.dtype).tiny
    w = ((other * gap).flatten(1).sum(1) / torch.where(agree, torch.ones_like(square), square)).clamp(0, 1)
    w = torch.where(agree, torch.ones_like(w), w)
    mixed = w[:, None, None, None] * model + (1 - w[:, None, None, None]) * other
    sigma = with_model.noise if with_model.noise is not None else model.new_tensor(1.0)
    w = torch.where(predicts_better(mixed / sigma, model / sigma, z), w, torch.ones_like(w))
    coefficients = w[:, None, None] * with_model.coefficients + (1 - w[:, None, None]) * alone.coefficients
    chosen = with_model.chosen | (w < 1)
    left = w[:, None, None, None] * model + (1 - w[:, None, None, None]) * other
    noise, domain = with_model.noise, with_model.domain
    return ResidualTerm(coefficients=coefficients, chosen=chosen, weight=w, left_out=left, noise=noise, domain=domain)
