"""Files of ``docs/capture-format.md``: OpenEXR images, capture directories and SVBRDF map folders,
validated with errors that name the file and key at fault, and written atomically."""

from .capture import Capture, CaptureError, Frame, LightSpec, read_capture, write_capture
from .exr import ExrError, read_exr, write_exr
from .svbrdf import Maps, SVBRDFError, read_svbrdf, write_svbrdf

__all__ = [
    "Capture",
    "CaptureError",
    "ExrError",
    "Frame",
    "LightSpec",
    "Maps",
    "SVBRDFError",
    "read_capture",
    "read_exr",
    "read_svbrdf",
    "write_capture",
    "write_exr",
    "write_svbrdf",
]
