"""``layerwatch config show``: the effective settings of a job and where each value came from."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Annotated

import typer

from layerwatch.cli import console
from layerwatch.cli.pipeline import PAPER_HELP, _toolpath, job_settings
from layerwatch.errors import ConfigError

__all__ = ["register", "parse_set"]

app = typer.Typer(help="The job's settings: `layerwatch config show [-c job.toml]`.", no_args_is_help=True)


def parse_set(items: list[str] | None) -> dict[str, dict]:
    """``["analysis.threshold=0.3", ...]`` -> ``{"analysis": {"threshold": 0.3}}`` (values read as TOML, else text).

    Raises
    ------
    ConfigError
        An item is not ``SECTION.KEY=VALUE``.
    """
    out: dict[str, dict] = {}
    for item in items or []:
        name, sep, text = item.partition("=")
        section, dot, key = name.strip().partition(".")
        if not (sep and dot and section and key):
            raise ConfigError(f"--set {item!r} is not SECTION.KEY=VALUE; e.g. --set analysis.threshold=0.3.")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out.setdefault(section, {})[key] = value
    return out


def _leaves(key: str, value: object) -> list[tuple[str, object]]:
    """``("policy.kinds", {"spaghetti": {"action": "rule"}})`` -> ``[("policy.kinds.spaghetti.action", "rule")]``."""
    if isinstance(value, dict) and value:
        return [leaf for k, v in value.items() for leaf in _leaves(f"{key}.{k}", v)]
    return [(key, value)]


@app.command("show")
def show(
    config: Annotated[Path | None, typer.Option("--config", "-c", help="Job config TOML.")] = None,
    gcode: Annotated[Path | None, typer.Option("--gcode", "-g", help="The job's G-code (centres the observed "
                                               "square on the part when no job file is given).")] = None,
    paper: Annotated[bool, typer.Option("--paper-settings", help=PAPER_HELP)] = False,
    set_: Annotated[list[str] | None, typer.Option("--set", help="SECTION.KEY=VALUE as a command-line flag would "
                                                   "set it, repeatable.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print {key: {value, source}} as JSON.")] = False,
) -> None:
    """Print every setting a verb would run with and its source: default, recommended, gcode, file or flag.

    The job file is resolved as ``analyze`` and ``evaluate`` do: ``-c``, else the bundled example's job
    file when no ``--gcode`` is given.
    """
    tp = _toolpath(gcode) if gcode is not None and config is None else None
    resolved = job_settings(config, gcode, tp, paper=paper, flags=parse_set(set_))
    values = resolved.config.model_dump(mode="json")
    rows = {}
    for key, src in sorted(resolved.sources.items()):
        value: object = values
        for part in key.split("."):
            value = value[part]  # type: ignore[index]
        rows.update({k: {"value": v, "source": src} for k, v in _leaves(key, value)})
    if as_json:
        console.print_json(json.dumps(rows))
        return
    console.print(f"job file: {resolved.path or 'none'}" + ("  (--paper-settings: recommended left out)" if paper else ""),
                  highlight=False, markup=False, soft_wrap=True)
    width = max(len(k) for k in rows)
    for key, row in rows.items():
        text = json.dumps(row["value"])
        console.print(f"{key:<{width}}  {text:<24}  {row['source']}", highlight=False, markup=False, soft_wrap=True)


def register(root: typer.Typer) -> None:
    """Add the ``config`` command group to the root app."""
    root.add_typer(app, name="config")
