"""The ``layerwatch`` command line.

Each verb group lives in its own module (``cli/gcode.py``, ``cli/geometry.py``
...) exposing ``register(app)``. A command line imports only its verb's module
(:data:`VERBS`), so ``layerwatch --help`` and ``layerwatch gcode info`` stay fast.

:func:`main` is the one entry point (the ``layerwatch`` script and ``python -m
layerwatch`` both call it). Its exit codes: 0 done, 1 the job failed or nothing
was analysed (a command raising ``typer.Exit(1)``), 2 a usage or input error
(every :class:`~layerwatch.errors.LayerwatchError` and every usage error of the
parser: unknown verb or option, missing or invalid value), each reported as
one line on stderr; 70 only for a bug (one line naming a crash file with the
traceback). Numeric options are validated by :class:`~layerwatch.cli.params.Finite`.
"""

from __future__ import annotations

import functools
import importlib
import os
import sys
import tempfile
import time
import traceback

import typer
from rich.console import Console
from rich.markup import escape
from rich.text import Text

from layerwatch import __version__
from layerwatch.cli.params import finite_of
from layerwatch.errors import LayerwatchError

__all__ = ["app", "main", "console", "err_console", "PROG"]

PROG = "layerwatch"

_app = typer.Typer(
    name=PROG,
    help="Watch a 3D print layer by layer and stop it early when it fails.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

#: verb -> the module under ``layerwatch.cli`` that registers it (in the order ``--help`` lists them).
#: A command line loads only its verb's module, so ``layerwatch gcode info`` never imports the
#: renderer, OpenCV or the dashboard; ``tests/cli`` checks this table against the full app.
VERBS: dict[str, str] = {
    "gcode": "gcode", "calibrate": "geometry", "warp": "geometry", "markers": "markers",
    "render": "render", "compare": "analysis", "analyze": "pipeline", "simulate": "pipeline",
    "evaluate": "pipeline", "monitor": "monitor", "history": "web", "report": "web", "serve": "web",
    "demo": "demo", "config": "config", "klipper-config": "klipper",
}
_registered: list[str] = []


def _register(*modules: str) -> None:
    """Register the verbs of ``modules`` (names under ``layerwatch.cli``) on the root app, once each."""
    for name in modules:
        if name not in _registered:
            importlib.import_module(f"layerwatch.cli.{name}").register(_app)
            _registered.append(name)


def _register_all() -> None:
    _register(*dict.fromkeys(VERBS.values()))


def __getattr__(name: str):
    """``layerwatch.cli.app``: the root Typer app with every verb registered (tests, docs, plugins)."""
    if name == "app":
        _register_all()
        return _app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


console, err_console = Console(), Console(stderr=True)


def _print_version(value: bool) -> None:
    if value:

        console.print(f"{PROG} {__version__}", markup=False, highlight=False)
        raise typer.Exit(0)


@_app.callback()
def _root(
    version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                 help="Print the version and exit."),
) -> None:
    """Watch a 3D print layer by layer and stop it early when it fails."""



def command(verb: str | None = None):
    """The click command tree of the root app, with help texts made literal.

    ``verb`` (the first word of a command line) registers only the module of that verb
    (see :data:`VERBS`); ``None`` or an unknown word registers every verb (help, usage errors).

    Typer renders help with rich markup, which swallows ``[topview]``-like text; every
    command and parameter help is escaped so it prints as written, and each numeric
    option's help ends with its accepted range (from its :class:`~layerwatch.cli.params.Finite`).
    """
    if verb in VERBS:
        _register(VERBS[verb])
    else:
        _register_all()
    return _built(tuple(_registered))


@functools.cache
def _built(_modules: tuple[str, ...]):
    """The click group of the app as registered with ``_modules`` (built once per set)."""
    group = typer.main.get_command(_app)
    _literal_help(group, getattr(group, "rich_markup_mode", None) == "rich")
    return group


