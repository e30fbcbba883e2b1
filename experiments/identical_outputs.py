"""Proof that a change leaves the fit's outputs as they were: save every output of a set of fits,
then compare two saved sets with ``torch.equal``; and compare an experiment's regenerated JSON with
the committed one, number by number, leaving out timings and memory.

    # the old code (a checkout of the commit before the change) and the new code save their fits:
    PYTHONPATH=/path/to/old/checkout python experiments/identical_outputs.py save CAPTURE OLD
    python experiments/identical_outputs.py save CAPTURE NEW
    python experiments/identical_outputs.py compare OLD NEW
    # an experiment's numbers against the committed ones:
    python experiments/model_selection.py --output /tmp/regen
    python experiments/identical_outputs.py numbers /tmp/regen experiments/results

``save`` fits CAPTURE (e.g. ``../shared/data/painting-dev``) with :data:`CASES`, one thread: auto,
every forced model, smoothing, the three starts, several tiles, float64 and the renderer's
quadrature. ``compare`` and ``numbers`` exit 1 on any difference.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import torch

CASES = {
    "auto": ({}, None),
    "auto_half": ({}, "::2"),
    "aniso": ({"model": "ward-aniso"}, None),
    "dual": ({"model": "ward-dual"}, "1::2"),
    "diffuse": ({"model": "diffuse"}, None),
    "smooth": ({"smooth": 10.0}, None),
    "grid_tiles": ({"init": "grid", "tile": 700}, "::3"),
    "naive_nounc": ({"init": "naive", "model": "ward-iso", "uncertainty": False}, None),
    "f64_render": ({"dtype": "float64", "quadrature": "render", "tile": 1000}, "::2"),
}
"""Fit settings and frames of each saved case, in the flat keys of the settings before their groups
(:func:`fit_config` builds them in either layout: the old code's and the new's run the same cases)."""
VARYING = ("second", "time", "per_s", "_ms", "peak_mb", "torch", "cache", "capture", "output", "command")
"""Keys of a result left out of the comparisons: timings, memory, versions and paths."""


def fit_config(settings: dict):
    """The ``FitConfig`` of a case's flat ``settings``: nested into their groups when this torchspec's
    settings have groups (``FitConfig.from_dict``, ``torchspec.pipeline.settings.nested_settings``),
    as they are otherwise (a checkout from before the groups)."""
    from torchspec.pipeline import FitConfig

    if hasattr(FitConfig, "from_dict"):
        from torchspec.pipeline.settings import nested_settings

        return FitConfig.from_dict(nested_settings(settings))
    return FitConfig(**settings)


def flat_settings(settings: dict) -> dict:
    """``stats["settings"]`` (a fit's settings, as ``asdict`` gives them) in the flat keys of the
    settings before their groups (``lm`` stays nested, as it was): the records of the two layouts
    compare key by key. Flat settings are returned as they are."""
    try:
        from torchspec.pipeline.settings import flat_settings
    except ImportError:  # a checkout from before the groups: its settings are flat
        return settings
    return flat_settings(settings)


def outputs(result) -> dict:
    """Every output of a fit (``torchspec.fit``'s result) as a flat dict: tensors and the stats
    without timings."""
    flat = {f"svbrdf.{f.name}": getattr(result.svbrdf, f.name) for f in dataclasses.fields(result.svbrdf)}
    for f in dataclasses.fields(result):
        value = getattr(result, f.name)
        if f.name == "svbrdf":
            continue
        if f.name == "stats":
            flat["stats"] = {key: item for key, item in value.items() if not any(v in key for v in VARYING)}
        elif isinstance(value, dict):
            flat.update({f"{f.name}.{key}": item for key, item in value.items()})
        elif dataclasses.is_dataclass(value):  # the checks
            flat.update({f"{f.name}.{g.name}": getattr(value, g.name) for g in dataclasses.fields(value)})
        else:
            flat[f.name] = value
    return flat


def save(capture: str, folder: Path) -> None:
    import torchspec as ts

    torch.set_num_threads(1)
    folder.mkdir(parents=True, exist_ok=True)
    for name, (settings, frames) in CASES.items():
        result = ts.fit(capture, config=fit_config(settings), frames=frames)
        torch.save(outputs(result), folder / f"{name}.pt")
        print(f"{name}: {result.stats['models']}")


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.shape == b.shape and a.dtype == b.dtype and torch.equal(a.isnan(), b.isnan()) and torch.equal(
            torch.where(a.isnan(), torch.zeros_like(a), a), torch.where(b.isnan(), torch.zeros_like(b), b)
        )
    return a == b


def compare(old: Path, new: Path) -> list[str]:
    """The outputs that differ between two folders of :func:`save` (``case key``)."""
    differ = []
    for path in sorted(old.glob("*.pt")):
        if not (new / path.name).is_file():
            differ.append(f"{path.stem}: missing in {new}")
            continue
        a, b = torch.load(path, weights_only=False), torch.load(new / path.name, weights_only=False)
        for saved in (a, b):  # the settings of either layout, compared key by key
            if isinstance(saved.get("stats"), dict) and isinstance(saved["stats"].get("settings"), dict):
                saved["stats"]["settings"] = flat_settings(saved["stats"]["settings"])
        if isinstance(a.get("stats"), dict) and isinstance(b.get("stats"), dict):
            # A setting the old code did not have (no case sets it: it is at its default) is not an
            # output; it is named, and its outputs compared as the rest.
            added = sorted(set(b["stats"].get("settings", {})) - set(a["stats"].get("settings", {})))
            for key in added:
                print(f"{path.stem}: new setting {key}={b['stats']['settings'].pop(key)!r} (at its default)")
        differ += [f"{path.stem} {key}" for key in sorted(set(a) | set(b)) if not _same(a.get(key), b.get(key))]
    return differ


def numbers(a, b, where: str = "") -> list[str]:
    """Where two JSON documents differ, leaving out the keys of :data:`VARYING` (NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if any(v in key.lower() for v in VARYING):
                continue
            if key not in a or key not in b:
                out.append(f"{where}/{key}: only in {'the new' if key in b else 'the committed'}")
            else:
                out += numbers(a[key], b[key], f"{where}/{key}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items against {len(b)}"]
        return [line for i, (x, y) in enumerate(zip(a, b, strict=True)) for line in numbers(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{where}: {a!r} against {b!r}"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    saving = commands.add_parser("save", help="save every output of the fits of CASES")
    saving.add_argument("capture")
    saving.add_argument("folder", type=Path)
    comparing = commands.add_parser("compare", help="compare two folders of saved fits with torch.equal")
    comparing.add_argument("old", type=Path)
    comparing.add_argument("new", type=Path)
    checking = commands.add_parser("numbers", help="compare regenerated experiment JSONs with committed ones")
    checking.add_argument("regenerated", type=Path)
    checking.add_argument("committed", type=Path)
    args = parser.parse_args(argv)
    if args.command == "save":
        save(args.capture, args.folder)
        return 0
    if args.command == "compare":
        differ = compare(args.old, args.new)
        print("\n".join(differ) if differ else f"identical: every output of {len(list(args.old.glob('*.pt')))} fits")
        return 1 if differ else 0
    status = 0
    for path in sorted(args.regenerated.glob("*.json")):
        committed = args.committed / path.name
        if not committed.is_file():
            print(f"{path.name}: nothing committed")
            continue
        differ = numbers(json.loads(committed.read_text()), json.loads(path.read_text()))
        print(f"{path.name}: " + ("identical numbers" if not differ else f"{len(differ)} differences"))
        for line in differ[:10]:
            print(f"  {line}")
        status |= bool(differ)
    return status


if __name__ == "__main__":
    sys.exit(main())
