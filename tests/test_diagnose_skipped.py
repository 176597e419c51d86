"""``diagnose``'s "not tried" reasons name the device's own numbers for the signals a
candidate reads (its temperature span, peak true rate per axis, heating and cooling,
specific force, an extra column), then what the term needs: never a generic "e.g."."""

from __future__ import annotations

import json

import numpy as np

from diffgyro.cli import main
from diffgyro.data import Recording
from diffgyro.effects import parse_term
from diffgyro.internal import reason

N = 200


def _rec(**kw) -> Recording:
    t = np.arange(N, dtype=float)
    return Recording(t=t, gyro=np.zeros((N, 3)), device="d", **kw)


def test_reason_names_the_span_the_device_has():
    rec = _rec(temp=np.linspace(20.0, 20.3, N))
    assert reason(parse_term("bias_poly(2)"), rec) == (
        "temperature spans only 0.3 °C (20.0 to 20.3 °C): bias_poly(2) needs a temperature "
        "span of at least 2 °C")
    flat = _rec(temp=np.full(N, 25.0))
    assert reason(parse_term("thermal_lag"), flat).startswith("temperature constant at 25.0 °C: ")


def test_reason_names_the_axes_and_rates_the_device_has():
    rate = np.zeros((N, 3))
    rate[:, 2] = 2e-4 * np.sin(np.arange(N) / 10.0)
    rec = _rec(rate=rate, temp=np.linspace(20, 21, N))
    why = reason(parse_term("misalignment"), rec)
    assert why.startswith("true rate peaks at 0, 0, 0.0002 rad/s on rx, ry, rz: misalignment "
                          "needs a true rate above"), why
    why = reason(parse_term("scale_poly(2)"), rec)  # both what it reads: rate and temperature
    assert "temperature spans only 1 °C (20.0 to 21.0 °C)" in why and "rx, ry, rz" in why


def test_reason_for_heating_gradient_accel_and_a_column():
    rec = _rec(temp=np.linspace(20, 30, N), accel=np.tile([0.0, 0.0, 9.81], (N, 1)),
               aux={"vdd": np.full(N, 3.3)})
    assert reason(parse_term("hysteresis"), rec, heating=np.ones(N)).startswith("it only heats: ")
    assert reason(parse_term("gradient"), rec, dtemp=np.full(N, 1e-4)).startswith(
        "|dT/dt| peaks at 0.006 °C/min: gradient needs")
    assert reason(parse_term("g_sens"), rec).startswith(
        "specific force varies by 0, 0, 0 m/s² on ax, ay, az: g_sens needs")
    assert reason(parse_term("aux(vdd)"), rec).startswith("column 'vdd' constant at 3.3: ")


def test_diagnose_lists_each_devices_reason(tmp_path, capsys):
    """A run that heats only, with gravity still: hysteresis and g_sens are not tried, and
    each line and each device's ``skipped`` says what its data show."""
    rng = np.random.default_rng(1)
    rows = ["device,t,gx,gy,gz,temp,ax,ay,az"]
    for dev, lo in (("a", 20.0), ("b", 25.0)):
        for i in range(72):
            g = 1e-3 + rng.normal(0, 1e-4, 3)
            rows.append(f"{dev},{0.5 * i},{g[0]},{g[1]},{g[2]},{lo + 10 * i / 71:.4f},0,0,9.81")
    path = tmp_path / "heat.csv"
    path.write_text("\n".join(rows) + "\n")
    assert main(["diagnose", str(path), "-m", "bias_poly(0)", "--candidates",
                 "bias_poly,hysteresis,g_sens", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    for d in doc["devices"]:
        assert d["skipped"]["hysteresis"].startswith("it only heats: hysteresis needs")
        assert d["skipped"]["g_sens"].startswith("specific force varies by 0, 0, 0 m/s²")
        assert not any("e.g." in why for why in d["skipped"].values())
    assert main(["diagnose", str(path), "-m", "bias_poly(0)", "--candidates",
                 "bias_poly,hysteresis,g_sens"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("not tried:")]
    assert "not tried: hysteresis (it only heats: hysteresis needs both heating and cooling " \
        "in the recording; every device)" in lines, lines
