"""Validation of command-line values at the edge: finite numbers in range, paths to write.

Every numeric option of every verb is declared with ``parser=Finite(lo, hi, ...)``::

    lift: Annotated[float, typer.Option("--lift", parser=Finite(0, 50, unit="mm"), help=...)] = 5.0

so ``nan``, ``inf``, ``1e999``, ``abc``, ``1.5`` for a count and values outside the range are
refused before the command runs: one line naming the option, what was given and what to give,
exit code 2 (a :class:`typer.BadParameter`, a usage error). ``tests/cli`` checks that every
``int``/``float`` option of the app has such a parser.

Paths the command writes use ``parser=WRITE_FILE`` or ``parser=WRITE_DIR`` (:class:`Writable`);
paths it reads use typer's own checks, ``exists=True, dir_okay=False`` (a file) or
``exists=True, file_okay=False`` (a folder).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import typer

from layerwatch.errors import ConfigError

__all__ = ["Finite", "SEED", "finite_of", "Writable", "WRITE_FILE", "WRITE_DIR", "WRITE_DB", "scheduler_address", "numbers"]

_INT = re.compile(r"[+-]?\d+")



def _fmt(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


class Finite:
    """Parser of a finite number in ``[lo, hi]`` (bounds optional, each may be open).

    Parameters
    ----------
    lo, hi : float or None
        Bounds; ``None`` leaves that side unbounded (the value must still be finite).
    integer : bool
        A whole number written as digits (``1.5``, ``1e3``, ``0x10`` are refused).
    lo_open, hi_open : bool
        Exclude the bound itself (``Finite(0, lo_open=True)``: strictly positive).
    unit : str
        Unit named in the error message (``"mm"``, ``"s"``, ``"px"``).

    Examples
    --------
    >>> Finite(0, 50, unit="mm")("5")
    5.0
    >>> Finite(1, 100_000, integer=True)(" 12 ")
    12
    """

    def __init__(self, lo: float | None = None, hi: float | None = None, *, integer: bool = False,
                 lo_open: bool = False, hi_open: bool = False, unit: str = "") -> None:
        self.lo, self.hi, self.integer = lo, hi, integer
        self.lo_open, self.hi_open, self.unit = lo_open, hi_open, unit

    @property
    def range_text(self) -> str:
        """The accepted values in words, e.g. ``"a whole number from 1 to 100000"``."""
        kind = "a whole number" if self.integer else "a finite number"
        unit = f" {self.unit}" if self.unit else ""
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None and not (self.lo_open or self.hi_open):
            return f"{kind} from {_fmt(lo)} to {_fmt(hi)}{unit}"
        parts = []
        if lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {_fmt(lo)}")
        if hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {_fmt(hi)}")
        if not parts:
            return f"{kind} in{unit}" if unit else kind
        return f"{kind} {' and '.join(parts)}{unit}"

    @property
    def range_hint(self) -> str:
        """Compact range for help texts, e.g. ``"0<=x<=50 mm"``."""
        lo = "" if self.lo is None else f"{_fmt(self.lo)}{'<' if self.lo_open else '<='}"
        hi = "" if self.hi is None else f"{'<' if self.hi_open else '<='}{_fmt(self.hi)}"
        core = f"{lo}x{hi}" if (lo or hi) else "finite"
        return f"{core}{' ' + self.unit if self.unit else ''}"

    def _in_range(self, x: float) -> bool:
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return False
        return not (self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi))

    def __call__(self, value: object) -> int | float:
        """Parse ``value`` (the command-line text, or a default already a number).

        Raises
        ------
        typer.BadParameter
            Not a number, not finite, not whole where required, or outside the range.
        """
        if isinstance(value, bool):
            raise typer.BadParameter(f"{value!r} is not a number; give {self.range_text}.")
        if isinstance(value, (int, float)):
            x: int | float = value
            shown = repr(value)
        else:
            text = str(value).strip()
            shown = repr(str(value))
            try:
                if self.integer:
                    if not _INT.fullmatch(text):
                        raise ValueError(text)
                    x = int(text)
                else:
                    x = float(text.replace("_", "#"))  # Python reads 1_0 as 10; a user did not mean it
            except ValueError:
                raise typer.BadParameter(f"{shown} is not {'a whole number' if self.integer else 'a number'}; "
                                         f"give {self.range_text}.") from None
        if isinstance(x, float) and not math.isfinite(x):
            raise typer.BadParameter(f"{shown} is not finite; give {self.range_text}.")
        if self.integer and isinstance(x, float):
            if x != int(x):
                raise typer.BadParameter(f"{shown} is not a whole number; give {self.range_text}.")
            x = int(x)
        if not self._in_range(x):
            raise typer.BadParameter(f"{shown} is out of range; give {self.range_text}.")
        return x if self.integer else float(x)


SEED = Finite(0, 2**32 - 1, integer=True)
"""Random seeds: what NumPy's legacy and new generators both accept."""


