"""No host synchronisation inside a solver step: every operation that makes the host wait for the
device (a tensor read as a Python value, a shape that depends on the data) is caught while
:func:`torchspec.lm.solver`'s step runs, for every model and light kernel. On the CPU nothing
waits, but the same operations would on CUDA; the solver's check every few steps
(``LMConfig.check_every``) is then the only synchronisation."""

import traceback

import pytest
import torch
from pixel_cases import grid_lights, random_svbrdf
from torch.overrides import TorchFunctionMode

import torchspec.lm.solver as lm_solver
from torchspec.lm import LMConfig, bounded, solve
from torchspec.model.lights import Kernel
from torchspec.model.quadrature import Quadrature
from torchspec.model.registry import MODELS, get_model

VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
SYNCS = {"item", "tolist", "nonzero", "argwhere", "__bool__", "__int__", "__float__", "__index__", "cpu", "numpy",
         "masked_select", "unique", "unique_consecutive", "nonzero_static"}
"""Operations that wait for the device's result (on CUDA)."""


class HostSyncs(TorchFunctionMode):
    """Records each synchronising operation (:data:`SYNCS`, a boolean mask as an index, or
    ``where`` with one argument) run while the mode is on."""

    def __init__(self):
        super().__init__()
        self.seen = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", str(func))
        masked = name in ("__getitem__", "__setitem__") and _has_mask(args[1])
        if name in SYNCS or masked or (name == "where" and len(args) == 1):
            caller = next(f for f in reversed(traceback.extract_stack()[:-1]) if "/torchspec/" in f.filename)
            self.seen.append(f"{name} at {caller.filename.split('/torchspec/')[-1]}:{caller.lineno}")
        return func(*args, **(kwargs or {}))


def _has_mask(index) -> bool:
    parts = index if isinstance(index, tuple) else (index,)
    return any(isinstance(p, torch.Tensor) and p.dtype == torch.bool for p in parts)


def _problem(kernel: Kernel, count: int = 6):
    g = torch.Generator().manual_seed(0)
    svbrdf, lights = random_svbrdf(count, g), grid_lights(kernel)
    observed = torch.rand(count, lights.directions.shape[0], 3, generator=g, dtype=torch.float64)
    weight = torch.ones(observed.shape[:2], dtype=torch.float64)
    weight[:, 0] = 0
    return svbrdf, lights, observed, weight


@pytest.mark.parametrize(
    "kernel", [Kernel("point"), Kernel("gaussian", sigma=0.08)], ids=["point", "gaussian"]
)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_solver_step_does_not_wait_for_the_device(name, kernel, monkeypatch):
    model = get_model(name)
    svbrdf, lights, observed, weight = _problem(kernel)
    bounds = model.bounds(3)
    params = bounds.to_free(model.pack(svbrdf))
    fn = model.residuals(observed, weight, lights, VIEW, ("R", "G", "B"), quadrature=Quadrature(), normal=True)
    recorder, steps = HostSyncs(), []
    step = lm_solver._step

    def watched(*args, **kwargs):
        steps.append(1)
        with recorder:
            return step(*args, **kwargs)

    monkeypatch.setattr(lm_solver, "_step", watched)
    result = solve(bounded(fn, bounds), params, config=LMConfig(max_iterations=3, check_every=4))
    assert steps and torch.isfinite(result.cost).all()
    assert not recorder.seen, f"host synchronisations inside a solver step: {sorted(set(recorder.seen))}"
