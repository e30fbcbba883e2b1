import contextlib
import threading
from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
"""The development captures: ``shared/data`` beside the checkout (``../shared/data`` from its root).
A fresh clone without it skips the tests that read a capture (:func:`shared_capture`)."""


def shared_capture(name: str) -> Path:
    """The folder ``SHARED / name`` (a capture, or a file or folder inside one); skips the calling
    test, saying what is missing, when it is absent."""
    path = SHARED / name
    if not path.exists():
        pytest.skip(f"needs the shared development data {path} (shared/data beside the checkout); absent here")
    return path


@pytest.fixture
def shared():
    """:func:`shared_capture` for a test: ``shared("painting-dev")`` is that capture's folder, or a skip."""
    return shared_capture

TOLERANCE = {torch.float32: 1e-5, torch.float64: 1e-10}
"""Noise-free location error allowed, in periods."""

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request):
    return request.param


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


def circular_error(position, truth, period=1.0):
    """Signed distance on the circle of circumference ``period``."""
    return torch.remainder(position - truth + period / 2, period) - period / 2


@pytest.fixture
def unknown_light_capture(tmp_path):
    """A small mirror capture (6 frames) written with its light kernel 'unknown', as a device's
    capture is before calibration: the capture's directory."""
    from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
    from torchspec.simulate.synth import MirrorConfig

    config = SimulationConfig(
        scene=SceneConfig(kind="mirror", mirror=MirrorConfig(width=4, height=4)),
        light=LightConfig(kernel="supergaussian", domain="angular", sigma=0.035, power=6.0),
        layout=LayoutConfig(kind="line", n=6, theta_min_deg=0.0, theta_max_deg=10.0),
    )
    write_simulation(tmp_path / "m", simulate(config))
    return tmp_path / "m"


@pytest.fixture(autouse=True)
def gltf_exports_are_valid(request):
    """Every ``.gltf`` a test writes under its ``tmp_path`` passes the Khronos glTF-Validator with 0
    errors (checked after the test, where node and the validator are installed:
    ``tests/gltf_validator.py``; ``test_export_rti.py`` says so with a skip where they are not)."""
    folder = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if folder is None:
        return
    from gltf_validator import validate, validator

    files = sorted(folder.rglob("*.gltf"))
    if files and validator()[1] is not None:
        bad = [report for report in validate(files) if report["numErrors"]]
        assert not bad, f"glTF-Validator errors: {bad}"


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium with WebGL2 (:class:`torchspec.view.browser.Browser`, 640 x 480); skips,
    saying why, where there is none."""
    from torchspec.view.browser import Browser, find_chromium

    chromium, why = find_chromium()
    if chromium is None:
        pytest.skip(f"no headless Chromium: {why}")
    with Browser(640, 480) as opened:
        if not opened.evaluate("!!document.createElement('canvas').getContext('webgl2')"):
            pytest.skip(f"{chromium} has no WebGL2 here (no GPU and no SwiftShader)")
        yield opened


@contextlib.contextmanager
def served_page(browser, site):
    """``site`` (:class:`torchspec.view.Site`) served on 127.0.0.1 and open in ``browser``."""
    from torchspec.view import serve

    server = serve(site)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        browser.open(f"http://127.0.0.1:{server.server_address[1]}/")
        yield browser
    finally:
        server.shutdown()
