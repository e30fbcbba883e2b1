"""The node loops fused by ``torch.compile`` (``Quadrature(compile=True)``): each function is
compiled once per process and kept, with the kind of sizes that suits it.

- The functions in :data:`FIXED_SIZES` are compiled with fixed sizes but for their batch (the
  first axis of the tensor arguments with ``rows`` rows: pixels, pairs); the others with every
  size dynamic. Fixed sizes suit the node rules and integrations; dynamic ones suit the clamp's
  integral and the sums over frames.
- A function's Python floats (a kernel's width) are constants of the graph; the view is passed as
  0-dim tensors (:class:`torchspec.model.lobe.LobeFrame`), read on the device, never on the host.
- Float32 products keep full precision (no TensorFloat32): the maps' tolerances are set by it.
  Inductor's warning that TF32 cores are left unused is silenced, since a user cannot act on it.
- Sizes that happen to be equal are not taken to be the same size (no duck shapes).
"""

from __future__ import annotations

import functools
import warnings

import torch
import torch.fx.experimental._config as fx_config
from torch import Tensor

__all__ = ["FIXED_SIZES", "compiled", "fused"]

# torch._inductor warns once per process on a GPU with TF32 cores; the precision is torchspec's choice
warnings.filterwarnings("ignore", message="TensorFloat32 tensor cores for float32 matrix multiplication")

FIXED_SIZES = set()
"""The functions compiled with fixed sizes but for their batch (:func:`compiled`)."""

_COMPILED = {}


def compiled(function):
    """``function`` fused by ``torch.compile``, called as ``fused(rows, *args)`` (built on first
    use, kept). Every size may change between calls; for the functions in :data:`FIXED_SIZES` only
    the first axis of the tensor arguments with ``rows`` rows may, and the other sizes (frames,
    nodes) are fixed: a fit keeps them, another capture compiles once more."""
    if function not in _COMPILED:
        fixed = function in FIXED_SIZES
        fused = torch.compile(function, dynamic=not fixed)

        @functools.wraps(function)
        def call(rows, *args, **kwargs):
            if fixed:
                _mark_batch((args, kwargs), rows)
            with torch._dynamo.config.patch(specialize_float=True), fx_config.patch(use_duck_shape=False):
                return fused(*args, **kwargs)

        _COMPILED[function] = call
    return _COMPILED[function]


def _mark_batch(value, rows: int) -> None:
    """Mark the first axis of the tensors in ``value`` (nested tuples, lists, dicts) with ``rows``
    rows as dynamic for torch.compile."""
    if isinstance(value, Tensor):
        if value.dim() and value.shape[0] == rows:
            torch._dynamo.maybe_mark_dynamic(value, 0)
    elif isinstance(value, (tuple, list)):
        for item in value:
            _mark_batch(item, rows)
    elif isinstance(value, dict):
        for item in value.values():
            _mark_batch(item, rows)


def fused(function, compile: bool, rows: int):
    """``function``, fused by torch.compile when ``compile`` and its batch has 2 rows or more
    (the compiler specialises sizes 0 and 1: a batch of 1 would compile again; it runs eager).

    Example:
        >>> fused(abs, False, 8) is abs
        True
    """
    return functools.partial(compiled(function), rows) if compile and rows > 1 else function
