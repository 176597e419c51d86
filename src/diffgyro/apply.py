"""Apply a calibration with numpy alone: the reference for firmware and other languages.

This file depends on numpy and the standard library only, so it can be
copied next to a data pipeline or read as the specification of the formula.
It derives the signals of ``diffgyro._signal_catalogue`` itself, in numpy
(:data:`SIGNALS`, and the list in step 3's ``term(EXPR)`` row): the one place
besides the catalogue, held to it signal by signal by tests/test_signal_catalogue.py.
For one device with calibration record ``dev`` (an entry of the file's
``devices`` list) and model spec ``spec``:

1. Clamp temperature to ``dev["temp_range"]`` (PX4 does the same) and
   centre it: ``Ts = (T - temp_centre) / temp_scale``.
2. dT/dt is the least-squares slope of the *measured* temperature over a
   centred window of ``dtemp_window`` seconds (half-width
   ``round(dtemp_window / 2 / dt)`` samples, clipped at the ends).
3. Every term gives per-axis regressor columns; ``beta[i]`` (axis i) holds
   their coefficients in spec order; time constants are ``exp(theta)``:

   ======================  ===============================================
   ``bias_poly(k)``        ``Ts**0 .. Ts**k``
   ``scale_poly(k)``       ``Ω_i · Ts**0 .. Ω_i · Ts**k``
   ``scale_asym``          ``|Ω_i|``
   ``scale_nonlin``        ``Ω_i**3``
   ``misalignment``        the other two axes' ``Ω_j`` (x: y, z; y: x, z; z: x, y)
   ``g_sens``              ``a_x, a_y, a_z`` (specific force, m/s²)
   ``gradient``            ``dT/dt`` (°C/s)
   ``temp_diff``           ``T − T_ext`` (°C, T clamped as in step 1)
   ``hysteresis``          +1 after heating, −1 after cooling (|dT/dt| > 0.05 °C/min), latched
   ``thermal_lag(k)``      ``Tlag_s**j − Ts**j``, j = 1..k; Tlag = T through a first-order lag τ
   ``warmup``              ``exp(−t/τ)``, t from the first sample
   ``aux(NAME,k)``         ``x_s**1 .. x_s**k`` (k = 1 if left out), x = extra column NAME
                           clamped to ``dev["aux"][NAME]["range"]``, ``x_s = (x − centre) /
                           scale`` with that entry's ``centre`` and ``scale``
   ``term(EXPR)``          one column: the product of EXPR's factors ``s``, ``s^k`` and
                           ``lag(s)`` (s through a first-order lag τ), signals ``temp`` (Ts),
                           ``temp_ext`` ((T_ext − temp_centre) / temp_scale), ``dtemp``
                           (dT/dt in °C/min), ``heating``, ``ax ay az`` (m/s² / 9.80665),
                           ``rx ry rz`` (rad/s), ``w`` (Ω_i of axis i), or an extra
                           column's ``x_s`` as for ``aux``
   ``random_walk``         none: the walk is tracked while fitting, not stored
   ======================  ===============================================

4. ``gyro_i = Ω_i + columns_i · beta_i``; compensation solves this for Ω
   with Newton steps (one step is exact when no term is nonlinear in Ω).

An accelerometer calibration (the file's ``channel`` is ``accel``) is applied by
:func:`compensate_accel` to the accelerometer's columns (m/s²), in one of two ways:

* several orientations (the model reads a reference input, ``scale_poly`` or
  ``misalignment``: there it was gravity): ``a = f + columns · beta`` with ``f`` the
  specific force in place of Ω, solved for ``f`` as in step 4; the result is the
  calibrated specific force (absolute offset, its thermal change and scale removed);
* one orientation (bias terms only): the soak determined the offset's *change* with
  temperature, so ``a − (columns · beta − columns_ref · beta)``, ``columns_ref`` being the
  columns at the reference state: ``T = temp_centre`` held steady (dT/dt = 0, no
  heating or cooling, ``T_ext = T``, extra columns at their centres). The result is the
  accelerometer as it reads at ``temp_centre``; its absolute offset is the accelerometer
  calibration's to remove, as both autopilots' parameters leave it.

A term registered outside diffgyro has no code here: its numpy columns are passed in
``terms``, a mapping from its name to ``fn(order, dev, rate, env, theta) -> (columns,
used)`` (``order`` the spec's whole-number argument or None, ``env`` from
:func:`environment`, ``theta`` the log τ from this term's on, ``used`` how many of them
it read); the term's class declares the same function as ``numpy_columns``.
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["compensate", "compensate_accel", "environment", "columns", "local_slope",
           "reads_input", "HEATING_THRESHOLD", "G", "SIGNALS"]

HEATING_THRESHOLD = 0.05 / 60.0
_OTHERS = ((1, 2), (0, 2), (0, 1))
_TERM = re.compile(r"^([a-z][a-z0-9_]*)(?:\((\d+)\))?$")
_AUX = re.compile(r"^aux\(([A-Za-z_][A-Za-z0-9_.]*)(?:,(\d+))?\)$")
_GRAMMAR = re.compile(r"^term\((.+)\)$")
_FACTOR = re.compile(r"^(?:lag\(([A-Za-z_][A-Za-z0-9_.]*)\)|([A-Za-z_][A-Za-z0-9_.]*))(?:\^(\d+))?$")
G = 9.80665


def _terms(spec: str):
    """(name, order) per term; an aux term gives ("aux", (column, order))."""
    out = []
    for part in spec.replace(" ", "").split("+"):
        g = _GRAMMAR.match(part)
        if g is not None:
            out.append(("term", _factors(g.group(1))))
            continue
        a = _AUX.match(part)
        if a is not None:
            out.append(("aux", (a.group(1), int(a.group(2) or 1))))
            continue
        m = _TERM.match(part)
        if m is None:
            raise ValueError(f"bad term {part!r}")
        out.append((m.group(1), None if m.group(2) is None else int(m.group(2))))
    return out


def _factors(expr: str):
    """(signal, lagged, power) of every factor of a ``term(EXPR)``."""
    out = []
    for f in expr.split("*"):
        m = _FACTOR.match(f)
        if m is None:
            raise ValueError(f"bad factor {f!r} of term({expr})")
        out.append((m.group(1) or m.group(2), m.group(1) is not None, int(m.group(3) or 1)))
    return out


def _force(k: int):
    return lambda dev, rate, env: env["accel"][:, k] / G


def _rate(k: int):
    return lambda dev, rate, env: rate[:, k]


#: Every signal of ``term(EXPR)`` by grammar name: ``(dev, rate, env) ->`` (n,), or (n, 3)
#: for ``w``. The numpy twin of the catalogue (``diffgyro._signal_catalogue``), held to it
#: by tests/test_signal_catalogue.py; any other name is an extra column.
SIGNALS = {
    "temp": lambda dev, rate, env: env["temp_s"],
    "temp_ext": lambda dev, rate, env: (env["temp_ext"] - dev["temp_centre"]) / dev["temp_scale"],
    "dtemp": lambda dev, rate, env: 60.0 * env["dtemp"],
    "heating": lambda dev, rate, env: env["heating"],
    **{f"a{c}": _force(k) for k, c in enumerate("xyz")},
    **{f"r{c}": _rate(k) for k, c in enumerate("xyz")},
    "w": lambda dev, rate, env: rate,
}


def _signal(name: str, dev: dict, rate: np.ndarray, env: dict) -> np.ndarray:
    """A grammar signal: (n,), or (n, 3) for ``w``."""
    if name in SIGNALS:
        return SIGNALS[name](dev, rate, env)
    return env["aux_s"][name]


def local_slope(t: np.ndarray, y: np.ndarray, half: int) -> np.ndarray:
    """Centred least-squares slope of y(t) over samples i-half .. i+half.

    **Arguments:**

    - ``t``: sample times (n,).
    - ``y``: the samples (n,).
    - ``half``: the window's half-width in samples (clipped at the ends).
    """
    n = len(t)
    tc, yc = t - t.mean(), y - y.mean()

    def csum(x):
        return np.concatenate([[0.0], np.cumsum(x)])

    c1, ct, cy, ctt, cty = csum(np.ones(n)), csum(tc), csum(yc), csum(tc * tc), csum(tc * yc)
    i = np.arange(n)
    lo, hi = np.clip(i - half, 0, n), np.clip(i + half + 1, 0, n)
    s1, st, sy = c1[hi] - c1[lo], ct[hi] - ct[lo], cy[hi] - cy[lo]
    stt, sty = ctt[hi] - ctt[lo], cty[hi] - cty[lo]
    var = stt - st * st / s1
    cov = sty - st * sy / s1
    return np.where(var > 0, cov / np.where(var > 0, var, 1.0), 0.0)


def latched_heating(dtemp: np.ndarray) -> np.ndarray:
    active = np.abs(dtemp) > HEATING_THRESHOLD
    if not active.any():
        return np.zeros_like(dtemp)
    # the sign of the latest active sample (before the first, of the first)
    latest = np.maximum.accumulate(np.where(active, np.arange(len(dtemp)), -1))
    latest[latest < 0] = np.argmax(active)
    return np.sign(dtemp[latest])


def first_order_lag(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    y = np.empty_like(x)
    y[0] = x[0]
    alpha = -np.expm1(-np.diff(t) / tau)
    for k in range(1, len(x)):
        y[k] = y[k - 1] + alpha[k - 1] * (x[k] - y[k - 1])
    return y


#: Terms whose columns do not read the rate: :func:`compensate` builds them once per device,
#: not at each of its Newton steps.
_RATE_FREE = frozenset({"bias_poly", "g_sens", "gradient", "temp_diff", "hysteresis",
                       "thermal_lag", "aux", "warmup", "random_walk"})


def columns(spec: str, dev: dict, rate: np.ndarray, env: dict, terms=None,
            kept: dict | None = None) -> np.ndarray:
    """Regressor columns (n, 3, p) of every term of ``spec`` at the true rate.

    **Arguments:**

    - ``spec``: the calibration file's model spec (``"bias_poly(2)+gradient"``).
    - ``dev``: the device's record in the file (``beta``, ``theta``, ``temp_centre``, …).
    - ``rate``: the true rate (n, 3), rad/s.
    - ``env``: the derived signals of :func:`environment`.
    - ``terms``: the numpy columns of terms registered outside diffgyro, by name (see the
      module's notes); None: built-in terms only.
    - ``kept``: a dict that this call fills with the columns of the terms that do not read
      the rate (``bias_poly``, ``gradient``, ``thermal_lag``, ...) and a later call with
      the same ``spec``, ``dev`` and ``env`` reads instead of building them again (the same
      arrays); None: none kept.
    """
    cols, q = [], 0
    theta = np.asarray(dev["theta"], float)
    for index, (name, k) in enumerate(_terms(spec)):
        if kept is not None and index in kept:
            c, used = kept[index]
        else:
            c, used = _term_columns(name, k, dev, rate, env, theta[q:], terms)
            if kept is not None and name in _RATE_FREE:
                kept[index] = c, used
        q += used
        if c is not None:
            cols.append(c)
    return np.concatenate(cols, axis=-1) if cols else np.zeros((rate.shape[0], 3, 0))


def _term_columns(name: str, k, dev: dict, rate: np.ndarray, env: dict, theta: np.ndarray,
                  terms) -> tuple[np.ndarray | None, int]:
    """(columns (n, 3, p) or None for a term without any, time constants it read from the
    start of ``theta``) of one term of a spec (:func:`columns`)."""
    n = rate.shape[0]
    ts = env.get("temp_s")
    if name == "bias_poly":
        c = np.stack([np.ones(n) if j == 0 else ts**j for j in range(k + 1)], -1)
        return np.repeat(c[:, None, :], 3, axis=1), 0
    if name == "scale_poly":
        p = np.stack([np.ones(n) if j == 0 else ts**j for j in range(k + 1)], -1)
        return rate[:, :, None] * p[:, None, :], 0
    if name == "scale_asym":
        return np.abs(rate)[:, :, None], 0
    if name == "scale_nonlin":
        return (rate**3)[:, :, None], 0
    if name == "misalignment":
        return np.stack([rate[:, list(o)] for o in _OTHERS], axis=1), 0
    if name == "g_sens":
        return np.repeat(env["accel"][:, None, :], 3, axis=1), 0
    if name == "gradient":
        return np.repeat(env["dtemp"][:, None, None], 3, axis=1), 0
    if name == "temp_diff":
        d = env["temp"] - env["temp_ext"]
        return np.repeat(d[:, None, None], 3, axis=1), 0
    if name == "hysteresis":
        return np.repeat(env["heating"][:, None, None], 3, axis=1), 0
    if name == "thermal_lag":
        k = 1 if k is None else k
        tau = float(np.exp(np.clip(theta[0], -6.9, 16.1)))
        lag = first_order_lag(env["t"], env["temp"], tau)
        lag_s = (lag - dev["temp_centre"]) / dev["temp_scale"]
        c = np.stack([lag_s**j - ts**j for j in range(1, k + 1)], -1)
        return np.repeat(c[:, None, :], 3, axis=1), 1
    if name == "aux":
        column, order = k
        xs = env["aux_s"][column]
        c = np.stack([xs**j for j in range(1, order + 1)], -1)
        return np.repeat(c[:, None, :], 3, axis=1), 0
    if name == "term":
        prod, q = np.ones((n, 3)), 0
        for sname, lagged, power in k:
            x = _signal(sname, dev, rate, env)
            if lagged:
                tau = float(np.exp(np.clip(theta[q], -6.9, 16.1)))
                q += 1
                x = first_order_lag(env["t"], x, tau)
            x = x**power
            prod = prod * (x if x.ndim == 2 else x[:, None])
        return prod[:, :, None], q
    if name == "random_walk":
        return None, 0
    if name == "warmup":
        tau = float(np.exp(np.clip(theta[0], -6.9, 16.1)))
        return np.repeat(np.exp(-env["t"] / tau)[:, None, None], 3, axis=1), 1
    if terms and name in terms:
        c, used = terms[name](k, dev, rate, env, theta)
        return np.asarray(c, float), int(used)
    raise ValueError(f"apply.py knows the built-in terms only, not {name!r}; "
                     f"pass its numpy columns as terms={{{name!r}: fn}}")


def environment(dev: dict, t, temp=None, temp_ext=None, accel=None, dtemp_window=60.0,
                aux=None) -> dict:
    """Derived signals of one device, as the calibration defines them (steps 1 and 2).

    **Arguments:**

    - ``dev``: the device's record in the calibration file (its ``temp_range``,
      ``temp_centre``, ``temp_scale`` and ``aux`` centring).
    - ``t``: sample times (n,), s.
    - ``temp``: die temperature (n,), °C, or None when no term reads it.
    - ``temp_ext``: external temperature (n,), °C, or None.
    - ``accel``: specific force (n, 3), m/s², or None.
    - ``dtemp_window``: the window of the dT/dt slope, s (the file's ``dtemp_window``).
    - ``aux``: the extra columns' samples (n,) by name, for ``aux(NAME)`` terms.
    """
    t = np.asarray(t, float) - float(t[0])
    env = {"t": t, "accel": None if accel is None else np.asarray(accel, float), "aux_s": {}}
    for name, e in dev.get("aux", {}).items():
        if aux is None or name not in aux:
            raise ValueError(f"the calibration needs extra column {name!r}")
        x = np.clip(np.asarray(aux[name], float), *e["range"])
        env["aux_s"][name] = (x - e["centre"]) / e["scale"]
    if temp is not None:
        raw = np.asarray(temp, float)
        lo, hi = dev.get("temp_range") or (-np.inf, np.inf)
        clamped = np.clip(raw, lo, hi)
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
        half = max(1, int(np.round(0.5 * dtemp_window / dt)))
        dtemp = local_slope(t, raw, half)
        env.update(temp=clamped, temp_raw=raw, temp_ext=None if temp_ext is None else
                   np.asarray(temp_ext, float),
                   temp_s=(clamped - dev["temp_centre"]) / dev["temp_scale"],
                   dtemp=dtemp, heating=latched_heating(dtemp))
    return env


def _device(calibration: dict, device: str) -> dict:
    """The file's entry of ``device`` (a ValueError naming it where absent)."""
    for d in calibration["devices"]:
        if d["device"] == device:
            return d
    raise ValueError(f"device {device!r} is not in the calibration")


#: Terms (and ``term(...)`` signals) that read the reference input: a rate on the gyro,
#: gravity on the accelerometer's faces.
_INPUT_TERMS = {"scale_poly", "scale_asym", "scale_nonlin", "misalignment"}
_INPUT_SIGNALS = {"rx", "ry", "rz", "w"}


def reads_input(spec: str) -> bool:
    """Whether the model ``spec`` reads the reference input (rate, or gravity on a face).

    **Arguments:**

    - ``spec``: the model's spec, as the calibration file holds it.
    """
    for name, k in _terms(spec):
        if name in _INPUT_TERMS or (name == "term" and any(f[0] in _INPUT_SIGNALS for f in k)):
            return True
    return False


def compensate_accel(calibration: dict, device: str, t, accel, temp=None, temp_ext=None,
                     iterations: int = 4, aux=None) -> np.ndarray:
    """Corrected accelerometer (n, 3), m/s², from measured ``accel`` (n, 3) with a parsed
    accelerometer calibration file (the module docstring: the specific force where the
    calibration read several orientations, the reading at ``temp_centre`` where one).

    **Arguments:**

    - ``calibration``: the accelerometer calibration file as a dict (``json.load``).
    - ``device``: the device's id in the file.
    - ``t``: sample times (n,), s.
    - ``accel``: the measured specific force (n, 3), m/s².
    - ``temp``: die temperature (n,), °C, where a term reads it.
    - ``temp_ext``: external temperature (n,), °C, for ``temp_diff``.
    - ``iterations``: Newton steps that invert the input-dependent terms.
    - ``aux``: extra column names to samples (n,), for ``aux(NAME)`` terms.
    """
    if calibration.get("channel", "gyro") != "accel":
        raise ValueError("not an accelerometer calibration (its channel is "
                         f"{calibration.get('channel', 'gyro')!r})")
    spec = calibration["model"]
    if reads_input(spec):
        return compensate(calibration, device, t, accel, temp, temp_ext, None, iterations, aux)
    dev = _device(calibration, device)
    beta = np.asarray(dev["beta"], float)
    acc = np.asarray(accel, float)
    env = environment(dev, t, temp, temp_ext, None, calibration.get("dtemp_window", 60.0), aux)
    offset = np.einsum("nip,ip->ni", columns(spec, dev, np.zeros_like(acc), env), beta)
    centre = np.array([float(dev["temp_centre"])])
    steady = {"t": np.array([np.inf]), "accel": None, "temp": centre, "temp_raw": centre,
              "temp_ext": centre, "temp_s": np.zeros(1), "dtemp": np.zeros(1),
              "heating": np.zeros(1), "aux_s": {k: np.zeros(1) for k in env["aux_s"]}}
    ref = np.einsum("nip,ip->ni", columns(spec, dev, np.zeros((1, 3)), steady), beta)[0]
    return acc - (offset - ref)


def compensate(calibration: dict, device: str, t, gyro, temp=None, temp_ext=None, accel=None,
               iterations: int = 4, aux=None, terms=None) -> np.ndarray:
    """True rate (n, 3) from the measured gyro with a parsed calibration file.

    **Arguments:**

    - ``calibration``: the calibration file as a dict (``json.load``).
    - ``device``: the device's id in the file.
    - ``t``: sample times (n,), s.
    - ``gyro``: the measured rate (n, 3), rad/s.
    - ``temp``: die temperature (n,), °C, where a term reads it.
    - ``temp_ext``: external temperature (n,), °C, for ``temp_diff``.
    - ``accel``: specific force (n, 3), m/s², for ``g_sens`` and accelerometer signals.
    - ``iterations``: Newton steps that invert the rate-dependent terms.
    - ``aux``: extra column names to samples (n,), for ``aux(NAME)`` terms.
    - ``terms``: term names to the numpy columns of terms registered outside diffgyro.
    """
    dev = _device(calibration, device)
    spec = calibration["model"]
    beta = np.asarray(dev["beta"], float)
    env = environment(dev, t, temp, temp_ext, accel, calibration.get("dtemp_window", 60.0), aux)
    gyro = np.asarray(gyro, float)

    kept: dict = {}  # the columns that do not read the rate, built at the first step

    def err(omega):
        return np.einsum("nip,ip->ni", columns(spec, dev, omega, env, terms, kept), beta)

    omega = gyro - err(np.zeros_like(gyro))
    eps = 1e-7
    for _ in range(iterations):
        f = omega + err(omega) - gyro
        jac = np.empty(gyro.shape + (3,))
        for k in range(3):  # finite-difference Jacobian per sample (terms act sample-wise)
            step = np.zeros_like(omega)
            step[:, k] = eps * np.maximum(1.0, np.abs(omega[:, k]))
            jac[:, :, k] = (omega + step + err(omega + step) - gyro - f) / step[:, k:k + 1]
        omega = omega - np.linalg.solve(jac, f[..., None])[..., 0]
    return omega
