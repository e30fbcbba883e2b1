"""The Khronos glTF-Validator (npm package ``gltf-validator``) run through node, for the glTF
exports of the tests: :func:`validator` finds it, :func:`validate` reports on files.

It is looked for in ``$TORCHSPEC_NODE_MODULES`` and in ``.ci/node_modules`` of the checkout
(``.ci/run`` installs it there: ``npm install --no-save --prefix .ci gltf-validator``)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "node" / "validate_gltf.js"
INSTALL = "npm install --no-save --prefix .ci gltf-validator@2.0.0-dev.3.10"


def validator() -> tuple[str | None, Path | None, str]:
    """``(node, node_modules, reason)``: the node executable and the folder holding
    ``gltf-validator``, or ``None`` for what is missing and the reason, said for a skip."""
    node = shutil.which("node")
    if node is None:
        return None, None, "node is not installed (the glTF-Validator runs on node)"
    folders = [Path(p) for p in [os.environ.get("TORCHSPEC_NODE_MODULES")] if p] + [ROOT / ".ci" / "node_modules"]
    for folder in folders:
        if (folder / "gltf-validator" / "package.json").is_file():
            return node, folder, ""
    return node, None, f"the npm package gltf-validator is not in {', '.join(map(str, folders))}; install: {INSTALL}"


def validate(paths: list[Path]) -> list[dict]:
    """One report per glTF file: ``numErrors``, ``numWarnings``, ``numInfos``, ``numHints`` and
    ``messages`` (severity, code, JSON pointer, text); raises ``RuntimeError`` without a validator."""
    node, modules, reason = validator()
    if modules is None:
        raise RuntimeError(reason)
    done = subprocess.run(
        [node, str(SCRIPT), *map(str, paths)],
        env={**os.environ, "NODE_PATH": str(modules)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"the glTF-Validator failed: {done.stderr.strip()}")
    return json.loads(done.stdout)
