"""term(EXPR): a bias term built from the signals a recording holds (the term grammar).

``EXPR`` is a product of factors joined by ``*``; a factor is a signal, ``lag(signal)``
(the signal through a first-order lag whose time constant is fitted, as ``thermal_lag``
fits its own) and may carry an integer power ``^k``::

    term(temp*az)          g-sensitivity along z that changes with temperature
    term(ay*az)            a product of specific forces (anisoelastic error)
    term(lag(heater))      an extra column reaching the die through its own thermal path
    term(temp^2*dtemp)     a thermal transient that grows with temperature

Every term has one coefficient per gyro axis (unit: rad/s per unit of the product).
The signals, centred and scaled as the built-in terms read them (float64, so that a
product of signals stays well conditioned), as :mod:`diffgyro._signal_catalogue` lists them:

========== ======================================================== ==============
name       value                                                    reads
========== ======================================================== ==============
temp       ``T_s = (T − centre) / scale`` (the temperature norm)     temp
temp_ext   ``(T_ext − centre) / scale`` (the same norm)              temp, temp_ext
dtemp      dT/dt in °C/min                                           temp
heating    +1 after heating, −1 after cooling (latched)              temp
ax ay az   specific force in g (m/s² / 9.80665)                      accel
rx ry rz   reference rate in rad/s                                   rate
w          each axis' own rate Ω_i (rad/s): per-axis                 rate
NAME       extra column NAME, centred and scaled (:mod:`diffgyro._aux`) aux:NAME
========== ======================================================== ==============

``lag`` takes any signal except the rates (compensation inverts the model sample by
sample); one lagged factor per term. The canonical text orders the factors as the
table does (extra columns by name, a lag after its plain signal) and merges repeated
factors into powers, so ``term(az*temp*temp)`` is written ``term(temp^2*az)``.
"""

from __future__ import annotations

import functools
import re
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._signal_catalogue import CATALOGUE, present
from ..data import aux_key
from ..errors import SpecError
from ..signals import Signals, TempNorm, masked_range
from ._base import MAX_ORDER, AbstractEffect, register
from ._common import (
    MIN_SPAN_PER_ORDER,
    duration,
    log_grid,
    rate_problem,
    temp_span,
    time_constant,
)
from ._thermal_lag import first_order_lag

#: The standard signals in canonical order (the signal catalogue: unit, derivation, needs).
STANDARD = CATALOGUE
#: Signals that depend on the true rate (compensation inverts them; no lag of them).
RATES = frozenset(k for k, s in CATALOGUE.items() if s.rate)
#: Most factors in one term.
MAX_FACTORS = 4
#: Span of a term's column below which the data cannot support it.
MIN_SPAN = 1e-9

_TOKEN = re.compile(r"\s*(?:(?P<name>[A-Za-z_][A-Za-z0-9_.]*)|(?P<int>[0-9]+)|(?P<op>[*^()]))")


def _fail(text: str, pos: int, what: str):
    raise SpecError(f"cannot read term({text}) at character {pos + 1} of {text!r}: {what}",
                    hint="write term(a*b), term(a^2*b) or term(lag(a)*b) with signals "
                         + ", ".join(STANDARD) + " or an extra column's name")


def _tokens(text: str) -> list[tuple[str, str, int]]:
    out, pos = [], 0
    while pos < len(text):
        if text[pos:].strip() == "":
            break
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            _fail(text, pos + len(text[pos:]) - len(text[pos:].lstrip()), "unexpected character "
                  f"{text[pos:].lstrip()[:1]!r}")
        kind = m.lastgroup
        out.append((kind, m.group(kind), m.start(kind)))
        pos = m.end()
    return out


def parse_factors(text: str) -> tuple[tuple[str, bool, int], ...]:
    """``"az*temp^2"`` -> ``(("temp", False, 2), ("az", False, 1))``: (signal, lagged, power)
    in canonical order; SpecError naming the character of the first error.

    **Arguments:**

    - ``text``: the product inside ``term(...)``.
    """
    # term synthesis reads the factors of the same few hundred products tens of thousands
    # of times (Term.factors): parsed once per text and catalogue (the order and the rate
    # check follow the catalogue, which register_signal extends)
    return _parse_factors(text, tuple((k, v.rate) for k, v in CATALOGUE.items()))


