"""The simulator's gyro output against the physics of DESIGN §1–2 written out here in numpy.

The simulator builds each device's deterministic error with the fitter's own ``model.error``,
so a fit test cannot see a wrong term: the fit and the data would share it. Here the
recorded rates of a noise-free rate-table run (turns about every axis in both directions,
faces changing the specific force, temperature ramps down and up with soaks) are compared
with each term's formula written from the design text, using only the true signals the
simulator keeps (``keep_components``) and coefficients set by the test:

    ω_meas_i = Ω_i + Σ_terms  (per axis i; Ts = (T − centre)/scale, T the sensor temperature)

    bias_poly(k)    Σ_j c_ij Ts^j                       scale_poly(k)  Ω_i Σ_j s_ij Ts^j
    scale_asym      a_i |Ω_i|                           scale_nonlin   n_i Ω_i³
    misalignment    m_i1 Ω_first + m_i2 Ω_second (the other two axes in x, y, z order)
    g_sens          Σ_j g_ij f_j  (specific force)      gradient       g_i dT/dt
    temp_diff       d_i (T − T_ext)                     hysteresis     h_i · (+1 heated / −1 cooled last)
    thermal_lag(k)  Σ_j l_ij (Tlag_s^j − Ts^j), τ·dTlag/dt = T − Tlag, settled at the start
    warmup          w_i exp(−t/τ)                       aux(x,k)       Σ_{j=1..k} a_ij x_s^j

The random walk is checked on its own: increments of variance K²·dt, uncorrelated.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.stats

from diffgyro.model import ErrorModel, Params
from diffgyro.simulate import simulate

EXACT = ("bias_poly(2)+scale_poly(1)+scale_asym+scale_nonlin+misalignment+g_sens+gradient+"
         "temp_diff+hysteresis+warmup+aux(vdd,2)")
PLAN = {"temps": (20.0, 0.0, 40.0), "rates": (30.0, 300.0), "settle": 5.0, "sample_rate": 2.0}
#: Each term's coefficients (3 axes × its columns), sized so every term moves the output by
#: about 1e-3 rad/s or more (Ts within ±0.5, |Ω| ≤ 5.2 rad/s, |f| = 9.8 m/s², dT/dt ≤ 0.017 °C/s).
COEFFS = {
    "bias_poly": [[2e-3, 3e-3, -1e-3], [-1e-3, 4e-3, 2e-3], [1.5e-3, -2e-3, 3e-3]],
    "scale_poly": [[1e-3, 2e-3], [-2e-3, 1e-3], [3e-3, -1e-3]],
    "scale_asym": [[5e-4], [-7e-4], [6e-4]],
    "scale_nonlin": [[2e-5], [-3e-5], [1e-5]],
    "misalignment": [[1e-3, -2e-3], [3e-3, 1e-3], [-1e-3, 2e-3]],
    "g_sens": [[1e-4, -2e-4, 3e-4], [2e-4, 1e-4, -1e-4], [-3e-4, 2e-4, 1e-4]],
    "gradient": [[0.1], [-0.2], [0.15]],
    "temp_diff": [[2e-4], [-3e-4], [1e-4]],
    "hysteresis": [[1e-3], [-2e-3], [1.5e-3]],
    "warmup": [[4e-3], [-3e-3], [2e-3]],
    "aux": [[1e-3, 5e-4], [-2e-3, 1e-3], [1.5e-3, -1e-3]],
    "thermal_lag": [[2e-2, 1e-2], [-1e-2, 2e-2], [1.5e-2, -2e-2]],
}
LOG_TAU = {"thermal_lag": math.log(400.0), "warmup": math.log(120.0)}
HEATING = 0.05 / 60.0  # °C/s: the hysteresis latch's threshold


def _params(spec: str) -> Params:
    model = ErrorModel.from_spec(spec)
    beta = np.concatenate([np.asarray(COEFFS[t.name], float) for t in model.terms], axis=1)
    theta = np.array([LOG_TAU[t.name] for t in model.terms if t.n_nonlinear])
    return Params(beta=beta, theta=theta)


def _run(spec: str):
    batch, truth = simulate("rate_table", 1, effects=spec, seed=4, noise="none",
                            keep_components=True, params=_params(spec), **PLAN)
    e = truth.env
    n = e["t"].size
    sig = {"t": e["t"], "T": e["temp"][0], "dT": e["dtemp"][0], "T_ext": np.asarray(e["chamber"]),
           "f": e["specific_force"][0], "w": e["rate"][0],
           "Ts": (e["temp"][0] - truth.norm.centre) / truth.norm.scale}
    for name, nm in truth.aux_norm.items():
        sig["aux:" + name] = (np.asarray(batch.aux[name][0, :n]) - nm.centre) / nm.scale
    gyro = np.asarray(batch.gyro[0, :n])
    return gyro, sig, truth


def _latched(dT: np.ndarray) -> np.ndarray:
    """+1 after the last |dT/dt| > threshold while heating, −1 while cooling; before the first
    such sample, the first state seen."""
    state = np.zeros_like(dT)
    active = np.flatnonzero(np.abs(dT) > HEATING)
    current = np.sign(dT[active[0]]) if active.size else 0.0
    for k in range(dT.size):
        if abs(dT[k]) > HEATING:
            current = np.sign(dT[k])
        state[k] = current
    return state


def _lag(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    """τ·dy/dt = x − y, y(0) = x(0), solved exactly for x linear between samples."""
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, x.size):
        h = t[k] - t[k - 1]
        s = (x[k] - x[k - 1]) / h
        e = math.exp(-h / tau)
        y[k] = x[k] - s * tau + (y[k - 1] - x[k - 1] + s * tau) * e
    return y


def _term(name: str, c: np.ndarray, sig: dict, norm, aux: str = "aux:vdd") -> np.ndarray:
    """One term's error (n, 3) from its coefficients c (3, p)."""
    w, ts = sig["w"], sig["Ts"]
    powers = np.stack([ts**j for j in range(c.shape[1])], axis=1)  # (n, p): 1, Ts, Ts², ...
    one = np.ones((1, 3))
    if name == "bias_poly":
        return powers @ c.T
    if name == "scale_poly":
        return w * (powers @ c.T)
    if name == "scale_asym":
        return c[:, 0] * np.abs(w)
    if name == "scale_nonlin":
        return c[:, 0] * w**3
    if name == "misalignment":
        others = {0: (1, 2), 1: (0, 2), 2: (0, 1)}
        return np.stack([c[i, 0] * w[:, a] + c[i, 1] * w[:, b] for i, (a, b) in others.items()], 1)
    if name == "g_sens":
        return sig["f"] @ c.T
    if name == "gradient":
        return sig["dT"][:, None] * c[:, 0] * one
    if name == "temp_diff":
        return (sig["T"] - sig["T_ext"])[:, None] * c[:, 0] * one
    if name == "hysteresis":
        return _latched(sig["dT"])[:, None] * c[:, 0] * one
    if name == "warmup":
        return np.exp(-(sig["t"] - sig["t"][0]) / math.exp(LOG_TAU["warmup"]))[:, None] * c[:, 0] * one
    if name == "aux":
        x = sig[aux]
        return np.stack([x ** (j + 1) for j in range(c.shape[1])], axis=1) @ c.T
    if name == "thermal_lag":
        lag_s = (_lag(sig["t"], sig["T"], math.exp(LOG_TAU["thermal_lag"])) - norm.centre) / norm.scale
        return np.stack([lag_s ** (j + 1) - ts ** (j + 1) for j in range(c.shape[1])], axis=1) @ c.T
    raise AssertionError(name)


