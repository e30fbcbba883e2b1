"""The coin (realrti-item9): its diffuse and specular maps under the default fit, as imported with
the camera's response estimated (the default) and decoded as sRGB (as before the estimate).

Each run imports the capture reduced by ``downsample`` (``rti_relight.load_reduced``), fits every
frame with the default settings and saves the maps (``coin_maps_<transfer>.npz``); with both saved,
``--figure`` draws the photograph under the highest light, ``k_d`` (as sRGB) and grey ``k_s`` of each,
with the medians of ``k_s`` and ``k_d`` over the coin (the largest connected region of pixels whose
brightness varies over the frames more than the median pixel's, holes filled) and over the paper
around it (the rest, 3 pixels away) (``coin_maps.json``, ``coin_maps.png``).

    python experiments/coin_maps.py --transfer srgb      # run with the package before the estimate (9ef344c)
    python experiments/coin_maps.py                      # the default (auto)
    python experiments/coin_maps.py --figure
"""

from __future__ import annotations

import argparse
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from _common import ROOT

OUT = ROOT / "experiments" / "results"


def fit(transfer: str | None, downsample: int) -> None:
    from rti_relight import load_reduced

    import torchspec

    with tempfile.TemporaryDirectory() as scratch:
        folder = ROOT / "../shared/data/rti/realrti-item9"
        capture, _, codes, _ = load_reduced(folder, Path(scratch), downsample, transfer)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = torchspec.fit(capture)
        top = int(capture.directions()[:, 2].argmax())
        np.savez(
            OUT / f"coin_maps_{transfer or 'auto'}.npz",
            diffuse=result.svbrdf.diffuse.numpy(),
            specular=result.svbrdf.specular.mean(-1).numpy(),
            lobe=result.lobe.numpy(),
            photo=codes[top].permute(1, 2, 0).numpy(),
            spread=codes.mean(1).std(0).numpy(),
        )


def figure() -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import ndimage

    runs = {name: np.load(OUT / f"coin_maps_{name}.npz") for name in ("srgb", "auto")}
    spread = runs["auto"]["spread"]
    labels, count = ndimage.label(spread > np.median(spread))
    sizes = ndimage.sum(np.ones_like(spread), labels, range(1, count + 1))
    coin = ndimage.binary_fill_holes(labels == 1 + int(np.argmax(sizes)))
    paper = ~ndimage.binary_dilation(coin, iterations=3)
    stats, fig = {}, plt.figure(figsize=(9, 6))
    for row, (name, run) in enumerate(runs.items()):
        kd, ks = run["diffuse"], run["specular"]
        stats[name] = {
            region: {
                "k_s_median": float(np.median(ks[mask])),
                "k_d_median": [float(v) for v in np.median(kd[mask], axis=0)],
                "lobe_share": float(run["lobe"][mask].mean()),
            }
            for region, mask in (("coin", coin), ("paper", paper))
        }
        panels = [
            (run["photo"], "photograph (highest light)"),
            (np.clip(kd / np.percentile(kd, 99), 0, 1) ** (1 / 2.2), f"k_d ({name})"),
            (
                ks,
                f"k_s ({name}): coin {stats[name]['coin']['k_s_median']:.2f}, "
                f"paper {stats[name]['paper']['k_s_median']:.2f}",
            ),
        ]
        for col, (image, title) in enumerate(panels):
            ax = fig.add_subplot(2, 3, 3 * row + col + 1)
            shown = ax.imshow(
                image, cmap="gray", vmin=0, vmax=max(1.0, float(np.percentile(ks, 99))) if col == 2 else None
            )
            if col == 2:
                fig.colorbar(shown, ax=ax, fraction=0.046)
            ax.set_title(title, fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(OUT / "coin_maps.png", dpi=90)
    (OUT / "coin_maps.json").write_text(json.dumps(stats, indent=2))
    return stats


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--transfer", default=None)
    parser.add_argument("--downsample", type=int, default=2)
    parser.add_argument("--figure", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.figure:
        print(json.dumps(figure(), indent=1))
    else:
        fit(args.transfer, args.downsample)
