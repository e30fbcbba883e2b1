import pytest
import torch

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
