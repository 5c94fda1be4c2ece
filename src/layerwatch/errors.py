"""The error hierarchy.

Every error a user can cause (bad input, bad config, unreachable hardware)
is a :class:`LayerwatchError`. Its message is one sentence that says what was
wrong, where, and what to do; the CLI prints it as one red line and exits
with code 2. Anything else escaping is a bug.
"""

from __future__ import annotations

import importlib

__all__ = [
    "LayerwatchError",
    "ConfigError",
    "GcodeError",
    "CalibrationError",
    "MarkerError",
    "WarpError",
    "RenderError",
    "AnalysisError",
    "CameraError",
    "PrinterError",
    "StorageError",
    "MissingExtraError",
]


class LayerwatchError(Exception):
    """Root of every error layerwatch raises on purpose."""


class ConfigError(LayerwatchError):
    """A configuration file or value is invalid."""


class GcodeError(LayerwatchError):
    """G-code could not be read; the message names file:line and the text."""


class CalibrationError(LayerwatchError):
    """Camera intrinsics could not be estimated from the given photos."""


class MarkerError(LayerwatchError):
    """Bed markers are missing, duplicated, or give an implausible pose."""


class WarpError(LayerwatchError):
    """A photo cannot be warped into the top view (size, model mismatch)."""


class RenderError(LayerwatchError):
    """A reference image or mask could not be rendered."""


class AnalysisError(LayerwatchError):
    """Images handed to the analysis do not fit together."""


class CameraError(LayerwatchError):
    """A camera source gave no usable frame."""


class PrinterError(LayerwatchError):
    """A printer host did not answer or refused a request."""


class StorageError(LayerwatchError):
    """The history database cannot be opened or written."""


class MissingExtraError(LayerwatchError):
    """An optional dependency is not installed."""

    def __init__(self, module: str, extra: str, purpose: str) -> None:
        super().__init__(
            f"{purpose} needs the Python package '{module}': "
            f"run `pip install 'layerwatch[{extra}]'`."
        )
        self.module = module
        self.extra = extra


def require(module: str, extra: str, purpose: str):
    """Import an optional module or raise :class:`MissingExtraError`.

    Parameters
    ----------
    module : str
        Importable module name, e.g. ``"fastapi"``.
    extra : str
        The pip extra that provides it, e.g. ``"web"``.
    purpose : str
        What the user was trying to do, used in the message.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on environment
        raise MissingExtraError(module, extra, purpose) from exc
