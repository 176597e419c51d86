"""``diffgyro simulate``: a batch of simulated devices with known truth.

Writes the recordings in the standard schema (CSV / Parquet / NPZ by
extension) and the truth beside them (``x.csv`` -> ``x.truth.json``).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from typing import Annotated

import typer

from diffgyro.errors import DataError

from . import _progress, app


def _value(text: str):
    """A plan-option value from the command line: a Python literal, else the text."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def _pairs(items: list[str] | None, what: str) -> dict:

    out = {}
    for item in items or []:
        for part in ([item] if what == "--set" else item.split(",")):
            key, sep, val = part.partition("=")
            if not sep or not key.strip():
                raise DataError(f"cannot read {what} {part!r}", hint="write KEY=VALUE")
            out[key.strip()] = _value(val.strip())
    return out


@app.command("simulate")
def simulate_command(
    plan: Annotated[str, typer.Option("--plan", "-p", help="Test plan: thermal, rate_table, s2, "
                                                          "six_face, static, attitude, warmup.")],
    devices: Annotated[int, typer.Option("--devices", "-n", help="Number of devices.", min=1)] = 3,
    effects: Annotated[str | None, typer.Option(
        "--effects", "-e", help="Effects present, as a model spec (default: the plan's).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed (same seed, same output).")] = 0,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Data file (.csv, .parquet, .npz); the truth goes to NAME.truth.json. "
                            "Without it the CSV goes to stdout.")] = None,
    preset: Annotated[str | None, typer.Option(
        "--preset", help="Device class: mems or fog (default: the plan's).")] = None,
    rate: Annotated[float | None, typer.Option("--rate", help="Sampling rate in Hz.")] = None,
    duration: Annotated[float | None, typer.Option(
        "--duration", help="Length in seconds (plans thermal, static, warmup, attitude).")] = None,
    temp_quantum: Annotated[float | None, typer.Option(
        "--temp-quantum", help="Temperature read-out step in °C (e.g. 1.0).")] = None,
    noise: Annotated[str | None, typer.Option(
        "--noise", help="'none', or levels to override, e.g. 'arw=1e-4,rrw=0' (rad/s/√Hz, "
                        "rad/s²/√Hz, bias_instability rad/s, quantum rad/s).")] = None,
    options: Annotated[list[str] | None, typer.Option(
        "--set", help="Plan option KEY=VALUE (repeatable), e.g. --set latitude=30 --set tilt=1.")] = None,
    truth: Annotated[Path | None, typer.Option(
        "--truth", help="Where to write the truth JSON (default: beside --out).")] = None,
) -> None:
    """Simulate devices through a test plan; write data and known truth."""
    from diffgyro.io import save
    from diffgyro.simulate import simulate, truth_path

    plan_options = _pairs(options, "--set")
    if rate is not None:
        plan_options["sample_rate"] = rate
    if duration is not None:
        plan_options["duration"] = duration
    if noise is not None and noise.strip().lower() not in ("none", "off", "0"):
        noise_arg = _pairs([noise], "--noise")
    else:
        noise_arg = noise
    with _progress.steps(f"simulating {devices} device(s), plan {plan}") as step:
        batch, known = simulate(plan, devices, effects=effects, seed=seed, preset=preset,
                                noise=noise_arg, temp_quantum=temp_quantum, **plan_options)
        if out is not None:
            step(f"writing {out}")
            path = save(batch, out)
    if out is None:
        frame = batch.to_frame()
        frame.to_csv(sys.stdout, index=False, float_format="%.17g")
        if truth is not None:
            known.to_json(truth)
        return
    tpath = truth if truth is not None else truth_path(path)
    known.to_json(tpath)
    n = int(batch.n_valid.max())
    print(f"wrote {path}: {batch.n_devices} devices x {n} samples, plan {known.plan}, "
          f"effects {known.spec}, preset {known.preset}; truth in {tpath}", file=sys.stderr)
