"""Picks of the pairs a residual function treats apart, of a size fixed before a solver step
(:func:`pick_pairs`), checked at the solver's check (:class:`Capacities`).

A residual function may compute something costly only for the entries of a mask ``(N, K)``: the
pixel-frame pairs whose light kernel reaches the normal's horizon. ``mask.nonzero()`` lists them,
but its size depends on the data, so on CUDA the host waits for the device. Inside
:func:`torchspec.lm.solve` a pick takes instead a fixed number of pairs, its capacity: the pairs
of the mask first, in ``nonzero``'s order, then as many others (each pair at most once) as fill the
capacity, ``valid`` telling them apart. The caller computes them all and writes back only the
valid ones (:func:`keep`), so the padding changes no value.

Each pick keeps its count on the device. At the solver's check (its one host synchronisation) the
counts are read with the number of running problems; where a pick held more pairs than its
capacity, the solver takes the steps since its last check again, with capacities that hold the
counts seen: no pick is ever cut short. The capacities are shares of the pick's pairs, per pick
of an evaluation (its place in the call sequence: the diffuse clamp and the lobe of each chunk
of pixels), set at each check to :data:`HEADROOM` times the largest share seen since the last
one (and :data:`SLACK` pairs), or :data:`DECAY` times the last capacity where that is more (a
count that falls back is followed slowly).
The start's evaluation, outside any step, picks exactly (``nonzero``) and sets the first
capacities.

Outside a solve a pick is ``nonzero``: exact, with one synchronisation.
"""

from __future__ import annotations

import contextvars
import math

import torch
from torch import Tensor

__all__ = ["HEADROOM", "SLACK", "DECAY", "Capacities", "fixed_pick", "pick_pairs", "keep"]

HEADROOM = 1.1
"""A pick's capacity over the largest share of its pairs seen since the last check ..."""
SLACK = 4
"""... and this many pairs more (a pick whose capacity falls under half a pair takes none)."""
DECAY = 0.5
"""A capacity falls by at most this factor from one check to the next."""

_ACTIVE = contextvars.ContextVar("torchspec_lm_capacities", default=None)


class Capacities:
    """The capacities of the picks of one solve (:func:`pick_pairs`), and the counts seen since
    the last check (on the device, but for the exact start's)."""

    def __init__(self):
        self.shares = {}  # (site, place) -> capacity per pair of the pick
        self.seen = {}  # (site, place) -> the largest share seen since the last check (a 0-dim tensor)
        self.over = None  # a pick held more pairs than its capacity since the last check (0-dim bool)
        self.exact = False
        self.place = 0

    def evaluate(self, function, *args, exact: bool = False):
        """``function(*args)`` (a residual function) with its picks under these capacities, or
        exact (``nonzero``: outside a step) with ``exact``."""
        token = _ACTIVE.set(self)
        self.exact, self.place = exact, 0
        try:
            return function(*args)
        finally:
            _ACTIVE.reset(token)

    def pick(self, mask: Tensor, site: str) -> tuple[Tensor, Tensor, Tensor | None]:
        """:func:`pick_pairs` under these capacities."""
        key = (site, self.place)
        self.place += 1
        total = mask.numel()
        if self.exact:
            pairs = mask.nonzero()
            self._saw(key, torch.full((), pairs.shape[0] / max(total, 1), dtype=torch.float64, device=mask.device))
            return pairs[:, 0], pairs[:, 1], None
        size = self.shares.get(key, 0.0) * total
        capacity = min(total, math.floor(size + 0.5) + SLACK) if size >= 0.5 else 0
        rows, cols, valid, count = fixed_pick(mask, capacity)
        self._saw(key, count.to(torch.float64) / max(total, 1))
        over = count > capacity
        self.over = over if self.over is None else self.over | over
        return rows, cols, valid

    def _saw(self, key, share: Tensor) -> None:
        self.seen[key] = share if key not in self.seen else torch.maximum(self.seen[key], share)

    def check(self, running: Tensor) -> tuple[int, bool]:
        """``(running, overflowed)``: the count ``running`` (a 0-dim tensor) and whether a pick
        held more pairs than its capacity since the last check, read in one synchronisation; the
        capacities for the next steps set from the shares seen."""
        keys = list(self.seen)
        over = self.over if self.over is not None else torch.zeros((), dtype=torch.bool, device=running.device)
        values = torch.stack([running.to(torch.float64), over.to(torch.float64), *(self.seen[k] for k in keys)])
        read = values.tolist()  # the host synchronisation
        overflowed = bool(read[1])
        for key, share in zip(keys, read[2:], strict=True):
            old = self.shares.get(key, 0.0)
            need = min(1.0, HEADROOM * share)
            self.shares[key] = max(old, need) if overflowed else max(need, DECAY * old)
        self.seen, self.over = {}, None
        return int(read[0]), overflowed


def fixed_pick(mask: Tensor, capacity: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The first ``capacity`` pairs ``(row, column)`` of ``mask (N, K)``'s entries ordered true
    first (each part in ``nonzero``'s order), whether each is true ``(capacity,)``, and the count of
    true entries (0-dim, on the device): no host synchronisation."""
    flat = mask.reshape(-1)
    position = torch.arange(flat.shape[0], device=mask.device)
    taken = flat.cumsum(0)
    count = taken[-1] if flat.shape[0] else taken.new_zeros(())
    if capacity == 0:
        empty = position[:0]
        return empty, empty, empty.bool(), count
    rank = torch.where(flat, taken - 1, count + position - taken)  # a permutation: true entries first
    chosen = torch.empty_like(position).scatter_(0, rank, position)[:capacity]
    valid = position[:capacity] < count
    columns = mask.shape[1]
    return chosen // columns, chosen % columns, valid, count


def pick_pairs(mask: Tensor, site: str) -> tuple[Tensor, Tensor, Tensor | None]:
    """The pairs ``(rows, columns)`` of the true entries of ``mask (N, K)``, and ``valid``: inside
    :func:`torchspec.lm.solve`'s step, a fixed number of pairs with the mask's first and ``valid
    (M,)`` telling them apart, without a host synchronisation (:class:`Capacities`, per ``site``
    and place in the evaluation); elsewhere exactly the mask's (``nonzero``) and ``valid`` ``None``.
    Write back with :func:`keep`."""
    capacities = _ACTIVE.get()
    if capacities is None:
        pairs = mask.nonzero()
        return pairs[:, 0], pairs[:, 1], None
    return capacities.pick(mask, site)


def keep(valid: Tensor | None, new: Tensor, old: Tensor) -> Tensor:
    """``new (M, ...)`` where ``valid (M,)`` (everywhere when ``None``), else ``old``: the values
    of a pick (:func:`pick_pairs`) to write back, its padding unchanged."""
    if valid is None:
        return new
    return torch.where(valid.reshape(-1, *([1] * (new.dim() - 1))), new, old)
