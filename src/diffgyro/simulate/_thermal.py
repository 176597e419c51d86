"""Sensor temperature inside a chamber: first-order lag plus self-heating.

Each device's sensor follows

    τ_s · dT_s/dt = T_c(t) + H · P(t) − T_s,        τ_h · dP/dt = p(t) − P

with ``T_c`` the chamber (air) temperature, ``H`` the self-heating (°C above
the chamber at nominal power, settled), ``p`` the dissipated-power schedule
(1 = nominal; 0 before power-on) and ``P`` its lagged effect on the housing.
Both lags are solved exactly for inputs that are linear between samples
(first-order hold), and the true derivative is the right-hand side itself,
``dT_s/dt = (T_c + H·P − T_s)/τ_s``, not a finite difference.

The inside–outside difference is then ``T_s − T_c = H·P − τ_s·dT_s/dt``:
it differs from ``dT/dt`` wherever the dissipated power changes (power-on,
power-level steps of a plan), which is what makes ``temp_diff`` and
``gradient`` separable.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter


def first_order_hold_lag(u: np.ndarray, tau: np.ndarray, dt: float, y0: np.ndarray | None = None):
    """``τ·dy/dt = u − y`` on a uniform grid, ``u`` linear between samples (exact).

    ``u`` is (devices, n), ``tau`` (devices,); ``y0`` the state at the first
    sample (default: settled, ``y0 = u[:, 0]``).
    """
    u = np.atleast_2d(np.asarray(u, dtype=float))
    tau = np.broadcast_to(np.asarray(tau, dtype=float), (u.shape[0],))
    u0 = u[:, :1]
    v = u - u0
    y = np.empty_like(u)
    k = np.arange(u.shape[1])
    for i in range(u.shape[0]):
        a = np.exp(-dt / tau[i])
        c = 1.0 - tau[i] / dt * (1.0 - a)
        # y[k+1] = a·y[k] + (1 − a − c)·v[k] + c·v[k+1], with y[0] = v[0] = 0
        y[i] = lfilter([c, 1.0 - a - c], [1.0, -a], v[i])
        if y0 is not None:
            y[i] += (np.asarray(y0, dtype=float).reshape(-1)[i] - u0[i, 0]) * a**k
    return y + u0


def sensor_temperature(
    chamber: np.ndarray,
    power: np.ndarray,
    dt: float,
    tau_sensor: np.ndarray,
    self_heating: np.ndarray,
    tau_heating: np.ndarray,
    settled: bool,
):
    """True sensor temperature, its exact time derivative and the power state.

    ``chamber`` and ``power`` are (n,) and shared by all devices; the device
    constants are (devices,). ``settled`` means the device was powered long
    before the first sample (no power-on transient).
    Returns ``(temp (d, n), dtemp (d, n) in °C/s, heat_state (d, n))``.
    """
    d = len(tau_sensor)
    p = np.broadcast_to(np.asarray(power, dtype=float), (d, len(power)))
    p0 = p[:, 0] if settled else np.zeros(d)
    state = first_order_hold_lag(p, tau_heating, dt, y0=p0)
    u = np.asarray(chamber, dtype=float)[None, :] + np.asarray(self_heating)[:, None] * state
    temp = first_order_hold_lag(u, tau_sensor, dt, y0=u[:, 0])
    dtemp = (u - temp) / np.asarray(tau_sensor)[:, None]
    return temp, dtemp, state
