"""What the built-in effect terms are, without their equinox classes (and so without JAX).

A calibration file names its model by spec; reading the file, exporting it and listing
the vocabulary need only each term's description: its name, physics, coefficient names
(one per column), time constants, the signals it reads and its unit. :data:`KINDS` holds
these for every built-in term, in the registry's order, and :func:`model_info` reads a
spec with them. A spec outside their reach (a ``term(EXPR)``, a user's registered term,
a spec the grammar refuses) is read by the full parser
(:meth:`diffgyro.model.ErrorModel.from_spec`), which imports JAX: its errors and its
reading are the reference. tests/test_term_info.py holds every kind to its class.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from ._vocabulary import AUX_PREFIX

__all__ = ["TermKind", "TermInfo", "ModelInfo", "KINDS", "model_info", "info_of"]


def _polynomial(letter: str, first: int) -> Callable[[dict], tuple[str, ...]]:
    """Coefficient names ``letter + j`` for j = first .. order."""
    return lambda args: tuple(f"{letter}{j}" for j in range(first, args["order"] + 1))


def _fixed(*names: str) -> Callable[[dict], tuple[str, ...]]:
    return lambda args: names


@dataclass(frozen=True)
class TermKind:
    """A built-in term as the registry describes it (its class's attributes)."""

    name: str
    description: str
    unit: str
    params: Callable[[dict], tuple[str, ...]]
    needs: frozenset[str] = frozenset()
    arguments: tuple[tuple[str, str], ...] = ()
    default_order: int | None = None
    min_order: int = 0
    nonlinear: tuple[str, ...] = ()
    noise: bool = False
    #: The signals read, where they depend on the arguments.
    reads: Callable[[dict], frozenset[str]] | None = None

    def requires(self, args: dict) -> frozenset[str]:
        """The data signals a term of these arguments reads."""
        return frozenset(self.needs) if self.reads is None else self.reads(args)

    def spec(self, args: dict) -> str:
        """The term as a spec writes it: a trailing order at its default is left out."""
        shown = [str(args[f]) for f, _ in self.arguments]
        if shown and self.arguments[-1][0] == "order" and args["order"] == self.default_order:
            shown.pop()
        return f"{self.name}({','.join(shown)})" if shown else self.name


def _with_temp(base: frozenset[str]) -> Callable[[dict], frozenset[str]]:
    return lambda args: base | ({"temp"} if args["order"] >= 1 else set())


_ORDER = (("order", "int"),)

#: Every built-in term, by name, in the registry's order (tests/test_term_info.py).
KINDS: dict[str, TermKind] = {k.name: k for k in (
    TermKind("aux", "bias ∝ an extra logged column NAME (polynomial of order k, default 1)",
             "rad/s per x_s^j", _polynomial("a", 1),
             arguments=(("column", "column"), ("order", "int")), default_order=1, min_order=1,
             reads=lambda args: frozenset({AUX_PREFIX + args["column"]})),
    TermKind("bias_poly", "per-axis bias, polynomial of temperature (k = 0: constant)",
             "rad/s per T_s^j", _polynomial("c", 0), arguments=_ORDER,
             reads=_with_temp(frozenset())),
    TermKind("g_sens", "3×3 g-sensitivity: bias proportional to specific force",
             "rad/s per m/s²", _fixed("g_x", "g_y", "g_z"), needs=frozenset({"accel"})),
    TermKind("gradient", "bias proportional to dT/dt", "rad/s per °C/s", _fixed("g"),
             needs=frozenset({"temp"})),
    TermKind("thermal_lag", "the bias polynomial sees temperature through a first-order lag "
             "with fitted time constant", "rad/s per T_s^j", _polynomial("l", 1),
             needs=frozenset({"temp"}), arguments=_ORDER, default_order=1, nonlinear=("tau",)),
    TermKind("term", "bias ∝ a product of signals, powers and one lag: term(temp*az), "
             "term(ay*az), term(lag(NAME)), term(temp^2*dtemp)",
             "rad/s per unit of the product", _fixed("c"), arguments=(("expr", "expr"),)),
    TermKind("hysteresis", "bias offset set by whether the sensor last heated or cooled, kept "
             "through soaks", "rad/s", _fixed("h"), needs=frozenset({"temp"})),
    TermKind("misalignment", "six off-diagonal cross-axis couplings",
             "rad (small angle, dimensionless)", _fixed("m_first", "m_second"),
             needs=frozenset({"rate"})),
    TermKind("random_walk", "stochastic bias random walk, Kalman-smoothed, variance by maximum "
             "likelihood", "(rad/s)²/s", _fixed(), noise=True),
    TermKind("scale_asym", "scale factor differs for positive and negative input rates",
             "1 (dimensionless)", _fixed("a"), needs=frozenset({"rate"})),
    TermKind("scale_nonlin", "scale-factor error growing with rate² (output term ∝ Ω³)",
             "(rad/s)^-2", _fixed("n"), needs=frozenset({"rate"})),
    TermKind("scale_poly", "per-axis scale-factor error, polynomial of temperature",
             "1 per T_s^j (dimensionless)", _polynomial("s", 0), arguments=_ORDER,
             reads=_with_temp(frozenset({"rate"}))),
    TermKind("temp_diff", "bias proportional to (temp − temp_ext)", "rad/s per °C", _fixed("d"),
             needs=frozenset({"temp", "temp_ext"})),
    TermKind("warmup", "exponential bias transient after power-on, fitted amplitude and time "
             "constant", "rad/s", _fixed("w"), needs=frozenset({"t"}), nonlinear=("tau",)),
)}


@dataclass(frozen=True)
class TermInfo:
    """One term of a model: what export, the file's checks and its units read."""

    name: str
    spec: str
    unit: str
    param_names: tuple[str, ...]
    nonlinear_names: tuple[str, ...]
    required: frozenset[str]
    noise: bool = False
    order: int | None = None

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def n_nonlinear(self) -> int:
        return len(self.nonlinear_names)

    def requires(self) -> frozenset[str]:
        return self.required


@dataclass(frozen=True)
class ModelInfo:
    """A model spec read into its terms: effects in order, the noise component apart."""

    terms: tuple[TermInfo, ...]
    noise: TermInfo | None = None

    @property
    def parts(self) -> tuple[TermInfo, ...]:
        return self.terms if self.noise is None else (*self.terms, self.noise)

    @property
    def spec(self) -> str:
        return "+".join(t.spec for t in self.parts)

    @property
    def n_params(self) -> int:
        return sum(t.n_params for t in self.terms)

    @property
    def n_nonlinear(self) -> int:
        return sum(t.n_nonlinear for t in self.terms)

    def requires(self) -> frozenset[str]:
        return frozenset().union(*(t.requires() for t in self.parts))


_PART = re.compile(r"([a-z][a-z0-9_]*)(?:\(([^()]*)\))?")
_COLUMN = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")
_ORDER_TEXT = re.compile(r"[0-9]")
_MAX_ORDER = 9
_MAX_SPEC = 1000


def _arguments(kind: TermKind, text: str | None) -> dict | None:
    """The arguments of a plain built-in term, or None where the full parser must read it."""
    given = [] if text is None else text.split(",")
    if len(given) > len(kind.arguments) or (given and not kind.arguments):
        return None
    args = {}
    for k, (field, what) in enumerate(kind.arguments):
        if k >= len(given):
            if field != "order" or kind.default_order is None:
                return None
            args[field] = kind.default_order
        elif what == "column" and _COLUMN.fullmatch(given[k]):
            args[field] = given[k]
        elif what == "int" and _ORDER_TEXT.fullmatch(given[k]):
            args[field] = int(given[k])
            if not kind.min_order <= args[field] <= _MAX_ORDER:
                return None
        else:
            return None
    return args


def _fast(spec: str) -> ModelInfo | None:
    """A spec of plain built-in terms, each written without spaces; None otherwise."""
    if not isinstance(spec, str) or not spec or len(spec) > _MAX_SPEC:
        return None
    terms, noise, seen = [], [], set()
    for part in spec.split("+"):
        m = _PART.fullmatch(part)
        kind = None if m is None else KINDS.get(m.group(1))
        if kind is None or kind.name == "term":
            return None
        args = _arguments(kind, m.group(2))
        if args is None:
            return None
        identity = (kind.name, args.get("column"))
        if identity in seen:
            return None
        seen.add(identity)
        info = TermInfo(kind.name, kind.spec(args), kind.unit, kind.params(args), kind.nonlinear,
                        kind.requires(args), kind.noise, args.get("order"))
        (noise if kind.noise else terms).append(info)
    if len(noise) > 1:
        return None
    return ModelInfo(tuple(terms), noise[0] if noise else None)


def info_of(term) -> TermInfo:
    """A :class:`TermInfo` of a term object of the registry (any term, a user's too)."""
    noise = not hasattr(term, "param_names")
    return TermInfo(term.name, term.spec, term.unit, () if noise else tuple(term.param_names()),
                    () if noise else tuple(term.nonlinear_names()), frozenset(term.requires()),
                    noise, getattr(term, "order", None))


def model_info(spec: str) -> ModelInfo:
    """The terms of ``spec``: read here for plain built-in terms, else by the full parser
    (JAX; :class:`~diffgyro.errors.SpecError` for a spec it refuses)."""
    fast = _fast(spec)
    if fast is not None:
        return fast
    from .model import ErrorModel

    model = ErrorModel.from_spec(spec)
    return ModelInfo(tuple(info_of(t) for t in model.terms),
                     None if model.noise is None else info_of(model.noise))
