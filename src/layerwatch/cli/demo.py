"""``layerwatch demo``: a simulated print with a failure, through the real pipeline."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from layerwatch.cli import console
from layerwatch.cli.params import SEED, WRITE_DIR, Finite
from layerwatch.errors import ConfigError
from layerwatch.evaluate.demo import run_demo
from layerwatch.evaluate.plate_demo import PLATE_FAILURES, run_plate_demo
from layerwatch.simulate import FAILURE_TYPES
from layerwatch.storage import History
from layerwatch.web.report import build_report

__all__ = ["register"]


def demo(
    out: Annotated[Path, typer.Option("--out", "-o", parser=WRITE_DIR, help="Results folder.")] = Path("demo-out"),
    layers: Annotated[int | None, typer.Option("--layers", "-n", parser=Finite(1, 100_000, integer=True), help="Simulate only the first N layers.")] = None,
    failure: Annotated[str, typer.Option("--failure", help="Injected failure type (spaghetti, layer_shift, ...).")] = "spaghetti",
    onset: Annotated[int, typer.Option("--onset", parser=Finite(1, 100_000, integer=True), help="First failed layer (0-based).")] = 15,
    seed: Annotated[int, typer.Option("--seed", parser=SEED, help="Simulation seed.")] = 1,
    keep_going: Annotated[bool, typer.Option("--keep-going", help="Do not stop at the pause; simulate every layer.")] = False,
    plate: Annotated[bool, typer.Option("--plate", help="A 4-object plate: the failure lands on one object, which is "
                                        "cancelled alone (EXCLUDE_OBJECT); the other three finish.")] = False,
) -> None:
    """Simulate the bundled example part with a failure part-way; stop where a printer would pause."""
    if failure not in FAILURE_TYPES:
        raise ConfigError(f"unknown --failure {failure!r}; use one of {', '.join(FAILURE_TYPES)}.")
    if plate:
        _plate(out, failure, onset, seed)
        return
    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*cols, console=console, transient=True) as bar:
        task = bar.add_task("simulating + analysing", total=None)
        res = run_demo(out, layers=layers, failure=failure, onset=onset, seed=seed, stop_at_pause=not keep_going,
                       progress=lambda d, n, text: bar.update(task, completed=d, total=n, description=text))
    for note in res.notes:
        console.print(f"[dim]{escape(note)}[/]")
    console.print(f"injected [bold]{res.failure}[/] from layer {res.onset}; decision rule: {res.policy}")
    if res.paused_at is None:
        console.print("[yellow]no pause: the print ran to the end without a pause decision.[/]")
    else:
        late = res.paused_at - res.onset
        console.print(f"[bold red]PAUSE[/] at layer {res.paused_at} ({late} layer(s) after the onset): {escape(res.reason)}")
    console.print(f"results in {res.out} (summary.md, overlays/, stack.png) in {res.seconds:.1f} s")
    if res.job_id is not None:
        with History(res.out / "history.db") as history:
            res.report = build_report(history, res.job_id, res.out / "report", image_root=res.out)
        console.print(f"report: {res.report}  (history: {res.out / 'history.db'}; "
                      f"`layerwatch history --db {res.out / 'history.db'}`)")


def _plate(out: Path, failure: str, onset: int, seed: int) -> None:
    """``demo --plate``: run :func:`~layerwatch.evaluate.plate_demo.run_plate_demo` and say what happened."""
    if failure not in PLATE_FAILURES:
        raise ConfigError(f"--plate puts the failure on one object: use --failure {' or '.join(PLATE_FAILURES)}.")
    cols = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*cols, console=console, transient=True) as bar:
        task = bar.add_task("simulating + analysing the plate", total=None)
        res = run_plate_demo(out, failure=failure, onset=onset, seed=seed,
                             progress=lambda d, n, text: bar.update(task, completed=d, total=n, description=text))
    console.print(f"plate of {len(res.objects)} objects ({', '.join(res.objects)}); injected [bold]{res.failure}[/] "
                  f"on {res.failed} from layer {res.onset}")
    for layer, action, reason in res.stops:
        console.print(f"[bold red]{action.upper().replace('_', ' ')}[/] after layer {layer}: {escape(reason)}")
    others = [o for o in res.objects if o not in res.cancelled]
    if res.layers == res.total_layers:
        console.print(f"the print ran to the end (layer {res.layers - 1}): {', '.join(others)} finished")
    else:
        console.print(f"[yellow]the printer stopped after layer {res.layers - 1} of {res.total_layers - 1}[/]")
    about = [a for a in res.later_alarms if a[3]]
    console.print(f"after the cancel: {len(about)} alarm(s) about the cancelled object, "
                  f"{len(res.later_alarms) - len(about)} notification(s) elsewhere")
    console.print(f"results in {res.out} (summary.md, overlays/, plate.gcode) in {res.seconds:.1f} s")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the root app."""
    app.command("demo")(demo)