def test_every_exact_term_against_its_formula():
    """Eleven terms at once: the recording equals Ω plus the formulas to rounding, and each
    term moves the output well above that (a term the simulator dropped or changed fails)."""
    gyro, sig, truth = _run(EXACT)
    model = ErrorModel.from_spec(EXACT)
    parts = {t.name: _term(t.name, np.asarray(COEFFS[t.name], float), sig, truth.norm)
             for t in model.terms}
    for name, part in parts.items():
        assert np.abs(part).max() > 5e-4, name
    want = sig["w"] + sum(parts.values())
    np.testing.assert_allclose(gyro, want, rtol=0, atol=1e-11)


def test_thermal_lag_against_the_differential_equation():
    """The lag term against τ·dTlag/dt = T − Tlag solved for a temperature linear between
    samples; the simulator's discrete lag may differ by the hold of one sample (dt/τ)."""
    gyro, sig, truth = _run("thermal_lag(2)")
    want = _term("thermal_lag", np.asarray(COEFFS["thermal_lag"], float), sig, truth.norm)
    got = gyro - sig["w"]
    size = np.abs(want).max()
    assert size > 1e-3
    dt_over_tau = (sig["t"][1] - sig["t"][0]) / math.exp(LOG_TAU["thermal_lag"])
    assert np.abs(got - want).max() < 2 * dt_over_tau * size
    # a lag of 10 % longer or shorter is far outside that
    for factor in (0.9, 1.1):
        tau = math.exp(LOG_TAU["thermal_lag"]) * factor
        lag_s = (_lag(sig["t"], sig["T"], tau) - truth.norm.centre) / truth.norm.scale
        ts = sig["Ts"]
        other = np.stack([lag_s - ts, lag_s**2 - ts**2], 1) @ np.asarray(COEFFS["thermal_lag"]).T
        assert np.abs(got - other).max() > 20 * np.abs(got - want).max()


def test_random_walk_increments():
    """The bias random walk: increments N(0, K²·dt), independent; two-sided 99.9 % bounds."""
    k, dt = 2e-5, 0.5
    batch, truth = simulate("static", 2, effects="bias_poly(0)+random_walk", seed=9,
                            noise={"arw": 0.0, "rrw": k, "bias_instability": 0.0, "quantum": 0.0},
                            params=Params(beta=np.zeros((3, 1)), theta=np.zeros(0)),
                            sample_rate=1 / dt, duration=4000.0, keep_components=True)
    n = int(batch.n_valid[0])
    walk = np.asarray(batch.gyro[:, :n])  # noise-free but for the walk, zero bias, no rate
    steps = np.diff(walk, axis=1).reshape(-1)
    m = steps.size
    var = np.var(steps, ddof=0) * m / (m - 1)
    lo, hi = scipy.stats.chi2.ppf([5e-4, 1 - 5e-4], m - 1) / (m - 1)
    assert lo < var / (k * k * dt) < hi, var / (k * k * dt)
    r1 = np.corrcoef(steps[:-1], steps[1:])[0, 1]
    assert abs(r1) < 3.3 / math.sqrt(m)
    assert np.abs(walk[:, 0]).max() < 5 * k * math.sqrt(dt)  # it starts from zero


def test_formulas_catch_a_wrong_coefficient():
    """The comparison is sharp: the same recording against a formula with one coefficient off."""
    gyro, sig, truth = _run(EXACT)
    coeffs = {k: np.asarray(v, float) for k, v in COEFFS.items()}
    coeffs["gradient"] = coeffs["gradient"] * 2.0
    model = ErrorModel.from_spec(EXACT)
    want = sig["w"] + sum(_term(t.name, coeffs[t.name], sig, truth.norm) for t in model.terms)
    assert np.abs(gyro - want).max() > 1e-4