def finite_of(param) -> Finite | None:
    """The :class:`Finite` parser of a typer-built click parameter, or ``None``."""
    info = getattr(getattr(param, "type_descriptor", None), "parameter_info", None)
    parser = getattr(info, "parser", None)
    return parser if isinstance(parser, Finite) else None


class Writable:
    """Parser of a path layerwatch will write: a file (``folder=False``) or a folder to fill.

    The path must not be the other kind of thing already. A file's folder must exist unless
    ``make_parents`` (the command creates it, as the history database does); a folder is
    created by the command with its missing parents. The nearest existing folder must be one
    this user may write in. What only the write itself can tell (a full disk, a read-only
    mount, ``/proc`` for root) is still reported by :func:`layerwatch.cli.main` as one line.
    """

    def __init__(self, folder: bool = False, make_parents: bool = False) -> None:
        self.folder = folder
        self.make_parents = folder or make_parents

    def __call__(self, value: object) -> Path:
        """Return ``value`` as a :class:`~pathlib.Path`, or raise :class:`typer.BadParameter`."""
        path = Path(str(value))
        if str(value).strip() == "":
            raise typer.BadParameter(f"the path is empty; give a {'folder' if self.folder else 'file name'}.")
        if not self.folder and path.is_dir():
            raise typer.BadParameter(f"{str(path)!r} is a folder; give a file name (e.g. {path / 'out'}).")
        if self.folder and path.exists() and not path.is_dir():
            raise typer.BadParameter(f"{str(path)!r} is a file, not a folder; give a folder to write into.")
        parent = path if self.folder else path.parent
        if not self.make_parents and not parent.is_dir():
            raise typer.BadParameter(f"the folder {str(parent)!r} does not exist; create it first or give another path.")
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise typer.BadParameter(f"{str(parent)!r} is not a folder, so {str(path)!r} cannot be created; "
                                     "give a path in a folder you can write to.")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise typer.BadParameter(f"cannot write in {str(parent)!r} (permission denied); "
                                     "give a path in a folder you can write to.")
        return path


WRITE_FILE = Writable(folder=False)
"""An output file (``-o out.gcode``, ``--json``, a database to create)."""
WRITE_DIR = Writable(folder=True)
"""An output folder (``-o results``, ``--cache``)."""
WRITE_DB = Writable(make_parents=True)
"""A database file, created with its folder when missing (``--db``, ``--history``)."""


_DASK_ADDRESS = re.compile(r"(?:(?:tcp|tls|ucx|ws|wss)://)?[A-Za-z0-9_.-]+:\d{1,5}")


def scheduler_address(value: object) -> str:
    """Parser of a Dask scheduler address: ``local`` or ``[tcp://]host:port``.

    Raises
    ------
    typer.BadParameter
        Anything else (a typo would otherwise wait for a connection time-out).
    """
    text = str(value).strip()
    if text == "local" or _DASK_ADDRESS.fullmatch(text) and 0 < int(text.rsplit(":", 1)[1]) < 65536:
        return text
    raise typer.BadParameter(f"{text!r} is not a Dask scheduler address; give 'local' or host:port "
                             "(e.g. tcp://10.0.0.5:8786).")


def numbers(text: str, count: int, option: str, each: Finite, example: str) -> tuple[float, ...] | None:
    """Parse ``"X,Y"``-like option text into ``count`` numbers, each checked by ``each``.

    Returns ``None`` for empty text (the option was not given).

    Raises
    ------
    ConfigError
        Wrong count, not numbers, not finite or out of range; the message names the option.
    """
    if not text.strip():
        return None
    parts = text.split(",")
    if len(parts) != count:
        raise ConfigError(f"{option} takes {count} numbers separated by commas, e.g. {example}; got {text!r}.")
    try:
        return tuple(float(each(p)) for p in parts)
    except typer.BadParameter as exc:
        raise ConfigError(f"{option} {text!r}: {exc.message}") from None
