"""The root of torchspec's exceptions for bad input.

Each module that validates input has its own exception (:class:`~torchspec.io.CaptureError`,
:class:`~torchspec.io.ExrError`, :class:`~torchspec.io.SVBRDFError`,
:class:`~torchspec.config.ConfigError`), all derived from :class:`TorchspecError`, itself a
:class:`ValueError`: a caller catches every "this input is wrong" at once with
``except TorchspecError`` and tells it apart from a bug, which raises anything else.

This module imports nothing from torchspec, so every module can import it.
"""

from __future__ import annotations

__all__ = ["TorchspecError"]


class TorchspecError(ValueError):
    """Input that torchspec refuses: a file, key, value or shape that breaks the format or a
    function's contract. The message names what is at fault, why, and how to fix it.

    Example:
        >>> from torchspec.io import read_capture
        >>> try:
        ...     read_capture("no-such-capture")
        ... except TorchspecError as error:
        ...     print(type(error).__name__, "names", "no-such-capture" in str(error))
        CaptureError names True
    """