@functools.lru_cache(maxsize=4096)
def _parse_factors(text: str, _catalogue: tuple) -> tuple[tuple[str, bool, int], ...]:
    toks = _tokens(text)
    if not toks:
        _fail(text, 0, "empty product")
    k, powers = 0, {}

    def expect(kind, value=None):
        nonlocal k
        if k >= len(toks):
            _fail(text, len(text), f"expected {value or 'a ' + kind} at the end")
        t = toks[k]
        if t[0] != kind or (value is not None and t[1] != value):
            _fail(text, t[2], f"expected {value or 'a signal name'}, not {t[1]!r}")
        k += 1
        return t

    while True:
        _, name, pos = expect("name")
        lagged = False
        if name == "lag" and k < len(toks) and toks[k][1] == "(":
            k += 1
            _, name, pos = expect("name")
            expect("op", ")")
            lagged = True
            if name in CATALOGUE and CATALOGUE[name].rate:
                _fail(text, pos, f"lag({name}): a rate cannot be lagged")
        power = 1
        if k < len(toks) and toks[k][1] == "^":
            k += 1
            if k >= len(toks) or toks[k][0] != "int":
                _fail(text, toks[k][2] if k < len(toks) else len(text), "expected a whole power")
            power, ppos = int(toks[k][1]), toks[k][2]
            if not 1 <= power <= MAX_ORDER:
                _fail(text, ppos, f"power {power} is outside 1..{MAX_ORDER}")
            k += 1
        powers[(name, lagged)] = powers.get((name, lagged), 0) + power
        if k == len(toks):
            break
        expect("op", "*")
    factors = tuple(sorted(((n, lg, p) for (n, lg), p in powers.items()), key=_order))
    if sum(p for _, _, p in factors) > MAX_ORDER:
        _fail(text, 0, f"total power above {MAX_ORDER}")
    if len(factors) > MAX_FACTORS:
        _fail(text, 0, f"more than {MAX_FACTORS} distinct factors")
    if sum(lg for _, lg, _ in factors) > 1:
        _fail(text, text.rfind("lag"), "one lagged factor per term")
    for n, lg, p in factors:
        if n == "heating" and not lg and p % 2 == 0:
            _fail(text, text.find("heating"), "heating is ±1: an even power of it is a constant")
    return factors


def _order(f):
    name, lagged, _ = f
    std = list(STANDARD)
    return (std.index(name) if name in STANDARD else len(std), name, lagged)


def format_factors(factors) -> str:
    """Canonical text of parsed factors."""
    out = []
    for name, lagged, p in factors:
        s = f"lag({name})" if lagged else name
        out.append(s if p == 1 else f"{s}^{p}")
    return "*".join(out)


def signal_value(sig, name: str):
    """Signal ``name`` of the grammar as (n,) or, for ``w``, (n, 3): a catalogue signal
    (:data:`diffgyro._signal_catalogue.CATALOGUE`), else an extra column.

    **Arguments:**

    - ``sig``: the device's :class:`~diffgyro.signals.Signals`.
    - ``name``: the signal's grammar name, or an extra column's.
    """
    if name in CATALOGUE:
        return CATALOGUE[name].value(sig)
    return sig.aux[name]