def _literal_help(cmd, rich: bool) -> None:
    """Escape the help texts of ``cmd`` and its subcommands (``rich``) and add the numeric ranges."""

    def literal(text):
        return escape(text) if rich and isinstance(text, str) else text

    cmd.help, cmd.short_help, cmd.epilog = literal(cmd.help), literal(cmd.short_help), literal(cmd.epilog)
    for p in cmd.params:
        fin = finite_of(p)
        text = getattr(p, "help", None)
        if fin is not None:
            text = f"{text or ''} [{fin.range_hint}]".strip()
        if text is not None and hasattr(p, "help"):
            p.help = literal(text)
    for sub in (getattr(cmd, "commands", None) or {}).values():
        _literal_help(sub, rich)


def _click_exceptions() -> tuple[tuple[type[Exception], ...], tuple[type[Exception], ...]]:
    """(ClickException classes, Abort classes) of typer's bundled click and, if installed, click."""
    errors: list[type[Exception]] = []
    aborts: list[type[Exception]] = [typer.Abort]
    for name in ("typer._click.exceptions", "click.exceptions"):
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        errors.append(mod.ClickException)
        if hasattr(mod, "Abort"):  # typer's bundled click raises typer.Abort instead
            aborts.append(mod.Abort)
    return tuple(errors), tuple(aborts)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _error_line(label: str, text: str, style: str = "bold red") -> None:
    """Print ``label text`` as one line on stderr; ``text`` is never read as markup."""
    err_console.print(Text.assemble((label, style), " ", _one_line(text)), soft_wrap=True, highlight=False)


def _usage_error(exc) -> int:
    """One line for a parser error (unknown verb/option, missing or bad value); exit 2 (or its code)."""
    if type(exc).__name__ == "NoArgsIsHelpError":  # (either click's) a bare group: its help was printed
        help_text = exc.format_message()
        if help_text.strip():
            console.print(help_text, markup=False, highlight=False)
        return 2
    text = exc.format_message()
    ctx = getattr(exc, "ctx", None)
    if ctx is not None and getattr(ctx, "command", None) is not None and ctx.help_option_names:
        text = f"{text.rstrip()} (see `{ctx.command_path} {ctx.help_option_names[-1]}`)"
    _error_line("error:", text)
    return int(getattr(exc, "exit_code", 2) or 2)


def main(argv: list[str] | None = None) -> int:
    """Run ``layerwatch ARGV`` (default ``sys.argv[1:]``) and return the exit code (0, 1, 2 or 70)."""
    click_errors, aborts = _click_exceptions()
    args = sys.argv[1:] if argv is None else list(argv)
    try:
        rv = command(args[0] if args else None).main(args=args, prog_name=PROG, standalone_mode=False)
    except LayerwatchError as exc:
        _error_line("error:", str(exc))
        return 2
    except KeyboardInterrupt:
        _error_line("interrupted", "", style="yellow")
        return 130
    except typer.Exit as exc:
        return int(exc.exit_code or 0)
    except click_errors as exc:
        return _usage_error(exc)
    except aborts:
        _error_line("aborted", "", style="yellow")
        return 1
    except OSError as exc:
        if exc.filename is None:  # not about a path the user gave: a bug (or a connector not wrapping it)
            return _internal_error(exc)
        # a path that passed the checks at the edge but cannot be used (read-only mount, full disk, /proc)
        where = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        _error_line("error:", f"{where}: {exc.strerror or exc}; check the path, its folder and permissions.")
        return 2
    except Exception as exc:
        return _internal_error(exc)
    return rv if isinstance(rv, int) and not isinstance(rv, bool) else 0


def _internal_error(exc: BaseException) -> int:
    """A bug, not bad input: one line naming a file with the traceback (``LAYERWATCH_DEBUG=1`` re-raises)."""
    if os.environ.get("LAYERWATCH_DEBUG"):
        raise exc
    where = "(not saved)"
    try:
        fd, where = tempfile.mkstemp(prefix=f"layerwatch-crash-{time.strftime('%Y%m%d-%H%M%S')}-", suffix=".txt")
        with os.fdopen(fd, "w") as f:
            f.write("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
    except OSError:
        pass
    _error_line("internal error:", f"{type(exc).__name__}: {exc} — a layerwatch bug; please report it "
                f"with the traceback in {where}")
    return 70  # EX_SOFTWARE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
