"""What every experiment script shares: its command line (a config and an output folder)."""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).parents[1]


def parse_args(doc: str, config: str, argv: list[str] | None = None, *, options=None) -> argparse.Namespace:
    """``--config`` (default ``experiments/configs/<config>``) and ``--output`` (default ``experiments/results``);
    ``options(parser)``, if given, adds a script's own."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "experiments" / "configs" / config)
    parser.add_argument("--output", type=Path, default=ROOT / "experiments" / "results")
    if options is not None:
        options(parser)
    return parser.parse_args(argv)


def scipy_fit(model, y, level, init, lights, view, channels, *, path="auto", quadrature=None, repeats=1):
    """The baseline a user would otherwise pick: ``scipy.optimize.least_squares`` (trust region
    reflective, the fit's bounds, the analytic Jacobian of :func:`torchspec.model.jacobian.jacobian` with the
    fit's :class:`~torchspec.model.quadrature.Quadrature` ``quadrature`` on the path ``path``) on each pixel
    of ``y (n, K, C)`` in turn, weighted as the fit weighs
    it (one over its ``level (n,)``), from the SVBRDF ``init (n,)``: the fit's own model, so the two
    differ in the solver only.

    Returns:
        ``(svbrdf (n,), seconds, evaluations)``: the fastest of ``repeats`` timings of the same loop
        (the machine's load varies) and the model evaluations per pixel.
    """
    import time
    from dataclasses import replace

    import numpy as np
    import torch
    from scipy.optimize import least_squares

    from torchspec.model.quadrature import Quadrature
    from torchspec.model.registry import ALPHA_BOUNDS

    dtype = y.dtype
    rule = replace(quadrature or Quadrature(), path=path)
    x0 = model.pack(init).double().numpy()
    kinds = model.bounds(len(channels)).kinds
    lower = np.array([-np.inf if k == "free" else (ALPHA_BOUNDS[0] if isinstance(k, tuple) else 0.0) for k in kinds])
    upper = np.array([ALPHA_BOUNDS[1] if isinstance(k, tuple) else np.inf for k in kinds])
    times = []
    for _ in range(max(1, repeats)):
        fitted, evaluations = [], []
        begin = time.perf_counter()
        for i in range(y.shape[0]):
            weight = torch.full((1, y.shape[1]), 1.0, dtype=dtype) / level[i]
            fn = model.residuals(y[i : i + 1], weight, lights, view, channels, quadrature=rule)
            index = torch.zeros(1, dtype=torch.long)
            cache = {}

            def value(x, fn=fn, index=index, cache=cache):
                r, j = fn(torch.as_tensor(x, dtype=dtype)[None], index)
                cache["j"] = (x.copy(), j[0].double().numpy())
                return r[0].double().numpy()

            def jac(x, fn=fn, index=index, cache=cache):
                if "j" in cache and np.array_equal(cache["j"][0], x):
                    return cache["j"][1]
                return fn(torch.as_tensor(x, dtype=dtype)[None], index)[1][0].double().numpy()

            x = np.clip(x0[i], lower + 1e-12, upper - 1e-12)
            out = least_squares(value, x, jac=jac, bounds=(lower, upper), method="trf", x_scale="jac")
            fitted.append(torch.as_tensor(out.x, dtype=dtype))
            evaluations.append(int(out.nfev))
        times.append(time.perf_counter() - begin)
    return model.unpack(torch.stack(fitted), channels, order=True), min(times), evaluations