@register
class Term(AbstractEffect):
    """``Δω_i = c_i · Π_f s_f^(k_f)``: a product of signals, integer powers and at most one
    first-order lag (τ fitted, shared by the axes); ``expr`` is its canonical text."""

    expr: str = eqx.field(static=True, default="")
    name = "term"
    description = ("bias ∝ a product of signals, powers and one lag: term(temp*az), "
                   "term(ay*az), term(lag(NAME)), term(temp^2*dtemp)")
    unit = "rad/s per unit of the product"
    arguments = (("expr", "expr"),)
    #: Synthesised by diagnose from the recording's signals, never offered as a built-in.
    grammar: ClassVar[bool] = True
    follows = "term:EXPR"  # the instance's product: followed_signal()

    def __check_init__(self):
        if self.expr:
            parse_factors(self.expr)

    @classmethod
    def parse_argument(cls, text: str) -> str:
        """The canonical text of an expression (SpecError naming the character of an error)."""
        return format_factors(parse_factors(text))

    @property
    def factors(self):
        return parse_factors(self.expr)

    @property
    def spec(self):
        return f"term({self.expr})"

    @property
    def identity(self) -> tuple:
        return (self.name, self.expr)

    @property
    def rate_dependent(self) -> bool:
        return any(n in CATALOGUE and CATALOGUE[n].rate for n, _, _ in self.factors)

    @property
    def lagged(self) -> str | None:
        """The lagged signal, or None."""
        return next((n for n, lg, _ in self.factors if lg), None)

    def requires(self) -> frozenset[str]:
        out: set[str] = set()
        for n, _, _ in self.factors:
            out |= CATALOGUE[n].reads if n in CATALOGUE else {aux_key(n)}
        return frozenset(out)

    def followed_signal(self):
        """``term:EXPR``: the report draws the residual against the product itself."""
        return f"term:{self.expr}"

    def param_names(self):
        return ("c",)

    def nonlinear_names(self):
        return ("tau",) if self.lagged else ()

    def nonlinear_init(self, sig):
        if not self.lagged:
            return jnp.zeros((0,))
        return jnp.log(jnp.clip(duration(sig) / 30.0, 10.0, 3600.0))[None]

    def nonlinear_grid(self, sig):
        if not self.lagged:
            return jnp.zeros((1, 0))
        return log_grid(5.0 * (sig.t[1] - sig.t[0]) + 1.0, jnp.maximum(duration(sig) / 3.0, 60.0), 12)

    def nonlinear_values(self, theta):
        return time_constant(theta)

    def product(self, sig, theta=None):
        """The product (n, 3); the lagged factor at ``τ = exp(theta[0])`` (unlagged when
        ``theta`` is None: the range check)."""
        n = sig.t.shape[0]
        out = jnp.ones((n, 3), sig.gyro.dtype)
        for name, lagged, p in self.factors:
            x = signal_value(sig, name)
            if lagged and theta is not None:
                x = first_order_lag(sig.t, x, time_constant(theta[0]))
            x = x**p
            out = out * (x if x.ndim == 2 else x[:, None])
        return out

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return self.product(sig, theta)[:, :, None]

    def range_problem(self, sig):
        x = self.product(sig)
        lo, hi = masked_range(x.T, sig.mask[None, :])
        problem = jnp.max(jnp.maximum(MIN_SPAN * jnp.maximum(jnp.abs(lo), jnp.abs(hi))
                                      + 1e-300 - (hi - lo), 0.0))
        names = {n for n, _, _ in self.factors}
        if "temp" in names:
            problem = problem + jnp.maximum(MIN_SPAN_PER_ORDER - temp_span(sig), 0.0)
        if "w" in names:
            problem = problem + rate_problem(sig)
        return problem

    def range_need(self) -> str:
        return f"signals {', '.join(n for n, _, _ in self.factors)} that vary in this recording"

    def describe(self) -> str:
        """The product in words ("temperature × a_z")."""
        parts = []
        for n, lg, p in self.factors:
            w = CATALOGUE[n].words if n in CATALOGUE else f"column {n}"
            w = f"{w} through a first-order lag" if lg else w
            parts.append(w if p == 1 else f"({w})^{p}")
        return " × ".join(parts)


def product_of(expr: str, rec, dtemp=None, axis: int = 0):
    """The product ``expr`` of a recording's signals in plain units (°C, g, rad/s, the
    column's own; a lagged factor unlagged: its τ is the fit's), for figures; None when the
    recording lacks one of them. Each factor is the catalogue's value
    (:data:`diffgyro._signal_catalogue.CATALOGUE`) on :func:`plain_signals`, or an extra
    column.

    **Arguments:**

    - ``expr``: the product (``"temp*az"``), as inside ``term(...)``.
    - ``rec``: the :class:`~diffgyro.data.Recording`.
    - ``dtemp``: its dT/dt (n,), °C/s, where known (else derived from ``rec``).
    - ``axis``: the gyro axis whose rate ``w`` stands for.
    """

    sig = plain_signals(rec, dtemp)
    have = sig.available
    out = np.ones(rec.n)
    for name, _, p in parse_factors(expr):
        info = CATALOGUE.get(name)
        if info is None:
            x = rec.aux.get(name)
        elif info.reads <= have and present(sig, name):
            x = info.value(sig)
            x = x[:, axis] if info.per_axis else x
        else:
            x = None
        if x is None:
            return None
        out = out * np.asarray(x, float) ** p
    return out


def plain_signals(rec, dtemp=None) -> Signals:
    """A recording's :class:`~diffgyro.signals.Signals` in plain units, on the host: the
    temperature uncentred (centre 0, scale 1: a catalogue signal of it reads °C), dT/dt
    the given ``dtemp`` (°C/s; None leaves it and the heating state out) and the heating
    state its sign (the figures' overlay, not the latched state a fit reads)."""
    n = rec.n
    heating = None if dtemp is None or rec.temp is None else np.sign(dtemp)
    return Signals(
        t=np.asarray(rec.t, float) - float(rec.t[0]), gyro=np.asarray(rec.gyro, float),
        mask=np.ones(n, bool), rate=np.zeros((n, 3)) if rec.rate is None else np.asarray(rec.rate),
        temp=rec.temp, temp_s=rec.temp, dtemp=None if rec.temp is None or dtemp is None
        else np.asarray(dtemp), heating=heating, temp_ext=rec.temp_ext, accel=rec.accel,
        norm=TempNorm(centre=np.float64(0.0), scale=np.float64(1.0)),
        has_rate=rec.rate is not None, aux=dict(rec.aux))
