"""``diffgyro demo``: the model-discovery loop on a simulated batch with a hidden effect."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from diffgyro.errors import DataError

from . import _progress, app
from .diagnose import print_diagnosis, print_ladder, wide_console


@app.command("demo")
def demo_command(
    out: Annotated[Path, typer.Option("--out", help="Folder of the HTML report.")] = Path("diffgyro-demo"),
    devices: Annotated[int, typer.Option("--devices", help="Simulated devices.")] = 4,
    seed: Annotated[int, typer.Option("--seed", help="Simulation seed.")] = 3,
) -> None:
    """Simulate gyros with a hidden effect, fit a base model, diagnose it, add the named
    effect, refit, print the ladder and write the report (default ./diffgyro-demo/)."""
    from diffgyro._demo import BASE, TRUTH, run_demo


    if devices < 1:
        raise DataError(f"--devices must be at least 1, not {devices}")
    console = wide_console()
    console.print(f"[bold]diffgyro demo[/bold]: the truth is [cyan]{TRUTH}[/cyan] "
                  f"(hidden); we start from [cyan]{BASE}[/cyan].")
    start = time.perf_counter()
    with _progress.steps("starting") as step:
        result = run_demo(out, n_devices=devices, seed=seed, progress=step)
    print_diagnosis(result.ladder.first, console)
    print_ladder(result.ladder, console)
    named = ", ".join(result.added) or "nothing"
    console.print(f"added: [bold]{named}[/bold]; final model [cyan]{result.ladder.spec}[/cyan]; "
                  f"report: {result.report} ({time.perf_counter() - start:.0f} s)")
