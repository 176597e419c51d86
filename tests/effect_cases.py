"""How the tests exercise each registered effect, read from the effect registry: the fit,
apply-parity and calibration-file tests parametrise over :func:`cases`, so a term
registered with ``@register`` (built in, or a user's, as the README shows) is covered by
them without editing them.

A built-in term has a hand-tuned entry in :data:`BUILT_IN` (the plan that excites it, the
terms beside it, its spec alone, its time constants). Any other registered effect gets a
case derived from its class (:func:`derived_case`): the simulator plan that excites the data
it ``requires``, a bias polynomial beside it, and a true coefficient that the simulator
cannot draw (it has no population for the term) sized here against the white noise
(:func:`simulate_case`). Its numpy form for ``diffgyro.apply`` is what the class declares
in ``numpy_columns`` (None: apply-parity checks that apply refuses it by name).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import numpy as np

from diffgyro.effects import AbstractEffect, registry, spec_arguments
from diffgyro.internal import batch_signals
from diffgyro.model import ErrorModel, Params
from diffgyro.simulate import simulate

#: White gyro noise only: recovery is judged against honest standard errors.
WHITE = {"rrw": 0.0, "bias_instability": 0.0, "quantum": 0.0}
#: log τ of a time constant in apply-parity's calibration files (thermal lag 300 s).
LOG_TAU = math.log(300.0)
#: A derived case's true coefficient moves the gyro by this many white-noise σ (RMS).
SIGNAL_TO_NOISE = 30.0


@dataclass(frozen=True)
class EffectCase:
    """One registered term as the tests exercise it.

    ``fit``: (plan, spec, plan options) of simulated data the fit must recover the truth
    from, or None where another test file fits it (``fit_elsewhere`` names it);
    ``alone``: the spec apply-parity and calibration files try the term with;
    ``theta``: log τ of each of the term's time constants there;
    ``numpy``: the numpy columns apply.py is given for the term (None: apply.py's own
    code for a built-in, or no numpy form declared for another term, see ``built_in``).
    """

    name: str
    fit: tuple[str, str, dict] | None
    alone: str
    theta: tuple[float, ...] = ()
    built_in: bool = True
    numpy: object = None
    fit_elsewhere: str = ""

    @property
    def has_numpy_form(self) -> bool:
        """Whether apply.py can compensate the term: its own code, or a declared form."""
        return self.built_in or self.numpy is not None

    @property
    def apply_terms(self) -> dict:
        """The ``terms=`` argument of ``apply.compensate`` for this term."""
        return {} if self.numpy is None else {self.name: self.numpy}


def _case(name, fit, alone, theta=(), fit_elsewhere=""):
    return EffectCase(name, fit, alone, theta, fit_elsewhere=fit_elsewhere)


#: Every built-in term, tuned by hand: the plan that excites it and the terms it needs
#: beside it (a scale factor needs a bias, hysteresis a temperature polynomial).
BUILT_IN = {c.name: c for c in [
    _case("bias_poly", ("thermal", "bias_poly(3)", {}), "bias_poly(3)"),
    _case("gradient", ("thermal", "bias_poly(2)+gradient", {}), "gradient"),
    _case("temp_diff", ("thermal", "bias_poly(2)+temp_diff", {}), "temp_diff"),
    _case("thermal_lag", ("thermal", "bias_poly(1)+thermal_lag", {}), "thermal_lag(2)",
          (LOG_TAU,)),
    _case("hysteresis", ("thermal", "bias_poly(2)+hysteresis", {}), "hysteresis"),
    _case("warmup", ("warmup", "bias_poly(0)+warmup", {}), "warmup", (math.log(600.0),)),
    _case("scale_poly", ("rate_table", "bias_poly(1)+scale_poly(1)", {}), "scale_poly(2)"),
    _case("scale_asym", ("rate_table", "bias_poly(1)+scale_poly(0)+scale_asym", {}),
          "scale_asym"),
    _case("scale_nonlin", ("rate_table", "bias_poly(1)+scale_poly(0)+scale_nonlin", {}),
          "scale_nonlin"),
    _case("misalignment", ("rate_table", "bias_poly(1)+scale_poly(0)+misalignment", {}),
          "misalignment"),
    _case("g_sens", ("six_face", "bias_poly(0)+g_sens", {"accel_errors": False}), "g_sens"),
    _case("aux", None, "aux(vdd,2)", fit_elsewhere="tests/test_aux.py"),
    _case("term", None, "term(temp*az*lag(vdd))", (math.log(200.0),),
          fit_elsewhere="tests/test_grammar.py"),
    _case("random_walk", None, "bias_poly(1)+random_walk", fit_elsewhere="tests/test_kalman.py"),
]}


def derived_case(cls: type[AbstractEffect]) -> EffectCase:
    """The case of a term without an entry in :data:`BUILT_IN`, from its class: the plan
    that excites what it reads (a rate table for the true rate, six faces for the specific
    force, the thermal chamber for temperature, a warm-up for time alone), a bias
    polynomial beside it, and its spec with its default arguments. A term that reads an
    extra column is not fitted here (no plan carries one); apply-parity still covers it."""
    args = []
    for fname, kind in spec_arguments(cls):
        if kind == "column":
            args.append("vdd")  # the extra column the shared recordings carry
        elif fname == "order":
            args.append(str(cls.default_order if cls.default_order is not None
                            else max(cls.min_order, 1)))
        else:
            raise ValueError(f"no generic argument for {cls.name}'s {fname!r} ({kind})")
    alone = f"{cls.name}({','.join(args)})" if args else cls.name
    term = ErrorModel.from_spec(alone).terms[0]
    needs = term.requires()
    if any(n.startswith("aux:") for n in needs):
        # the simulator's plans carry no extra column a user term could read
        return EffectCase(cls.name, None, alone, (LOG_TAU,) * term.n_nonlinear, built_in=False,
                          numpy=cls.numpy_columns,
                          fit_elsewhere="its own tests (it reads an extra column)")
    if "rate" in needs:
        fit = ("rate_table", f"bias_poly(1)+{alone}", {})
    elif "accel" in needs:
        fit = ("six_face", f"bias_poly(0)+{alone}", {"accel_errors": False})
    elif needs & {"temp", "temp_ext"}:
        fit = ("thermal", f"bias_poly(2)+{alone}", {})
    else:
        fit = ("warmup", f"bias_poly(0)+{alone}", {})
    return EffectCase(cls.name, fit, alone, (LOG_TAU,) * term.n_nonlinear, built_in=False,
                      numpy=cls.numpy_columns)


def cases() -> list[EffectCase]:
    """One case per registered term, in the registry's order (built-ins first). A noise
    process other than the built-in random walk has no generic case: its fit is its own
    registered function."""
    out = []
    for name, cls in registry().items():
        if name in BUILT_IN and cls.__module__.startswith("diffgyro."):
            out.append(BUILT_IN[name])
        elif issubclass(cls, AbstractEffect):
            out.append(derived_case(cls))
    return out


def fit_cases() -> list[EffectCase]:
    """The cases the fit and calibration-file tests run (the others name their file)."""
    return [c for c in cases() if c.fit is not None]


def simulate_case(case: EffectCase, n: int, seed: int):
    """``(batch, truth)`` of ``n`` devices through the case's plan with white noise. The
    simulator draws every built-in term's coefficients; a term it has no population for is
    added here: its columns on the base run's signals (the same temperatures, rates and
    forces: they do not depend on the gyro's errors), a coefficient per axis of random sign
    giving :data:`SIGNAL_TO_NOISE` σ, its time constants at the case's ``theta``."""
    plan, spec, opts = case.fit
    model = ErrorModel.from_spec(spec)
    own = [t for t in model.terms if not type(t).__module__.startswith("diffgyro.")]
    if not own:
        return simulate(plan, n, effects=spec, seed=seed, noise=WHITE, **opts)
    assert own == [model.terms[-1]], "a derived case puts its own term last"
    term = own[0]
    base_spec = "+".join(t.spec for t in model.terms[:-1])
    batch, truth = simulate(plan, n, effects=base_spec, seed=seed, noise=WHITE, **opts)
    sig = batch_signals(batch, norm=truth.norm)
    theta = np.asarray(case.theta, float)
    rng = np.random.default_rng(seed)
    dt = float(np.median(np.diff(np.asarray(batch.t[0, : int(batch.n_valid[0])]))))
    sigma = np.broadcast_to(np.asarray(truth.noise.arw, float).reshape(n, -1), (n, 3))
    sigma = sigma / np.sqrt(dt)
    beta = np.zeros((n, 3, term.n_params))
    for d in range(n):
        s = jax.tree.map(lambda a, d=d: a[d], sig)
        cols = np.asarray(term.columns(s, theta))[: int(batch.n_valid[d])]
        size = SIGNAL_TO_NOISE * sigma[d, :, None] / np.maximum(cols.std(axis=0), 1e-300)
        sign = rng.choice([-1.0, 1.0], size.shape) * rng.uniform(0.5, 1.0, size.shape)
        beta[d] = size * sign / np.sqrt(term.n_params)
    params = Params(beta=np.concatenate([np.asarray(truth.params.beta), beta], -1),
                    theta=np.concatenate([np.asarray(truth.params.theta),
                                          np.tile(theta, (n, 1))], -1))
    return simulate(plan, n, effects=spec, seed=seed, noise=WHITE, params=params,
                    temp_norm=truth.norm, **opts)
