"""Reflectance models a pixel can be fitted with, and their parameter packing.

Each model is a subset of the Ward parameters of :mod:`torchspec.model.jacobian` with bounds:

===================  ===============================================  ======================
model                parameters (in this order)                       bounds
===================  ===============================================  ======================
``diffuse``          normal angles a, b; k_d (C)                      k_d >= 0
``ward-iso``         + grey k_s (1); alpha                            k_s >= 0, alpha in ALPHA_BOUNDS
``ward-iso-colour``  + k_s (C); alpha                                 k_s >= 0, alpha in ALPHA_BOUNDS
``ward-aniso``       + k_s (C); alpha_x, alpha_y; rotation            k_s >= 0, alpha in ALPHA_BOUNDS
``ward-dual``        + grey k_s (1); alpha; grey k_s2 (1); alpha2     k_s, k_s2 >= 0, both alpha in
                                                                      ALPHA_BOUNDS
===================  ===============================================  ======================

``ward-dual`` is two isotropic grey lobes on one normal, a sharp and a broad one: a varnish over a
glossy layer, whose highlight a single Ward lobe cannot shape (its core too wide or its skirt too
narrow). The lobes are interchangeable in the model; :meth:`Model.unpack` names the sharper one the
first (``SVBRDF.specular``) and the broader the second (``SVBRDF.specular2``).

Bounds are kept by reparametrisation in the solver (:class:`torchspec.lm.Bounds`): softplus for
the coefficients, which may reach 0, and a sigmoid for the roughness.

The models are a registry (:data:`MODELS`, :func:`register`): a :class:`Model` declares its
parameters once (:class:`torchspec.model.params.Param`) and its lobe as an object
(:class:`torchspec.model.lobes.Lobe`); its packing, bounds, Jacobian columns and deviations, its code in
:data:`MODEL_CODES`, the ladder's checks, ``fit --model``'s choices and the maps a fit writes
follow. A model whose lobe has no closed forms is rendered on the nodes and its Jacobian taken by
forward-mode AD (:meth:`Model.forward_jacobian`), in the fit (:meth:`Model.residuals`) and in its
deviations and peak checks (:func:`torchspec.model.forward_terms.forward_sandwich_terms`); ``auto``'s
gate of a second lobe (:func:`torchspec.pipeline.prediction.second_lobe_held_out`) is Ward's.

Example:
    >>> from torchspec.model.lobes import BECKMANN
    >>> beckmann = Model("beckmann-iso", (NORMAL, DIFFUSE, GREY, ALPHA), BECKMANN)
    >>> with registered(beckmann):
    ...     MODEL_CODES.index("beckmann-iso"), beckmann.size(3)
    (5, 7)
    >>> "beckmann-iso" in MODELS
    False
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..lm import Bounds, NormalEquations
from .brdf import SVBRDF
from .jacobian import jacobian
from .least_squares import normal_equations
from .lights import Lights
from .lobes import WARD, Lobe
from .params import FIELDS, Param, check_params
from .quadrature import Quadrature
from .rendering import render

__all__ = [
    "Model",
    "MODELS",
    "MODEL_CODES",
    "BUILT_IN",
    "get_model",
    "render_chosen",
    "register",
    "unregister",
    "registered",
    "split_lobe",
    "sharper_first",
    "NORMAL",
    "DIFFUSE",
    "GREY",
    "ALPHA",
    "ALPHA_BOUNDS",
]

ALPHA_BOUNDS = (1e-3, 1.0)
"""The roughness a fit may take: below, the lobe is narrower than any light kernel resolves; above,
the Ward lobe no longer describes a gloss. A lobe that fades into the diffuse (``k_s -> 0``) leaves
``alpha`` undetermined: the bounds keep it finite."""


@dataclass(frozen=True)
class Model:
    """A reflectance model: its parameters, declared once, and its lobe.

    Everything else is derived from the declaration: :meth:`size`, :meth:`bounds`, :meth:`pack`,
    :meth:`unpack`, the Jacobian's columns (:meth:`select`), the standard deviations' fields
    (:meth:`fields`), and, once :func:`register`-ed, the model's code, the ladder's checks, the
    command line's choices and the maps a fit writes.

    Attributes:
        name: its name in configs and ``svbrdf.json``.
        params: its parameters in the solver's order (:class:`~torchspec.model.params.Param`).
        lobe: the lobe the renderer integrates (:class:`torchspec.model.lobes.Lobe`), ``None`` for none.
        start: a hook ``svbrdf -> svbrdf`` giving :meth:`pack` the fields this model has and a
            smaller model's fit lacks (``ward-dual``: its two lobes either side of one).
        order: a hook ``svbrdf -> svbrdf`` for :meth:`unpack`'s ``order`` (``ward-dual``: the
            sharper lobe first).
        ladder: in ``auto``'s default ladder (:data:`torchspec.pipeline.LADDER`).
    """

    name: str
    params: tuple[Param, ...]
    lobe: Lobe | None = None
    start: Callable[[SVBRDF], SVBRDF] | None = None
    order: Callable[[SVBRDF], SVBRDF] | None = None
    ladder: bool = False

    def __post_init__(self):
        check_params(self.name, self.params, self.lobe is not None)

    def fills(self, field: str) -> bool:
        """Whether a parameter fills the SVBRDF's ``field`` (:data:`~torchspec.model.params.FIELDS`)."""
        return any(p.field == field for p in self.params)

    @property
    def grey(self) -> bool:
        """One ``k_s`` for every channel (or no ``k_s``)."""
        return not any(p.field == "specular" and p.per_channel for p in self.params)

    @property
    def anisotropic(self) -> bool:
        """A rotation of the lobe among the parameters (with ``alpha_x``, ``alpha_y``)."""
        return self.fills("rotation")

    def size(self, channels: int) -> int:
        """``P``, the number of parameters for ``channels`` channels."""
        return sum(p.count(channels) for p in self.params)

    def bounds(self, channels: int, least: float = ALPHA_BOUNDS[0]) -> Bounds:
        """The solver's reparametrisation of each parameter; ``least``: the smallest roughness
        (at least :data:`ALPHA_BOUNDS`' low end; :func:`torchspec.model.layout.resolvable_roughness`)."""
        alpha = ("interval", max(least, ALPHA_BOUNDS[0]), ALPHA_BOUNDS[1])
        kinds = []
        for p in self.params:
            kinds += [alpha if p.bound == "roughness" else p.bound] * p.count(channels)
        return Bounds(tuple(kinds))

    def pack(self, svbrdf: SVBRDF) -> Tensor:
        """``(N, P)`` parameters of a flat ``svbrdf`` (through :attr:`start` first, if declared).

        ``ward-dual`` from an SVBRDF with one lobe (a smaller model's fit) starts its lobes either
        side of it: half its ``k_s`` each, at ``alpha / 2`` and ``2 alpha`` (within the bounds)."""
        if self.start is not None:
            svbrdf = self.start(svbrdf)
        return torch.cat([p.pack(svbrdf, self.name) for p in self.params], -1)

    def unpack(self, params: Tensor, channels: tuple[str, ...], order: bool = False) -> SVBRDF:
        """A flat :class:`~torchspec.SVBRDF` (``k_s = 0``, ``alpha = 0`` without a lobe).

        ``order``: ``ward-dual``'s sharper lobe first (the solver's parameters keep the order they
        started in; :attr:`order`)."""
        fields = self.fields(params, len(channels))
        zero = params.new_zeros((params.shape[0], 1))
        fields.setdefault("specular", zero)
        fields.setdefault("roughness", zero.expand(-1, 2).clone())
        svbrdf = SVBRDF(channels=channels, **fields)
        return self.order(svbrdf) if order and self.order is not None else svbrdf

    def fields(self, params: Tensor, channels: int, normal: bool = True) -> dict[str, Tensor]:
        """The SVBRDF fields the parameters ``(N, P)`` fill, by name: what :meth:`unpack` builds
        on, and (``normal=False``: without the normal from its angles) the standard deviations'
        fields of :mod:`torchspec.pipeline.uncertainty`."""
        out, at = {}, 0
        for p in self.params:
            count = p.count(channels)
            if normal or p.field != "normal":
                out[p.field] = p.fill(params[:, at : at + count])
            at += count
        return out

    def offsets(self, channels: int) -> dict[str, int]:
        """Where each field's columns start in :mod:`torchspec.model.jacobian`'s order for this model's
        SVBRDF (:func:`torchspec.model.jacobian.parameters`: ``2 + C + C_s + 3 [+ C_s2 + 2]``), and
        ``"end"``, their count."""
        width = {"specular": 1, "specular2": 0, "roughness2": 0}
        width.update({p.field: p.count(channels) for p in self.params if p.field in ("specular", "specular2")})
        width.update(normal=2, diffuse=channels, roughness=2, rotation=1)
        if self.fills("specular2"):
            width["roughness2"] = 2
        offsets, at = {}, 0
        for name in FIELDS:
            offsets[name], at = at, at + width[name]
        return offsets | {"end": at}

    def columns(self, channels: int) -> tuple[tuple[int, ...], ...]:
        """For each parameter, the columns of :meth:`offsets`' order that it moves (summed)."""
        offsets, out = self.offsets(channels), []
        for p in self.params:
            o = offsets[p.field]
            if p.field in ("roughness", "roughness2") and p.count(channels) == 1:
                out.append((o, o + 1))  # an isotropic alpha moves both alpha_x and alpha_y
            else:
                out += [(o + i,) for i in range(p.count(channels))]
        return tuple(out)

    def select(self, full: Tensor, channels: int) -> Tensor:
        """This model's columns ``(..., P)`` of a Jacobian in :mod:`torchspec.model.jacobian`'s order
        ``(..., 2 + C + C_s + 3)`` (``+ C_s2 + 2`` with a second lobe: its ``k_s`` and ``alpha``):
        an isotropic ``alpha`` moves both ``alpha_x`` and ``alpha_y``; a rotation not fitted is
        left out (:meth:`columns`)."""
        columns = self.columns(channels)
        picked, run = [], None
        for sources in columns:
            if len(sources) == 1 and run is not None and sources[0] == run[1]:
                run = (run[0], run[1] + 1)
                continue
            if run is not None:
                picked.append(full[..., run[0] : run[1]])
                run = None
            if len(sources) == 1:
                run = (sources[0], sources[0] + 1)
            else:
                summed = full[..., sources[0] : sources[0] + 1]
                for j in sources[1:]:
                    summed = summed + full[..., j : j + 1]
                picked.append(summed)
        if run is not None:
            picked.append(full[..., run[0] : run[1]])
        return picked[0] if len(picked) == 1 else torch.cat(picked, -1)

    def selection(self, channels: int, like: Tensor) -> Tensor:
        """:meth:`select` as a matrix ``(2 + C + C_s + 3 [+ C_s2 + 2], P)``: ``select(J) = J @ selection``."""
        eye = torch.eye(self.offsets(channels)["end"], dtype=like.dtype, device=like.device)
        return self.select(eye, channels)

    def residuals(
        self,
        observed: Tensor,
        weight: Tensor,
        lights: Lights,
        view: Tensor,
        channels: tuple[str, ...],
        *,
        quadrature: Quadrature = Quadrature(),
        normal: bool = False,
    ) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor] | NormalEquations]:
        """The solver's residual function for these pixels: ``(params (M, P), index (M,)) ->
        (residuals (M, K C), jacobian (M, K C, P))`` with ``residual = weight (rendered -
        observed)``.

        Args:
            observed: ``(N, K, C)`` recorded values.
            weight: ``(N, K)`` or ``(N, K, C)``: 0 drops a sample; a per-pixel scale evens the
                costs of bright and dark pixels.
            quadrature: the model's quadrature (:class:`torchspec.model.quadrature.Quadrature`).
            normal: return the :class:`~torchspec.lm.NormalEquations` instead
                (:func:`torchspec.model.least_squares.normal_equations`): the same solver steps without
                the Jacobian in memory, and with ``quadrature.compile`` one fused pass over the
                frames.
        """
        w = weight if weight.dim() == 3 else weight[..., None]
        if self.lobe is not None and not self.lobe.analytic:
            return self._forward_residuals(observed, w, lights, view, channels, quadrature)
        if normal:
            select = self.selection(len(channels), observed)

            def equations(params: Tensor, index: Tensor) -> NormalEquations:
                svbrdf = self.unpack(params, channels)
                wi = w[index].expand(-1, -1, len(channels))
                out = normal_equations(
                    svbrdf,
                    lights,
                    view,
                    observed[index],
                    wi,
                    select,
                    quadrature=quadrature,
                    diffuse_only=self.lobe is None,
                    isotropic=not self.anisotropic,
                )
                return NormalEquations(*out)

            return equations

        def fn(params: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
            svbrdf = self.unpack(params, channels)
            value, full = jacobian(
                svbrdf,
                lights,
                view,
                quadrature=quadrature,
                diffuse_only=self.lobe is None,
                isotropic=not self.anisotropic,
            )
            wi = w[index]
            r = ((value - observed[index]) * wi).flatten(1)
            jac = self.select(full, len(channels)) * wi[..., None]
            return r, jac.flatten(1, 2)

        return fn

    def forward_jacobian(
        self,
        params: Tensor,
        lights: Lights,
        view: Tensor,
        channels: tuple[str, ...],
        quadrature: Quadrature = Quadrature(),
    ) -> tuple[Tensor, Tensor]:
        """The rendered values ``(N, K, C)`` of the parameters ``params (N, P)`` and their Jacobian
        ``(N, K, C, P)`` in this model's own parameters, by forward-mode AD through :meth:`unpack`
        and the renderer (with :attr:`lobe`), one JVP a parameter: what a lobe without closed forms
        is fitted (:meth:`residuals`) and assessed (:func:`torchspec.model.forward_terms.forward_sandwich_terms`)
        with; any lobe's, Ward's too."""

        def forward(p: Tensor) -> Tensor:
            return render(self.unpack(p, channels), lights, view, quadrature=quadrature, lobe=self.lobe or WARD)

        eye = torch.eye(params.shape[-1], dtype=params.dtype, device=params.device)
        value, columns = None, []
        for j in range(params.shape[-1]):
            value, column = torch.func.jvp(forward, (params,), (eye[j].expand_as(params),))
            columns.append(column)
        return value, torch.stack(columns, -1)

    def _forward_residuals(self, observed, w, lights, view, channels, quadrature):
        """:meth:`residuals` of a lobe without closed forms: the Jacobian in this model's own
        parameters by :meth:`forward_jacobian` (no ``normal`` equations: the solver takes the
        Jacobian)."""

        def fn(params: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
            value, jac = self.forward_jacobian(params, lights, view, channels, quadrature)
            wi = w[index]
            r = ((value - observed[index]) * wi).flatten(1)
            return r, (jac * wi[..., None]).flatten(1, 2)

        return fn


def split_lobe(svbrdf: SVBRDF) -> SVBRDF:
    """``ward-dual``'s start (:attr:`Model.start`): an SVBRDF with one lobe gets two either side of
    it, half its grey ``k_s`` each, at ``alpha / 2`` and ``2 alpha`` (within the bounds); one with a
    second lobe is kept."""
    if svbrdf.specular2 is not None:
        return svbrdf
    ks = 0.5 * svbrdf.specular.mean(-1, keepdim=True)
    alpha = svbrdf.roughness.mean(-1, keepdim=True)
    low, high = ALPHA_BOUNDS
    sharp, broad = (0.5 * alpha).clamp(2 * low, high / 2), (2.0 * alpha).clamp(2 * low, high / 2)
    return replace(svbrdf, specular=ks, roughness=sharp.expand(-1, 2), specular2=ks, roughness2=broad.expand(-1, 2))


def sharper_first(svbrdf: SVBRDF) -> SVBRDF:
    """``ward-dual``'s :attr:`Model.order`: the lobe of the smaller roughness first."""
    alpha, alpha2 = svbrdf.roughness[:, :1], svbrdf.roughness2[:, :1]
    swap = alpha2 < alpha
    ks, ks2 = svbrdf.specular, svbrdf.specular2
    return replace(
        svbrdf,
        specular=torch.where(swap, ks2, ks),
        specular2=torch.where(swap, ks, ks2),
        roughness=torch.where(swap, alpha2, alpha).expand(-1, 2),
        roughness2=torch.where(swap, alpha, alpha2).expand(-1, 2),
    )


NORMAL = Param("a, b", "normal", size=2)
"""The normal's two tilt angles (:func:`torchspec.model.geometry.normal_from_angles`), every model's first."""
DIFFUSE = Param("k_d", "diffuse", per_channel=True, bound="nonnegative")
"""``k_d`` per channel, every model's second."""
GREY = Param("k_s", "specular", bound="nonnegative")
"""One grey ``k_s`` (``replace(GREY, per_channel=True)``: one per channel)."""
ALPHA = Param("alpha", "roughness", bound="roughness")
"""One isotropic roughness."""

MODELS: dict[str, Model] = {}
"""The registered models by name (:func:`register`), in the order of their codes
(:data:`MODEL_CODES`): the built-in ones first, in this order."""
_BUILT_IN = (
    Model("diffuse", (NORMAL, DIFFUSE)),
    Model("ward-iso", (NORMAL, DIFFUSE, GREY, ALPHA), WARD, ladder=True),
    Model("ward-iso-colour", (NORMAL, DIFFUSE, replace(GREY, per_channel=True), ALPHA), WARD, ladder=True),
    Model(
        "ward-aniso",
        (
            NORMAL,
            DIFFUSE,
            replace(GREY, per_channel=True),
            Param("alpha_x, alpha_y", "roughness", size=2, bound="roughness"),
            Param("rotation", "rotation"),
        ),
        WARD,
        ladder=True,
    ),
    Model(
        "ward-dual",
        (
            NORMAL,
            DIFFUSE,
            GREY,
            ALPHA,
            Param("k_s2", "specular2", bound="nonnegative"),
            replace(ALPHA, name="alpha2", field="roughness2"),
        ),
        WARD,
        start=split_lobe,
        order=sharper_first,
        ladder=True,
    ),
)


def register(model: Model) -> Model:
    """Add ``model`` to :data:`MODELS`, with the next code of :data:`MODEL_CODES`: configs, the
    command line's ``--model`` and ``auto``'s ladder then take its name.

    Raises:
        TorchspecError: a model of that name is registered already.
    """
    if model.name in MODELS or model.name == "auto":
        raise TorchspecError(f"a model called {model.name!r} is registered already (or reserved).")
    MODELS[model.name] = model
    return model


def unregister(name: str) -> None:
    """Remove the model ``name`` that :func:`register` added (the last codes only: a built-in
    model, or one registered before another, keeps its code)."""
    if name not in MODELS or name in BUILT_IN:
        raise TorchspecError(f"model {name!r} is not a registered extra model (of {list(MODELS)[len(BUILT_IN) :]}).")
    if list(MODELS)[-1] != name:
        raise TorchspecError(f"model {name!r}: unregister the models registered after it first (codes stay).")
    del MODELS[name]


@contextmanager
def registered(model: Model) -> Iterator[Model]:
    """:func:`register` ``model`` for a ``with`` block, :func:`unregister` it after."""
    register(model)
    try:
        yield model
    finally:
        unregister(model.name)


for _model in _BUILT_IN:
    register(_model)
BUILT_IN = tuple(MODELS)
"""The built-in models' names, in code order."""


class _Codes(Sequence):
    """The registered models' names in code order, read from :data:`MODELS` at each use."""

    def __getitem__(self, index):
        return tuple(MODELS)[index]

    def __len__(self) -> int:
        return len(MODELS)

    def __eq__(self, other) -> bool:
        return tuple(self) == (tuple(other) if isinstance(other, (tuple, list, _Codes)) else other)

    def __hash__(self) -> int:
        return hash(tuple(self))

    def __repr__(self) -> str:
        return repr(tuple(self))


MODEL_CODES: Sequence[str] = _Codes()
"""``model.exr``'s codes: the index of each pixel's model in this sequence (:data:`MODELS`' names,
the registered models' included)."""


def render_chosen(
    svbrdf: SVBRDF, code: Tensor | None, lights: Lights, view: Tensor, *, quadrature: Quadrature = Quadrature()
) -> Tensor:
    """:func:`torchspec.model.rendering.render` of flat maps ``svbrdf (n,)`` whose pixels each have their
    model, ``code (n,)`` (:data:`MODEL_CODES`' index; ``None``: Ward's lobe for all), each with
    its model's lobe: ``(n, K, C)``. One render when every pixel's lobe is Ward's (or none)."""
    lobes = [MODELS[name].lobe or WARD for name in MODEL_CODES]
    others = sorted({i for i, lobe in enumerate(lobes) if lobe is not WARD})
    if code is None or not others:
        return render(svbrdf, lights, view, quadrature=quadrature)
    code = code.long()
    groups = [[i for i, lobe in enumerate(lobes) if lobe is WARD]]
    groups += [[i for i in others if lobes[i] is lobe] for lobe in dict.fromkeys(lobes[i] for i in others)]
    count = lights.directions.shape[0]
    out = svbrdf.diffuse.new_zeros((svbrdf.diffuse.shape[0], count, svbrdf.diffuse.shape[-1]))
    for group in groups:
        index = torch.isin(code, torch.tensor(group, device=code.device)).nonzero()[:, 0]
        if index.numel():
            lobe = lobes[group[0]]
            out[index] = render(svbrdf[index], lights, view, quadrature=quadrature, lobe=lobe).to(out)
    return out


def get_model(name: str) -> Model:
    """The model called ``name``; a clear error lists the known ones.

    Example:
        >>> get_model("ward-iso").size(3)  # 2 angles, 3 k_d, a grey k_s, one alpha
        7
    """
    if name not in MODELS:
        raise TorchspecError(f"model must be one of {sorted(MODELS)}; got {name!r}.")
    return MODELS[name]
