"""Recordings with hidden effects (one, or several joined by ``+``), made independently of ``diffgyro.simulate``.

The diagnosis must hold on data the project did not simulate, so these
recordings come from separate, deliberately plain numpy code: three test
plans (thermal chamber, rate table, multi-position), a die temperature that
lags the chamber and self-heats after power-on, a temperature read-out that
lags the die and is quantised, gyro noise with white, flicker (sum of
Gauss–Markov processes) and random-walk parts plus output quantisation, and
every effect written from its physics (dT/dt of the die, die minus air
temperature, a latched heating state, ...), not from the library's regressor
columns. Only the *size* of a hidden effect is set with the library: the
effect is scaled so that what the base model cannot absorb (its least-squares
residual against the base design) has a chosen RMS relative to the white
noise σ, which is what decides whether it can be seen at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import lfilter

from diffgyro.data import Recording

DEG = math.pi / 180.0
G = 9.80665
EARTH = 7.292115e-5


@dataclass(frozen=True)
class Noise:
    """Gyro and temperature noise of one recording.

    ``white`` σ per sample (rad/s); ``flicker`` bias instability B relative to
    ``white``; ``drift`` the random walk's spread over the record (K·√T)
    relative to ``white``; ``quantum`` output LSB relative to ``white``;
    ``temp_quantum`` °C read-out step; ``readout_lag`` s of the temperature
    read-out behind the die.
    """

    white: float = 2.5e-4
    flicker: float = 0.1
    drift: float = 0.15
    quantum: float = 0.0
    temp_noise: float = 0.01
    temp_quantum: float = 0.0
    readout_lag: float = 5.0
    lowpass: float = 0.0     # lag-1 correlation of the white noise (an internal low-pass filter)


def draw_noise(rng: np.random.Generator) -> Noise:
    """Varied, realistic noise settings (not the simulator's defaults)."""
    return Noise(
        white=float(np.exp(rng.uniform(np.log(8e-5), np.log(1e-3)))),
        flicker=float(rng.uniform(0.0, 0.25)),
        drift=float(rng.uniform(0.0, 0.3)),
        quantum=float(rng.choice([0.0, 0.0, 0.3, 0.7])),
        temp_noise=float(rng.uniform(0.0, 0.05)),
        temp_quantum=float(rng.choice([0.0, 0.01, 0.1, 0.5, 1.0])),
        readout_lag=float(rng.uniform(0.0, 10.0)),
    )


# --------------------------------------------------------------------------- plans


def _lag(u: np.ndarray, tau: float, dt: float, y0: float | None = None) -> np.ndarray:
    """First-order lag, exact for ``u`` held between samples."""
    a = math.exp(-dt / tau)
    y0 = u[0] if y0 is None else y0
    y, _ = lfilter([1.0 - a], [1.0, -a], u, zi=[a * y0])
    return y


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


@dataclass
class Plan:
    """A test plan on a uniform grid: chamber air temperature, power, body rate and
    the rotation body→level frame (for gravity and Earth rate)."""

    t: np.ndarray
    chamber: np.ndarray
    power: np.ndarray
    rate: np.ndarray          # (n, 3) true body rate from the motion (rad/s)
    attitude: np.ndarray      # (n, 3, 3) body -> level frame (z up)
    has_rate: bool


def thermal_plan(rng: np.random.Generator, fs: float = 2.0, hours: float = 3.0) -> Plan:
    """Static device in a chamber: soak, cool, soak, heat, soak, cool back, soak to the end,
    with a power-level change in the middle (separates temp_diff from gradient)."""
    r = rng.uniform(0.7, 2.0) / 60.0  # °C/s
    start = rng.uniform(20, 30)
    lo = start - rng.uniform(15, 30)
    hi = start + rng.uniform(15, 30)
    total = hours * 3600.0
    pts = [(0.0, start)]
    t = rng.uniform(600, 1200)
    pts.append((t, start))
    cur = start
    for target in (lo, hi, start):
        t += abs(target - cur) / r
        pts.append((t, target))
        t += rng.uniform(1200, 2400)
        pts.append((t, target))
        cur = target
    pts = [(a * min(1.0, 0.95 * total / t), b) for a, b in pts]  # squeeze only if too long
    pts.append((total + 1.0, pts[-1][1]))
    n = int(total * fs)
    tt = np.arange(n) / fs
    chamber = np.interp(tt, [p[0] for p in pts], [p[1] for p in pts])
    power = np.ones(n)
    step_at = rng.uniform(0.35, 0.65) * total
    power[tt >= step_at] = rng.uniform(0.3, 0.7)  # a power-level change (separates temp_diff)
    att = np.broadcast_to(_rot(rng.normal(size=3), rng.uniform(0, 0.2)), (n, 3, 3)).copy()
    return Plan(tt, chamber, power, np.zeros((n, 3)), att, has_rate=bool(rng.uniform() < 0.5))


def _spin_profile(n_plateau: float, rate: float, acc: float, fs: float):
    ramp = abs(rate) / acc
    tt = np.arange(int((2 * ramp + n_plateau) * fs)) / fs
    prof = np.minimum(np.minimum(tt / ramp, 1.0), np.maximum((2 * ramp + n_plateau - tt) / ramp, 0.0))
    return rate * np.clip(prof, 0.0, 1.0)


def rate_table_plan(rng: np.random.Generator, fs: float = 2.0, hours: float = 2.0) -> Plan:
    """Single-axis table; the device is remounted with each axis on the spin axis in turn
    and spun at ± a ladder of rates; room temperature with self-heating."""
    rates = np.array([2, 5, 10, 20, 50, 100, 150, 200, 300]) * DEG
    acc = 100 * DEG
    plateau = rng.uniform(30, 50)
    stop = rng.uniform(10, 20)
    segs_rate, segs_att = [], []
    mounts = [np.eye(3), _rot([1, 0, 0], -math.pi / 2), _rot([0, 1, 0], math.pi / 2)]
    # mount k puts body axis k on the table's (vertical) spin axis
    total = hours * 3600.0
    t = 0.0
    k = 0
    while t < total:
        m = mounts[k % 3]
        axis_body = m.T @ np.array([0.0, 0.0, 1.0])
        for r in rng.permutation(np.concatenate([rates, -rates])):
            prof = _spin_profile(plateau, r, acc, fs)
            prof = np.concatenate([prof, np.zeros(int(stop * fs))])
            segs_rate.append(prof[:, None] * axis_body[None, :])
            segs_att.append(np.broadcast_to(m, (len(prof), 3, 3)))
            t += len(prof) / fs
        k += 1
    rate = np.concatenate(segs_rate)
    att = np.concatenate(segs_att)
    n = int(total * fs)
    rate, att = rate[:n], att[:n]
    if len(rate) < n:
        n = len(rate)
    tt = np.arange(n) / fs
    room = rng.uniform(18, 28) + rng.uniform(-1.5, 1.5) * np.sin(2 * math.pi * tt / rng.uniform(4e3, 2e4))
    return Plan(tt, room, np.ones(n), rate, att, has_rate=True)


def multi_position_plan(rng: np.random.Generator, fs: float = 2.0, hours: float = 2.0) -> Plan:
    """Static in 24 orientations (6 faces × 4 headings), turned between them at a known rate."""
    faces = [np.eye(3), _rot([1, 0, 0], math.pi), _rot([1, 0, 0], math.pi / 2),
             _rot([1, 0, 0], -math.pi / 2), _rot([0, 1, 0], math.pi / 2), _rot([0, 1, 0], -math.pi / 2)]
    tilt = _rot(rng.normal(size=3), rng.uniform(0, 0.01))  # the table is not level
    total = hours * 3600.0
    hold = total / 24.0 - 10.0
    turn_rate = rng.uniform(20, 40) * DEG
    rates, atts = [], []
    for f in rng.permutation(6):
        for h in range(4):
            base = tilt @ _rot([0, 0, 1], h * math.pi / 2) @ faces[f]
            nh = int(hold * fs)
            rates.append(np.zeros((nh, 3)))
            atts.append(np.broadcast_to(base, (nh, 3, 3)))
            # a 90° turn about the level z axis over 10 s, raised cosine
            nt = int(10 * fs)
            s = (np.arange(nt) + 0.5) / nt
            ang = 0.5 * math.pi * 0.5 * (1 - np.cos(math.pi * s))
            dang = 0.5 * math.pi * 0.5 * math.pi / 10.0 * np.sin(math.pi * s)
            axis_body = base.T @ np.array([0.0, 0.0, 1.0])
            rates.append(dang[:, None] * axis_body[None, :])
            atts.append(np.stack([_rot([0, 0, 1], a) @ base for a in ang]))
    del turn_rate
    rate = np.concatenate(rates)
    att = np.concatenate(atts)
    n = len(rate)
    tt = np.arange(n) / fs
    room = rng.uniform(18, 28) + rng.uniform(-1, 1) * tt / tt[-1]
    return Plan(tt, room, np.ones(n), rate, att, has_rate=True)


PLANS = {"thermal": thermal_plan, "rate_table": rate_table_plan, "multi_position": multi_position_plan}


# --------------------------------------------------------------------------- physics


def _heating_state(dtemp: np.ndarray, threshold: float = 0.05 / 60.0) -> np.ndarray:
    state = np.zeros_like(dtemp)
    cur = 0.0
    for i, d in enumerate(dtemp):
        if d > threshold:
            cur = 1.0
        elif d < -threshold:
            cur = -1.0
        state[i] = cur
    first = np.flatnonzero(state)
    if first.size:
        state[: first[0]] = state[first[0]]
    return state


def effect_signal(name: str, rng: np.random.Generator, env: dict) -> np.ndarray:
    """An (n, 3) error pattern of effect ``name`` with random unit-scale coefficients."""
    n = env["t"].shape[0]
    c = rng.normal(size=3) * rng.choice([-1, 1], size=3)
    dT = (env["die"] - 25.0) / 40.0
    if name == "bias_poly":          # curvature beyond a quadratic base polynomial
        return np.outer(dT**3, c)
    if name == "gradient":
        return np.outer(env["ddie"] * 60.0, c)
    if name == "temp_diff":
        return np.outer(env["die"] - env["air"], c)
    if name == "thermal_lag":        # bias follows the die seen through another lag
        tau = rng.uniform(150, 900)
        return np.outer((_lag(env["die"], tau, env["dt"]) - env["die"]) / 10.0, c)
    if name == "hysteresis":
        return np.outer(_heating_state(env["ddie"]), c)
    if name == "warmup":
        tau = rng.uniform(60, 900)
        return np.outer(np.exp(-env["t"] / tau), c)
    if name == "scale_poly":
        return env["rate"] * c[None, :]
    if name == "scale_asym":
        return np.abs(env["rate"]) * c[None, :]
    if name == "scale_nonlin":
        return env["rate"] ** 3 * c[None, :]
    if name == "misalignment":
        m = rng.normal(size=(3, 3))
        np.fill_diagonal(m, 0.0)
        return env["rate"] @ m.T
    if name == "g_sens":
        return env["force"] @ rng.normal(size=(3, 3)).T
    if name == "vdd":                # bias follows the logged supply voltage
        return np.outer((env["vdd"] - 5.0) / 0.05, c)
    if name == "temp_x_dtemp":       # outside the vocabulary: a gradient sensitivity ∝ T
        return np.outer((env["die"] - env["die"].mean()) / 20.0 * env["ddie"] * 60.0, c)
    if name == "heater_lag":         # outside the vocabulary: a logged heater through its own lag
        return np.outer(_lag(env["heater"], 300.0, env["dt"]), c)
    if name == "temp_x_vdd":         # outside the vocabulary: supply sensitivity ∝ temperature
        return np.outer((env["die"] - env["die"].mean()) / 20.0 * (env["vdd"] - 5.0) / 0.05, c)
    if name == "sin_duty":           # outside the vocabulary: a periodic function of a column
        return np.outer(np.sin(2.0 * math.pi * 2.5 * env["duty"]), c)
    if name == "random_walk":
        steps = rng.normal(size=(n, 3))
        steps[0] = 0.0
        return np.cumsum(steps, axis=0)
    raise ValueError(name)


def supply_voltage(t: np.ndarray, seed: int) -> np.ndarray:
    """A logged 5 V supply, independent of the temperatures (a stream of its own): a
    low-passed wander, load steps and a little read-out noise."""
    rng = np.random.default_rng([seed, 5005])
    n = t.shape[0]
    dt = float(t[1] - t[0])
    wander = _lag(np.cumsum(rng.normal(size=n)) * math.sqrt(dt), 600.0, dt, y0=0.0)
    wander *= 0.03 / max(np.std(wander), 1e-12)
    steps = np.zeros(n)
    for at in rng.uniform(t[0], t[-1], 5):
        steps[t >= at] += rng.choice([-1.0, 1.0]) * rng.uniform(0.01, 0.03)
    return 5.0 + wander + steps - steps.mean() + rng.normal(size=n) * 5e-4


def duty_cycle(t: np.ndarray, seed: int) -> np.ndarray:
    """A logged heater or fan duty in [0, 1]: levels held for about 20 s each (a stream of
    its own, independent of the temperatures)."""
    rng = np.random.default_rng([seed, 7007])
    dt = float(t[1] - t[0])
    hold = np.maximum(1, rng.exponential(20.0 / dt, size=t.shape[0]).astype(int))
    levels = np.repeat(rng.uniform(0.0, 1.0, size=hold.size), hold)
    return levels[: t.shape[0]]


def _flicker(n: int, dt: float, rng: np.random.Generator) -> np.ndarray:
    """Unit bias instability: sum of Gauss–Markov processes, two per decade."""
    r = math.sqrt(10.0)
    var = math.log(r) / (2 * math.pi)
    out = np.zeros((n, 3))
    tau = 2 * dt
    while tau < 3 * n * dt:
        a = math.exp(-dt / tau)
        x0 = rng.normal(size=3) * math.sqrt(var)
        for k in range(3):
            e = rng.normal(size=n) * math.sqrt(var * (1 - a * a))
            out[:, k] += lfilter([1.0], [1.0, -a], e, zi=[a * x0[k]])[0]
        tau *= r
    return out


@dataclass
class Hidden:
    recording: Recording
    effect: str | None
    plan: str
    noise: Noise
    size: float          # RMS of the hidden effect's unabsorbed part / white σ
    truth_error: np.ndarray  # the full deterministic error (n, 3)
    hidden: np.ndarray       # the hidden effect alone (n, 3)
    env: dict                # die and air temperature, true dT/dt, rates, force
    noise_rms: float = 0.0   # RMS of all the gyro noise added (white, flicker, walk, LSB), mean removed


def make_recording(plan: str, effect: str | None, base_spec: str, seed: int, *,
                   size: float = 1.0, noise: Noise | None = None, fs: float = 2.0,
                   hours: float | None = None, earth_in_reference: bool = True,
                   device: str | None = None) -> Hidden:
    """One device on ``plan`` whose errors are those of ``base_spec`` plus ``effect``.

    The hidden effect is scaled so the part the base model cannot absorb has
    RMS ``size × noise.white``. Effect ``"vdd"`` is a bias that follows a logged
    supply voltage, recorded as the extra column ``vdd``. Several effects joined
    by ``+`` (``"gradient+bias_poly"``) are hidden together, each scaled so on its
    own; ``"temp_x_dtemp"`` (bias ∝ T·dT/dt of the die), ``"sin_duty"`` (bias ∝
    sin(5π·duty) of a logged duty column ``duty``), ``"heater_lag"`` (a logged heater
    column ``heater`` through a 300 s first-order lag) and ``"temp_x_vdd"`` (bias ∝ die
    temperature × the logged supply ``vdd``) are outside every built-in term.
    """
    from diffgyro.data import Batch
    from diffgyro.internal import batch_signals
    from diffgyro.model import ErrorModel

    rng = np.random.default_rng(seed)
    noise = noise or Noise()
    kw = {} if hours is None else {"hours": hours}
    p = PLANS[plan](rng, fs=fs, **kw)
    n, dt = p.t.shape[0], 1.0 / fs
    # die temperature: chamber + self-heating after power-on (device starts cold), lagged
    heat = rng.uniform(2.0, 6.0) * _lag(p.power, rng.uniform(400, 1000), dt, y0=0.0)
    die = _lag(p.chamber + heat, rng.uniform(150, 600), dt, y0=p.chamber[0])
    ddie = np.gradient(die, dt)
    readout = _lag(die, noise.readout_lag, dt) if noise.readout_lag > 0 else die
    temp = readout + rng.normal(size=n) * noise.temp_noise
    if noise.temp_quantum > 0:
        temp = np.round(temp / noise.temp_quantum) * noise.temp_quantum
    air = p.chamber + rng.normal(size=n) * 0.02
    force = np.einsum("nji,j->ni", p.attitude, np.array([0.0, 0.0, G]))
    earth_level = EARTH * np.array([math.cos(0.8), 0.0, math.sin(0.8)])
    earth = np.einsum("nji,j->ni", p.attitude, earth_level)
    true_rate = p.rate + earth
    env = {"t": p.t, "dt": dt, "die": die, "ddie": ddie, "air": air, "rate": true_rate,
           "force": force}
    aux = {}
    if {"vdd", "temp_x_vdd"} & set((effect or "").split("+")):
        env["vdd"] = aux["vdd"] = supply_voltage(p.t, seed)
    if "heater_lag" in (effect or "").split("+"):  # heater levels held about 10 min
        held = duty_cycle(p.t[::30], seed)
        env["heater"] = aux["heater"] = np.repeat(held, 30)[: p.t.shape[0]]
    if "sin_duty" in (effect or "").split("+"):
        env["duty"] = aux["duty"] = duty_cycle(p.t, seed)

    # the base model's errors, with realistic coefficients (fitted exactly by the base model)
    base = np.zeros((n, 3))
    dT = (die - 25.0) / 40.0
    specs = base_spec.split("+")
    for s in specs:
        name = s.split("(")[0]
        order = int(s.split("(")[1].rstrip(")")) if "(" in s else None
        if name == "bias_poly":
            cs = rng.normal(size=(order + 1, 3)) * np.array([5e-3, 5e-3, 1e-3, 5e-4, 2e-4][: order + 1])[:, None]
            base += sum(np.outer(dT**j, cs[j]) for j in range(order + 1))
        elif name == "scale_poly":
            cs = rng.normal(size=(order + 1, 3)) * np.array([1e-3, 2e-4, 1e-4][: order + 1])[:, None]
            base += sum(true_rate * (dT**j)[:, None] * cs[j] for j in range(order + 1))
        elif name == "misalignment":
            m = rng.normal(size=(3, 3)) * 1e-3
            np.fill_diagonal(m, 0.0)
            base += true_rate @ m.T
        elif name == "g_sens":
            base += force @ (rng.normal(size=(3, 3)).T * 1e-5)
        elif name in ("gradient", "temp_diff", "hysteresis", "warmup", "thermal_lag",
                      "scale_asym", "scale_nonlin"):
            base += effect_signal(name, rng, env) * 2e-4
        else:
            raise ValueError(s)

    rate_ref = p.rate + (earth if earth_in_reference else 0.0)
    gyro_clean = true_rate + base
    rec0 = Recording(t=p.t, gyro=gyro_clean, temp=temp, temp_ext=air, accel=force + rng.normal(size=(n, 3)) * 2e-3,
                     rate=rate_ref if p.has_rate else None, device=device or f"{plan}-{effect}-{seed}",
                     aux=aux)
    hidden = np.zeros((n, 3))
    for name in (effect.split("+") if effect is not None and size > 0 else ()):
        pattern = effect_signal(name, rng, env)
        # part of the pattern the base model cannot absorb, in principle: the base design
        # evaluated on the true die temperature (read-out lag and steps are extra)
        true_rec = Recording(t=p.t, gyro=gyro_clean, temp=die, temp_ext=p.chamber, accel=force,
                             rate=true_rate if p.has_rate else None)
        sig = batch_signals(Batch.from_recordings([true_rec], bucket=False))
        sig1 = __import__("jax").tree.map(lambda a: a[0] if hasattr(a, "ndim") and a.ndim else a, sig)
        x = np.asarray(ErrorModel.from_spec(base_spec).design(sig1, np.zeros(0)))
        resid = np.empty_like(pattern)
        for i in range(3):
            coef, *_ = np.linalg.lstsq(x[:, i, :], pattern[:, i], rcond=None)
            resid[:, i] = pattern[:, i] - x[:, i, :] @ coef
        rms = math.sqrt(np.mean(resid**2))
        if rms < 0.05 * math.sqrt(np.mean(pattern**2)):
            raise ValueError(f"{name} is almost absorbed by {base_spec} on this plan")
        hidden += pattern * (size * noise.white / max(rms, 1e-300))
    # noise
    white = rng.normal(size=(n, 3)) * noise.white
    if noise.lowpass > 0:  # MA(1) with lag-1 correlation ρ, same variance
        a = (1 - math.sqrt(max(1 - 4 * noise.lowpass**2, 0.0))) / (2 * noise.lowpass)
        white = (white + a * np.roll(white, 1, axis=0)) / math.sqrt(1 + a * a)
    fl = _flicker(n, dt, rng) * noise.flicker * noise.white if noise.flicker > 0 else 0.0
    total_t = n * dt
    steps = rng.normal(size=(n, 3)) * (noise.drift * noise.white / math.sqrt(total_t)) * math.sqrt(dt)
    steps[0] = 0.0
    gyro = gyro_clean + hidden + white + fl + np.cumsum(steps, axis=0)
    if noise.quantum > 0:
        lsb = noise.quantum * noise.white
        gyro = np.round(gyro / lsb) * lsb
    rec = replace_recording(rec0, gyro)
    added = gyro - (gyro_clean + hidden)
    noise_rms = float(np.sqrt(np.mean(np.var(added, axis=0))))
    return Hidden(rec, effect, plan, noise, size, base + hidden, hidden, env, noise_rms)


def replace_recording(rec: Recording, gyro: np.ndarray) -> Recording:
    return Recording(t=rec.t, gyro=gyro, temp=rec.temp, temp_ext=rec.temp_ext, accel=rec.accel,
                     rate=rec.rate, device=rec.device, source=rec.source, aux=rec.aux)


__all__ = ["Hidden", "Noise", "PLANS", "draw_noise", "duty_cycle", "effect_signal", "make_recording",
           "replace", "supply_voltage"]
