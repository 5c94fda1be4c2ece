"""The ``layerwatch`` command line.

Each verb group lives in its own module (``cli/gcode.py``, ``cli/geometry.py``
...) exposing ``register(app)``. Heavy imports happen inside the commands so
``layerwatch --help`` stays fast. Every :class:`~layerwatch.errors.LayerwatchError`
becomes one red line on stderr and exit code 2.
"""

from __future__ import annotations

import sys

import typer

from layerwatch.errors import LayerwatchError

__all__ = ["app", "main", "console", "err_console"]

app = typer.Typer(
    name="layerwatch",
    help="Watch a 3D print layer by layer and stop it early when it fails.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _consoles():
    from rich.console import Console

    return Console(), Console(stderr=True)


console, err_console = _consoles()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", help="Print the version and exit."),
) -> None:
    """Watch a 3D print layer by layer and stop it early when it fails."""
    if version:
        from layerwatch import __version__

        console.print(f"layerwatch {__version__}")
        raise typer.Exit(0)


def _register_all() -> None:
    from layerwatch.cli import analysis, demo, gcode, geometry, monitor, pipeline, render, web
    from layerwatch.cli import klipper as klipper_verb

    for module in (gcode, geometry, render, analysis, pipeline, monitor, web, demo, klipper_verb):
        module.register(app)


_register_all()


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the app, turning expected errors into one line and exit 2."""
    try:
        app(args=argv, standalone_mode=False)
    except LayerwatchError as exc:
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        return 2
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/]")
        return 130
    except typer.Exit as exc:
        return int(exc.exit_code or 0)
    except Exception as exc:  # click usage errors and aborts
        import click

        if isinstance(exc, click.exceptions.Abort):
            err_console.print("[yellow]aborted[/]")
            return 1
        if isinstance(exc, click.ClickException):
            exc.show()
            return exc.exit_code
        return _internal_error(exc)
    return 0


def _internal_error(exc: BaseException) -> int:
    """A bug, not bad input: one line naming a file with the traceback (``LAYERWATCH_DEBUG=1`` re-raises)."""
    import os
    import tempfile
    import time
    import traceback

    if os.environ.get("LAYERWATCH_DEBUG"):
        raise exc
    where = "(not saved)"
    try:
        fd, where = tempfile.mkstemp(prefix=f"layerwatch-crash-{time.strftime('%Y%m%d-%H%M%S')}-", suffix=".txt")
        with os.fdopen(fd, "w") as f:
            f.write("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
    except OSError:
        pass
    err_console.print(f"[bold red]internal error:[/] {type(exc).__name__}: {exc} — a layerwatch bug; please report it "
                      f"with the traceback in {where}", highlight=False, soft_wrap=True)
    return 70  # EX_SOFTWARE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
