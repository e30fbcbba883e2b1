"""The camera's response, self-calibrated from the photographs of a capture.

An 8 or 16-bit photograph without a colour profile does not say how its codes ``v`` in ``[0, 1]``
relate to radiance: sRGB, a plain power, linear, or a film-like S curve are all written the same
way. Under distant lights of equal intensity a Lambertian surface's stack is, in linear units,
``y_k = l_k . b`` per pixel and channel (``l_k`` the light's direction, ``b`` the albedo times the
normal): rank 3 in the frames. A wrong curve breaks that, so the curve that lets the cosine law
explain the codes best is the camera's (the directions are known; the law is not bent by a power).

The inverse response (codes to linear) is the family, per channel,

    g(v) = (h(u(v)) - h(0)) / (1 - h(0)),   h(u) = ((u + a) / (1 + a)) ** gamma,
    u(v) = 1/2 + logit(q(-s/2) + v (q(s/2) - q(-s/2))) / s     (s > 0; u(v) = v at s = 0)
    u(v) = (q(|s| (v - 1/2)) - q(-|s|/2)) / (q(|s|/2) - q(-|s|/2))  (s < 0)

with ``q`` the logistic function
``gamma > 0`` a power, ``a >= 0`` an offset with which it is sRGB's shape (sRGB is ``a = 0.055,
gamma = 2.4`` but for its linear toe below code 0.04, within 9e-4), ``s`` (``contrast``) a
logistic S curve of slope ``|s|`` applied to the encoded values, as film-like tone curves are
made: ``s > 0`` undoes one that raised the contrast, ``s < 0`` one that lowered it.
Nested members, chosen by what they predict (:func:`estimate_response`): ``linear`` (no
parameter), ``power`` (gamma), ``offset`` (gamma, a) and ``film`` (gamma, a, s). Every member
is monotone, with ``g(0) = 0`` and ``g(1) = 1``: a clipped code stays at 1.

:func:`estimate_response` fits it by variable projection: for each curve the per-pixel Lambertian
``b`` is the weighted least-squares solution (closed form, each sample weighted by its code's slope
``g'(v)`` to code units), and the misfit is measured in codes, where the photographs' noise is:
``v - g^-1(l_k . b)``. Cast and attached shadows, highlights and dark or clipped codes are outliers:
dark and clipped codes are left out, the rest weighted by Cauchy's loss in rounds.
Each member's misfit is then judged on frames left out of the Lambertian fit (five folds of the
frames, each predicted under its light as written), and a larger member is kept only where it
predicts them better by more than three standard errors over the pixels (and by :data:`GAIN`),
and its parameters stay inside their bounds (one at a bound fits what is not a camera's curve:
a coin's highlights). The uncertainty is the
spread of the curve fitted on four disjoint quarters of the pixels; a member whose curve they do
not determine (:data:`MAX_STD`) gives way to the next smaller one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..errors import TorchspecError

__all__ = [
    "FAMILIES",
    "ResponseCurve",
    "ResponseEstimate",
    "ResponseError",
    "describe_response",
    "estimate_response",
    "invert_curve",
    "response_samples",
]

FAMILIES = ("linear", "power", "offset", "film")
"""The nested members of the family, smallest first: the parameters each one frees."""
DARK = 0.03
"""Codes below this are not used to estimate the curve (noise and compression dominate them)."""
BRIGHT = 0.97
"""Codes above this are not used either (near clipping, a camera's shoulder)."""
KEEP = 0.25
"""The share of the pixels the curve is estimated on: those the Lambertian model explains best."""
GAIN = 0.005
"""A larger member must also lower the left-out loss by this share of the smaller one's."""
MAX_STD = 0.02
"""The largest standard deviation (linear units) of a curve that is kept; above it, the next
smaller member of the family is taken."""
GAMMA = (0.3, 4.0)
"""The range of the fitted power."""
OFFSET = 0.5
"""The largest fitted offset."""
CONTRAST = 12.0
"""The steepest S curve (its logistic's slope) of the ``film`` member."""


class ResponseError(TorchspecError):
    """A stack from which no response can be estimated (too few frames or usable pixels)."""


@dataclass(frozen=True)
class ResponseCurve:
    """An inverse camera response per channel: codes ``v`` in ``[0, 1]`` to linear values (the
    module's family). Each parameter is a tuple with one value per channel.

    Example:
        >>> curve = ResponseCurve(gamma=(2.4,), offset=(0.055,), contrast=(0.0,))
        >>> round(float(curve.decode(torch.tensor([[0.5]]))), 4)  # sRGB's shape (sRGB: 0.2140)
        0.2134
        >>> round(float(curve.encode(curve.decode(torch.tensor([[0.3]])))), 5)
        0.3
    """

    gamma: tuple[float, ...]
    offset: tuple[float, ...]
    contrast: tuple[float, ...]

    def __post_init__(self) -> None:
        if not len(self.gamma) == len(self.offset) == len(self.contrast) >= 1:
            raise ResponseError(
                "a response curve must give gamma, offset and contrast for each channel; got "
                f"{len(self.gamma)}, {len(self.offset)} and {len(self.contrast)} values."
            )
        for name, values, ok in (
            ("gamma", self.gamma, lambda x: x > 0),
            ("offset", self.offset, lambda x: x >= 0),
            ("contrast", self.contrast, lambda x: abs(x) <= CONTRAST),
        ):
            if not all(math.isfinite(x) and ok(x) for x in values):
                raise ResponseError(f"a response curve's {name} is out of range; got {list(values)}.")

    @property
    def channels(self) -> int:
        return len(self.gamma)

    def _params(self, like: Tensor) -> Tensor:
        return torch.tensor([self.gamma, self.offset, self.contrast], dtype=like.dtype, device=like.device).T

    def decode(self, values: Tensor, *, channel_dim: int = -1) -> Tensor:
        """Codes to linear values, elementwise per channel along ``channel_dim`` (of size
        :attr:`channels`, or any size for a one-channel curve); dtype and device kept. Codes
        outside ``[0, 1]`` are clamped first."""
        values = values.clamp(0, 1)
        params = _broadcast(self._params(values), values, channel_dim)
        return _curve(values, params, any(self.contrast))[0]

    def encode(self, values: Tensor, *, channel_dim: int = -1) -> Tensor:
        """Linear values to codes, the inverse of :meth:`decode` on ``[0, 1]`` (closed form:
        :func:`invert_curve`); values outside ``[0, 1]`` are clamped first."""
        values = values.clamp(0, 1)
        return invert_curve(values, _broadcast(self._params(values), values, channel_dim))

    def slope_at_one(self, like: Tensor, *, channel_dim: int = -1) -> Tensor:
        """``g'(1)`` per channel, shaped to broadcast against ``like`` along ``channel_dim``: the
        slope of :meth:`decode` at the brightest code (how a curve is continued above it)."""
        ones = torch.ones_like(like)
        return _curve(ones, _broadcast(self._params(ones), ones, channel_dim), any(self.contrast))[1]

    def to_json(self) -> dict:
        return {"gamma": list(self.gamma), "offset": list(self.offset), "contrast": list(self.contrast)}

    @classmethod
    def from_json(cls, data: dict, where: str = "response") -> ResponseCurve:
        """The curve of :meth:`to_json`; :class:`ResponseError` naming ``where`` when malformed."""
        try:
            return cls(
                tuple(map(float, data["gamma"])), tuple(map(float, data["offset"])), tuple(map(float, data["contrast"]))
            )
        except (KeyError, TypeError, ValueError) as error:
            raise ResponseError(
                f"{where} must hold gamma, offset and contrast lists; got {data!r} ({error})."
            ) from None


def _broadcast(params: Tensor, values: Tensor, channel_dim: int) -> Tensor:
    """``params (C, 3)`` shaped to broadcast against ``values`` along ``channel_dim``: ``(..., 3)``."""
    if params.shape[0] == 1:
        return params[0]
    dim = channel_dim % values.ndim
    if values.shape[dim] != params.shape[0]:
        raise ResponseError(
            f"values must have {params.shape[0]} channels along dimension {channel_dim}; "
            f"got shape {tuple(values.shape)}."
        )
    shape = [1] * values.ndim + [3]
    shape[dim] = params.shape[0]
    return params.reshape(shape)


def _contrast(v: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """``(u(v), u'(v))``: the contrast curve of the module's docstring, slope ``s`` (``u = v`` near 0)."""
    flat = s.abs() < 1e-3
    m = torch.where(flat, 1e-3, s.abs())  # the double-where: no 0/0 in the branch not taken
    low, high = torch.sigmoid(-m / 2), torch.sigmoid(m / 2)
    p = (low + v * (high - low)).clamp(torch.finfo(v.dtype).eps, 1 - torch.finfo(v.dtype).eps)
    u_pos = 0.5 + torch.logit(p) / m
    du_pos = (high - low) / (m * p * (1 - p))
    z = torch.sigmoid(m * (v - 0.5))
    u_neg = (z - low) / (high - low)
    du_neg = m * z * (1 - z) / (high - low)
    u = torch.where(flat, v, torch.where(s > 0, u_pos, u_neg))
    u = torch.where(v <= 0, 0.0, torch.where(v >= 1, 1.0, u.clamp(0, 1)))  # the ends exact, not rounded
    du = torch.where(flat, torch.ones_like(v), torch.where(s > 0, du_pos, du_neg))
    return u, du


def _curve(v: Tensor, params: Tensor, contrast: bool = True) -> tuple[Tensor, Tensor]:
    """``(g(v), g'(v))`` for ``params (..., 3)`` = (gamma, offset, contrast) broadcasting with ``v``
    (``contrast`` False: the contrast taken as 0 whatever ``params`` hold)."""
    gamma, a = params[..., 0], params[..., 1]
    if contrast:
        u, du = _contrast(v, params[..., 2])
    else:  # no S curve: u = v (the same values, without the work)
        u, du = v, torch.ones_like(v)
    base = ((u + a) / (1 + a)).clamp(min=torch.finfo(v.dtype).tiny)
    h0 = (a / (1 + a)).clamp(min=0) ** gamma
    h = base**gamma
    scale = 1 - h0
    dh = gamma / (1 + a) * base ** (gamma - 1)
    return (h - h0) / scale, dh * du / scale


def invert_curve(y: Tensor, params: Tensor) -> Tensor:
    """``g^-1(y)`` for linear values ``y`` in ``[0, 1]`` and ``params (..., 3)`` = (gamma, offset,
    contrast) broadcasting with ``y`` (:func:`_curve`'s ``g``), in closed form: the power and
    offset undone, then the logistic contrast curve of the module's docstring."""
    gamma, a, s = params[..., 0], params[..., 1], params[..., 2]
    h0 = (a / (1 + a)).clamp(min=0) ** gamma
    u = ((1 + a) * (h0 + y * (1 - h0)).clamp(min=0) ** (1 / gamma) - a).clamp(0, 1)
    flat = s.abs() < 1e-3
    m = torch.where(flat, 1e-3, s.abs())
    low, high = torch.sigmoid(-m / 2), torch.sigmoid(m / 2)
    eps = torch.finfo(y.dtype).eps
    v_pos = (torch.sigmoid(m * (u - 0.5)) - low) / (high - low)  # s > 0: u = 1/2 + logit(p) / m
    v_neg = 0.5 + torch.logit((low + u * (high - low)).clamp(eps, 1 - eps)) / m  # s < 0
    v = torch.where(flat, u, torch.where(s > 0, v_pos, v_neg))
    return torch.where(y <= 0, 0.0, torch.where(y >= 1, 1.0, v.clamp(0, 1)))


# --- estimation -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ResponseEstimate:
    """What :func:`estimate_response` found.

    Attributes:
        curve: the chosen member's curve (:class:`ResponseCurve`).
        family: its name (:data:`FAMILIES`).
        std: ``(C,)`` the curve's standard deviation in linear units, the largest over codes in
            ``[0, 1]`` (the spread of four quarters of the pixels, over 2).
        left_out_loss: each member's mean robust loss (Cauchy's, at ``scale``) of the code
            residuals of frames left out of the Lambertian fit: what chose the member.
        fitted: each member's curve.
        pixels: the pixels the estimate used.
        scale: ``(C,)`` the robust deviation of the code residuals the members were judged at.
        glare: the ``glare`` the estimate left out samples within (degrees; 0: none).
        judged: where candidate curves were judged by the fit
            (:func:`torchspec.calibration.response_judge.judge_curves`), each one's PSNR in dB.
    """

    curve: ResponseCurve
    family: str
    std: tuple[float, ...]
    left_out_loss: dict[str, float]
    fitted: dict[str, ResponseCurve] = field(repr=False)
    pixels: int = 0
    scale: tuple[float, ...] = ()
    glare: float = 0.0
    judged: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict:
        """The record a capture's manifest keeps (``source.response``, docs/capture-format.md)."""
        return {
            "family": self.family,
            **self.curve.to_json(),
            "std": list(self.std),
            "left_out_loss": dict(self.left_out_loss),
            "candidates": {name: curve.to_json() for name, curve in self.fitted.items()},
            "pixels": self.pixels,
            "scale": list(self.scale),
            "glare": self.glare,
            "judged_psnr_db": dict(self.judged),
        }


def response_samples(codes: Tensor, count: int, *, seed: int = 0) -> Tensor:
    """The indices of up to ``count`` pixels of ``codes (K, C, N)`` to estimate a response from:
    pixels whose median code lies within ``[0.05, 0.9]`` in every channel, drawn at random with
    ``seed`` (reproducibly, on the CPU)."""
    median = codes.median(dim=0).values  # (C, N)
    usable = ((median > 0.05) & (median < 0.9)).all(0).nonzero().flatten().cpu()
    if usable.numel() > count:
        generator = torch.Generator().manual_seed(seed)
        # on the CPU: a seeded draw, the same on every device; moved below
        usable = usable[torch.randperm(usable.numel(), generator=generator)[:count]].sort().values
    return usable.to(codes.device)


def _unpack(theta: Tensor, family: str) -> Tensor:
    """``theta (C, 3)`` unconstrained to ``(C, 3)`` (gamma, offset, contrast) of ``family``."""
    zero = torch.zeros_like(theta[:, 0])
    gamma = GAMMA[0] + (GAMMA[1] - GAMMA[0]) * torch.sigmoid(theta[:, 0]) if family != "linear" else zero + 1
    offset = OFFSET * torch.sigmoid(theta[:, 1]) if family in ("offset", "film") else zero
    contrast = CONTRAST * torch.tanh(theta[:, 2]) if family == "film" else zero
    return torch.stack([gamma, offset, contrast], -1)


def _lambert(y: Tensor, a: Tensor, weights: Tensor) -> Tensor:
    """Per channel and pixel the weighted least-squares ``b (C, N, 3)`` of ``y (C, K, N)`` on
    ``a (C, K, 3)`` with ``weights (C, K, N)`` (a small ridge keeps a pixel with few samples finite)."""
    normal = torch.einsum("ckn,cki,ckj->cnij", weights, a, a)
    rhs = torch.einsum("ckn,ckn,cki->cni", weights, y, a)
    ridge = 1e-9 * normal.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] + 1e-12
    eye = torch.eye(3, dtype=y.dtype, device=y.device)
    return torch.linalg.solve(normal + ridge * eye, rhs[..., None])[..., 0]


def _inverse(y: Tensor, params: Tensor, contrast: bool, points: int = 1025) -> Tensor:
    """Codes of linear ``y (C, K, N)`` in ``[0, 1]`` under the curves ``params (C, 3)``: the curve
    tabulated on ``points`` codes and interpolated (differentiable in ``params``)."""
    grid = torch.linspace(0, 1, points, dtype=y.dtype, device=y.device)
    table = _curve(grid[None], params[:, None, :], contrast)[0].expand(y.shape[0], -1)  # (C, G), increasing
    flat = y.flatten(1).contiguous()
    index = torch.searchsorted(table.detach().contiguous(), flat.detach()).clamp(1, points - 1)
    low, high = table.gather(1, index - 1), table.gather(1, index)
    t = ((flat - low) / (high - low).clamp(min=torch.finfo(y.dtype).tiny)).clamp(0, 1)
    return ((index - 1 + t) / (points - 1)).reshape(y.shape)


def _misfit(theta: Tensor, family: str, codes: Tensor, directions: Tensor, weights: Tensor, held=None) -> Tensor:
    """Code residuals ``(C, K, N)``: each pixel's Lambertian ``b`` fitted (weighted least squares
    on the linear values, each sample weighted by its code's slope to code units) under the
    lights as written, its prediction encoded by the curve ``theta`` and compared with ``codes``.
    ``held (K,)`` given: each frame predicted from the fit of the frames of other folds (its
    index in ``held``)."""
    params = _unpack(theta, family)
    y, slope = _curve(codes, params[:, None, None, :], family == "film")
    w = weights / slope**2
    if held is None:
        shading = torch.einsum("cki,cni->ckn", directions, _lambert(y, directions, w))
    else:
        shading = torch.zeros_like(y)
        for fold in range(int(held.max()) + 1):
            mask = (held == fold)[None, :, None]
            b = _lambert(y, directions, w * ~mask)
            shading = torch.where(mask, torch.einsum("cki,cni->ckn", directions, b), shading)
    return codes - _inverse(shading.clamp(0, 1), params, family == "film")


def _scale(residual: Tensor, usable: Tensor) -> Tensor:
    """``(C, 1, 1)`` a robust deviation (1.4826 MAD) of the usable ``residual (C, K, N)``, per channel."""
    flat = torch.where(usable, residual.abs(), torch.nan).flatten(1)
    return (1.4826 * flat.nanmedian(-1).values).clamp(min=1e-4)[:, None, None]


def _cauchy(residual: Tensor, scale: Tensor) -> Tensor:
    """Cauchy's loss ``log(1 + (r / s)^2)``: a sample far off (a highlight, a cast shadow) counts
    little, and no weight is ever 0, so the set of samples cannot shrink round by round."""
    return torch.log1p((residual / scale) ** 2)


def _loss(theta: Tensor, family: str, codes: Tensor, directions: Tensor, usable: Tensor, scale: Tensor) -> Tensor:
    """The robust loss (Cauchy's, at ``scale``) of the curve ``theta`` on the usable samples."""
    with torch.no_grad():
        residual = _misfit(theta, family, codes, directions, usable.to(codes.dtype))
        weights = usable / (1 + (residual / scale) ** 2)
        return (_cauchy(_misfit(theta, family, codes, directions, weights), scale) * usable).sum()


def _fit(family: str, codes, directions, usable, theta, scale, *, rounds: int = 2):
    """``(theta, scale)``: the curve of ``family`` by L-BFGS in rounds of Cauchy weights
    (iteratively reweighted); ``scale`` None: re-estimated each round from the residuals."""
    weights = usable.to(codes.dtype)
    theta = theta.clone()
    for _ in range(rounds):
        if family != "linear":
            theta.requires_grad_(True)
            optimiser = torch.optim.LBFGS(
                [theta], max_iter=25, line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12
            )

            def closure(theta=theta, weights=weights, optimiser=optimiser):
                optimiser.zero_grad()
                loss = (weights * _misfit(theta, family, codes, directions, weights) ** 2).sum() / weights.sum()
                loss.backward()
                return loss

            optimiser.step(closure)
            theta = theta.detach()
        with torch.no_grad():
            residual = _misfit(theta, family, codes, directions, weights)
            s = _scale(residual, usable) if scale is None else scale
            weights = usable / (1 + (residual / s) ** 2)
    return theta, s


def _check(codes: Tensor, directions: Tensor, families: tuple[str, ...]) -> None:
    """:class:`ResponseError` for arguments :func:`estimate_response` cannot use, in words."""
    if codes.ndim != 3 or directions.shape != (codes.shape[0], 3):
        raise ResponseError(
            f"codes must be (K, C, N) and directions (K, 3); got {tuple(codes.shape)} and {tuple(directions.shape)}."
        )
    k, _, n = codes.shape
    if k < 6 or n < 16:
        raise ResponseError(f"a response needs at least 6 frames and 16 pixels; got {k} frames and {n} pixels.")
    if not families or any(f not in FAMILIES for f in families):
        raise ResponseError(f"families must be among {FAMILIES}; got {families!r}.")


def estimate_response(
    codes: Tensor,
    directions: Tensor,
    *,
    families: tuple[str, ...] = FAMILIES,
    sigmas: float = 3.0,
    per_channel: bool = False,
    glare: float = 0.0,
    view: Tensor | None = None,
) -> ResponseEstimate:
    """The inverse response of ``codes (K, C, N)`` (encoded values in ``[0, 1]`` of ``N`` pixels,
    e.g. from :func:`response_samples`) photographed under distant lights ``directions (K, 3)``
    (unit, towards the lights). Work follows the inputs' dtype and device (float64 recommended).

    Each member of ``families`` is fitted (module docstring); the smallest one is chosen unless a
    larger one predicts frames left out of the Lambertian fit better by more than ``sigmas``
    standard errors of the per-pixel difference. The lights' intensities are taken as equal: on a
    nearly flat object a gain per frame would mimic any curve (its shading changes with the
    light's elevation alone, as a power of it does). One curve serves every channel unless
    ``per_channel`` (cameras apply one; a curve per channel would also bend the colours with the
    brightness wherever the model misses). ``glare`` > 0 leaves out the samples whose half vector
    (between the light and ``view``, default ``+z``) lies within ``glare`` degrees of the pixel's
    normal (from a first fit), where a lobe would add to the Lambertian shading.

    Raises:
        ResponseError: fewer than 6 frames or 16 pixels, or too few usable codes (a stack that is
            nearly all dark or clipped).
    """
    _check(codes, directions, families)
    k, c, n = codes.shape
    v = codes.permute(1, 0, 2).contiguous()  # (C, K, N)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype, device=v.device) if view is None else view
    usable = (v > DARK) & (v < BRIGHT) & (directions[:, 2] > 0).to(v.device)[None, :, None]
    v = v.clamp(DARK / 2, 1)  # the codes not used carry no weight; kept off 0, where a slope can be infinite
    if int(usable.sum()) < 6 * n * c:  # one sync, once: the data must carry the estimate
        raise ResponseError(
            f"a response needs most codes within [{DARK}, {BRIGHT}]; only {int(usable.sum())} of {v.numel()} are. "
            "Pass the photographs' transfer explicitly (--transfer srgb, linear or gamma:G)."
        )
    d = directions.to(v)[None].expand(c, k, 3)
    theta = torch.zeros(c if per_channel else 1, 3, dtype=v.dtype, device=v.device)
    theta[:, 0] = _logit((2.2 - GAMMA[0]) / (GAMMA[1] - GAMMA[0]))
    theta[:, 1] = _logit(0.05 / OFFSET)
    power, scale = _fit("power", v, d, usable, theta, None)
    if glare > 0:  # no sample near a highlight: its half vector within ``glare`` degrees of the normal
        y, slope = _curve(v, _unpack(power, "power")[:, None, None, :], False)
        normal = torch.nn.functional.normalize(_lambert(y, d, usable / slope**2).mean(0), dim=-1)  # (N, 3)
        half = torch.nn.functional.normalize(directions.to(v) + view.to(v), dim=-1)  # (K, 3)
        usable = usable & ((half @ normal.T) < math.cos(math.radians(glare)))[None]
    # the pixels the Lambertian model explains best (a varnish's broad lobe is no outlier sample by
    # sample, but its pixel is the worse explained): the estimate is made on them alone
    per_pixel = (_cauchy(_misfit(power, "power", v, d, usable.to(v.dtype)), scale) * usable).sum((0, 1))
    per_pixel = per_pixel / usable.sum((0, 1)).clamp(min=1)
    usable = usable & (per_pixel <= per_pixel.quantile(KEEP))[None, None, :]
    _, scale = _fit("power", v, d, usable, power, None)  # the robust scale every member is judged at
    state, loss = {}, {}
    for family in families:
        start = state[list(state)[-1]] if state else theta
        if family == "film":  # from either side of the flat start (no gradient at s = 0), from the power
            # fit with a small offset (offset and contrast trade off: from the offset fit it stalls): the better
            starts = [state.get("power", start).clone() for _ in range(2)]
            for one, side in zip(starts, (1, -1), strict=True):
                one[:, 1], one[:, 2] = _logit(0.01 / OFFSET), side * math.atanh(2 / CONTRAST)
            fits = [_fit(family, v, d, usable, one, scale)[0] for one in starts]
            state[family] = min(fits, key=lambda t: float(_loss(t, family, v, d, usable, scale)))
        else:
            state[family], _ = _fit(family, v, d, usable, start, scale)
        with torch.no_grad():
            residual = _misfit(state[family], family, v, d, usable.to(v.dtype))
            weights = usable / (1 + (residual / scale) ** 2)
            held = torch.arange(k, device=v.device) % 5
            loss[family] = _cauchy(_misfit(state[family], family, v, d, weights, held), scale) * usable
    count = usable.sum((0, 1)).clamp(min=1)  # per pixel
    per_pixel = {f: e.sum((0, 1)) / count for f, e in loss.items()}
    ranked = [families[0]]  # each member kept over the last one, smallest first
    for family in families[1:]:
        diff = per_pixel[ranked[-1]] - per_pixel[family]
        margin = max(sigmas * float(diff.std() / math.sqrt(diff.numel())), GAIN * float(per_pixel[ranked[-1]].mean()))
        if float(diff.mean()) > margin and not _at_bound(_unpack(state[family], family), family):
            ranked.append(family)
    while True:  # a curve the pixels do not determine is not kept: the next smaller one is
        chosen = ranked.pop()
        std = _spread(chosen, v, d, usable, state[chosen], scale)
        if not ranked or max(std) <= MAX_STD:
            break
    total = usable.sum().clamp(min=1)
    return ResponseEstimate(
        curve=_curve_of(state[chosen], chosen),
        family=chosen,
        std=std,
        left_out_loss={f: float(e.sum() / total) for f, e in loss.items()},
        fitted={f: _curve_of(theta, f) for f, theta in state.items()},
        pixels=n,
        scale=tuple(float(x) for x in scale.flatten()),
        glare=glare,
    )


def _at_bound(params: Tensor, family: str) -> bool:
    """Whether a fitted curve's free parameters reach their bounds: the photographs push it beyond
    the family, so what it fits is not a camera's curve (a coin's highlights, say)."""
    gamma, offset, contrast = params[:, 0], params[:, 1], params[:, 2]
    span = GAMMA[1] - GAMMA[0]
    hits = (gamma < GAMMA[0] + 0.01 * span) | (gamma > GAMMA[1] - 0.01 * span)
    if family in ("offset", "film"):
        hits = hits | (offset > 0.98 * OFFSET)
    if family == "film":
        hits = hits | (contrast.abs() > 0.98 * CONTRAST)
    return bool(hits.any())


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _curve_of(theta: Tensor, family: str) -> ResponseCurve:
    params = _unpack(theta, family).double().cpu()
    return ResponseCurve(*(tuple(float(x) for x in params[:, i]) for i in range(3)))


def _spread(family: str, v, d, usable, theta, scale, parts: int = 4) -> tuple[float, ...]:
    """Per channel, the largest standard deviation over codes of the curve, from ``parts``
    disjoint sets of pixels fitted alone (their spread over ``sqrt(parts)``)."""
    if family == "linear":
        return tuple(0.0 for _ in range(v.shape[0]))
    grid = torch.linspace(0, 1, 101, dtype=v.dtype, device=v.device)
    curves = []
    for part in range(parts):
        pick = torch.arange(part, v.shape[-1], parts, device=v.device)
        fitted, _ = _fit(family, v[..., pick], d, usable[..., pick], theta, scale, rounds=1)
        curves.append(_curve(grid[None], _unpack(fitted, family)[:, None, :], family == "film")[0])
    stacked = torch.stack(curves)  # (parts, C, 101)
    return tuple(float(x) for x in (stacked.std(0) / math.sqrt(parts)).amax(-1))


def describe_response(record: dict) -> str:
    """One line of words for a manifest's ``source.response`` (:meth:`ResponseEstimate.to_json`)."""
    family = record.get("family", "?")
    parts = {
        "linear": "",
        "power": "gamma {g}",
        "offset": "gamma {g}, offset {a}",
        "film": "gamma {g}, offset {a}, contrast {k}",
    }
    values = {
        "g": "/".join(f"{x:.3g}" for x in record.get("gamma", [])),
        "a": "/".join(f"{x:.3g}" for x in record.get("offset", [])),
        "k": "/".join(f"{x:+.3g}" for x in record.get("contrast", [])),
    }
    shape = parts.get(family, "").format(**values)
    std = max(record.get("std") or [0.0])
    words = f"camera response estimated ({family}{', ' + shape if shape else ''}; +-{std:.2g} in linear units"
    if record.get("glare"):
        words += f"; samples within {record['glare']:g} deg of a highlight left out"
    judged = record.get("judged_psnr_db") or {}
    if judged:
        words += "; left-out photographs predicted at " + ", ".join(f"{n} {v:.1f} dB" for n, v in judged.items())
    return words + ")"
