"""``auto``'s fit time against one forced model on the same capture (issue 20: no more than 1.5x).

Each fit runs in a fresh process (its own compilations, nothing warm from the other), the forced
model first; prints wall and CPU seconds, their ratios and the models chosen.

    python experiments/bench_auto.py CAPTURE [--model ward-aniso] [--threads 2]

The benchmark capture is the one ``experiments/bench_fit.py`` simulates and caches (512 x 512 x 144,
under ``/tmp/torchspec-bench-fit``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = """
import json, sys, time
import torch
import torchspec as ts
from torchspec.pipeline import FitConfig
torch.set_num_threads(int(sys.argv[3]))
config = FitConfig.from_dict(json.loads(sys.argv[2]))
wall, cpu = time.perf_counter(), time.process_time()
fit = ts.fit(sys.argv[1], config=config)
print(json.dumps({"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, "models": fit.stats["models"]}))
"""


def timed(capture: str, settings: dict, threads: int) -> dict:
    """One fit of ``capture`` with ``settings`` in a fresh process: wall and CPU seconds, models."""
    done = subprocess.run(
        [sys.executable, "-c", CHILD, capture, json.dumps(settings), str(threads)], capture_output=True, text=True
    )
    if done.returncode != 0:
        raise RuntimeError(f"the fit of {capture} with {settings} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture")
    parser.add_argument("--model", default="ward-aniso", help="the forced model to compare with")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    forced = timed(args.capture, {"model": args.model}, args.threads)
    auto = timed(args.capture, {}, args.threads)
    print(f"{'fit':12s} {'wall s':>8s} {'CPU s':>8s}  models")
    for name, row in ((args.model, forced), ("auto", auto)):
        models = {k: v for k, v in row["models"].items() if v}
        print(f"{name:12s} {row['wall']:8.1f} {row['cpu']:8.1f}  {models}")
    ratio = {"wall": auto["wall"] / forced["wall"], "cpu": auto["cpu"] / forced["cpu"]}
    print(f"auto / {args.model}: wall {ratio['wall']:.2f}x, CPU {ratio['cpu']:.2f}x")
    return {"forced": forced, "auto": auto, "ratio": ratio}


if __name__ == "__main__":
    main()
