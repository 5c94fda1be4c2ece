"""CLI verb ``layerwatch klipper-config``: print the Klipper macro file for the ``klipper`` profile."""

from __future__ import annotations

import sys

import typer

from layerwatch import __version__
from layerwatch.gcode.klipper_macros import klipper_config as text

__all__ = ["register"]


def klipper_config() -> None:
    """Print layerwatch.cfg (macros LAYERWATCH_SNAPSHOT / LAYERWATCH_WAIT); add [include layerwatch.cfg] to printer.cfg."""
    sys.stdout.write(text(__version__))


def register(app: typer.Typer) -> None:
    """Add ``klipper-config`` to the root app."""
    app.command("klipper-config")(klipper_config)
