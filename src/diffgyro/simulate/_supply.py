"""Extra logged columns for ``aux(NAME)`` effects: a supply voltage independent of temperature."""

from __future__ import annotations

import numpy as np

from ._population import stream


def supply_voltage(t: np.ndarray, n_devices: int, seed: int, name: str = "vdd",
                   nominal: float = 5.0) -> np.ndarray:
    """A regulated supply (V), (devices, n): a slow wander (±40 mV over a few periods of the
    run), load steps (±25 mV at random times) and a small ripple (2 mV), drawn from a stream
    of its own, so it is independent of the temperature profile."""
    rng = stream(seed, f"supply:{name}")
    t = np.asarray(t, float)
    span = max(float(t[-1] - t[0]), 1.0)
    out = np.empty((n_devices, t.shape[0]))
    for i in range(n_devices):
        periods = rng.uniform(1.5, 3.5)
        phase = rng.uniform(0, 2 * np.pi)
        wander = 0.04 * np.sin(2 * np.pi * periods * (t - t[0]) / span + phase)
        steps = np.zeros_like(t)
        for when in np.sort(rng.uniform(t[0], t[-1], 6)):
            steps[t >= when] += rng.choice([-1.0, 1.0]) * 0.025
        steps -= steps.mean()
        ripple = 0.002 * np.sin(2 * np.pi * (t - t[0]) / rng.uniform(20.0, 60.0))
        out[i] = nominal + wander + steps + ripple
    return out
