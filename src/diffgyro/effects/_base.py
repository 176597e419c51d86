"""The abstract effect term and noise process, their registry and the model-spec grammar.

Every physical effect adds, per gyro axis ``i``, a contribution that is
linear in the term's per-axis coefficients ``beta[i]`` once its few shared
nonlinear parameters (time constants) are fixed::

    contribution[:, i] = columns(signals, theta)[:, i, :] @ beta[i]

Terms linear in all parameters have no ``theta``. This one shape covers
bias, scale factor (columns ∝ true rate), misalignment (columns = the other
axes' rates), g-sensitivity (columns = specific force) and the separable
nonlinear terms (thermal lag, warm-up), and it is what lets the fits use
closed-form least squares and variable projection.

A noise process (the bias random walk) is not a sum of columns: it is the
model's noise component, estimated by a state-space smoother while fitting.
It shares the registry and the spec grammar (``bias_poly(2)+random_walk``); its
fit is registered by class (:func:`register_noise_fit`): the front door
(:mod:`diffgyro.fit`) registers the random walk's, a user's own code its process'.
"""

from __future__ import annotations

import abc
import difflib
import re
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..errors import SpecError
from ..signals import Signals

AXES = ("x", "y", "z")


class AbstractTerm(eqx.Module):
    """What every registered spec name carries: a deterministic effect
    (:class:`AbstractEffect`) or the model's noise component (:class:`AbstractNoise`).

    Class attributes describe the term for the registry and the command line:
    ``name`` (the spec name), ``description`` (one line of physics),
    ``needs`` (data signals it reads: ``temp``, ``temp_ext``, ``accel``,
    ``rate``, ``t``), ``unit`` (unit of its per-axis coefficients; of a noise
    process, of its learned variance) and the arguments its spec takes: ``order_arg`` (an integer order, e.g.
    ``bias_poly(2)``) or, in general, ``arguments``: ``(field, kind)`` pairs in
    spec order, kind ``"int"`` (an order from ``min_order`` to
    :data:`MAX_ORDER`) or ``"column"`` (the name of an extra logged column,
    e.g. ``aux(vdd,2)``); a trailing ``order`` with a ``default_order`` may be
    left out.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    needs: ClassVar[frozenset[str]] = frozenset()
    unit: ClassVar[str] = ""
    order_arg: ClassVar[bool] = False
    default_order: ClassVar[int | None] = None
    min_order: ClassVar[int] = 0
    #: Spec arguments as (field, kind) pairs; empty: ``(("order", "int"),)`` if ``order_arg``.
    arguments: ClassVar[tuple[tuple[str, str], ...]] = ()
    #: The signal the term's contribution follows, where its evidence is sought and against
    #: which reports plot the residual: ``temp``, ``dtemp`` (dT/dt), ``temp_diff``
    #: (temp − temp_ext), ``heating`` (heating vs cooling), ``rate``, ``abs_rate``, ``rate3``,
    #: ``cross_rate`` (the other axes' rates), ``accel``, ``early`` (the first minutes),
    #: ``time``, or ``aux:NAME`` (an extra logged column); None: no single signal.
    follows: ClassVar[str | None] = None
    #: How an explanation says the residual behaves when this term is missing
    #: ("scales with dT/dt"); None: "follows the `NAME` term".
    evidence_phrase: ClassVar[str | None] = None
    #: Terms of one family mimic each other on common test plans; diagnose reports a
    #: family's close candidates together (e.g. ``"thermal transient"``). None: no family.
    family: ClassVar[str | None] = None

    @property
    def spec(self) -> str:
        """This term as it is written in a model spec."""
        return self.name

    @property
    def identity(self) -> tuple:
        """What may appear only once in a model: the name and any column arguments."""
        return (self.name, *(getattr(self, f) for f, kind in spec_arguments(type(self))
                             if kind == "column"))

    def followed_signal(self) -> str | None:
        """The signal this term follows (``follows``; a term whose signal depends on its
        arguments, such as the column of ``aux(NAME)``, overrides this)."""
        return self.follows

    def requires(self) -> frozenset[str]:
        """Data signals this term reads (may depend on its order)."""
        return frozenset(self.needs)

    @abc.abstractmethod
    def coefficient_summary(self) -> str:
        """What the term fits per axis, as the list of effects shows it."""


class AbstractNoise(AbstractTerm):
    """A noise process: the model's noise component (at most one), estimated by a
    state-space smoother while fitting instead of by regression, so it has no columns.
    Its fit is found through :func:`register_noise_fit`."""

    def coefficient_summary(self) -> str:
        return "variance (learned)"


#: Fit functions of models with a noise component, by the component's class.
_NOISE_FITS: dict[type, Callable] = {}


def register_noise_fit(cls: type[AbstractNoise]) -> Callable[[Callable], Callable]:
    """Decorator: ``fn(model, batch, *, norm, options, **overrides)`` fits models whose
    noise component is a ``cls``. :func:`diffgyro.fit.fit` dispatches through this table
    and registers the built-in ``RandomWalk``'s fit (:func:`diffgyro.kalman.fit_random_walk`)
    itself, so every edge is an import the module graph shows.

    **Arguments:**

    - ``cls``: the noise process's class (a subclass of :class:`AbstractNoise`).
    """
    def add(fn: Callable) -> Callable:
        _NOISE_FITS[cls] = fn
        return fn

    return add


def noise_fit(noise: AbstractNoise) -> Callable:
    """The fit registered for the class of ``noise`` (or the nearest base class); the
    built-in processes' fits are registered once :mod:`diffgyro.fit` is imported.

    **Arguments:**

    - ``noise``: a model's noise component.
    """
    for cls in type(noise).__mro__:
        if cls in _NOISE_FITS:
            return _NOISE_FITS[cls]
    raise SpecError(f"no fit is registered for the noise component {noise.spec!r}",
                    hint="register one with diffgyro.effects.register_noise_fit")


class AbstractEffect(AbstractTerm):
    """One physical error term: regressor columns per axis. Subclasses are small final
    modules."""

    #: True if the contribution depends on the true rate (inverted by ``compensate``).
    rate_dependent: ClassVar[bool] = False
    #: True when the term's first column is a constant (a fixed bias): the linear solver
    #: centres the other columns against it, and a random walk beside it starts at zero.
    constant_bias: ClassVar[bool] = False
    #: True when a time constant shorter than the window that estimates dT/dt is the
    #: ``gradient`` term at the data's resolution: diagnose searches τ from that window up.
    tau_from_dtemp_window: ClassVar[bool] = False
    #: The term's columns in numpy, for :mod:`diffgyro.apply` (which holds the built-in
    #: terms' own): a function ``(order, dev, rate, env, theta) -> (columns, used)``, given
    #: to ``apply.compensate(..., terms={name: fn})``; ``used`` is how many of the log τ
    #: in ``theta`` (this term's first) it read. None: apply.py cannot compensate the term.
    numpy_columns: ClassVar[Callable | None] = None

    @abc.abstractmethod
    def param_names(self) -> tuple[str, ...]:
        """Names of the per-axis linear coefficients (one column each)."""

    def labels(self, axis: int) -> tuple[str, ...]:
        """Names of the coefficients of gyro axis ``axis`` as a user reads them."""
        return self.param_names()

    def coefficient_summary(self) -> str:
        return ", ".join(self.param_names())

    def nonlinear_names(self) -> tuple[str, ...]:
        """Names of the shared nonlinear parameters (time constants, in seconds)."""
        return ()

    def nonlinear_init(self, sig: Signals) -> Float[Array, " q"]:
        """Starting values of the nonlinear parameters in their solver space (log τ)."""
        return jnp.zeros((0,))

    def nonlinear_grid(self, sig: Signals) -> Float[Array, "g q"]:
        """Candidate starting values (solver space) searched before the local solve."""
        return self.nonlinear_init(sig)[None]

    def nonlinear_values(self, theta: Float[Array, " q"]) -> Float[Array, " q"]:
        """Physical values (seconds) of the nonlinear parameters from solver space."""
        return jnp.exp(theta)

    @abc.abstractmethod
    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        """Regressor columns per axis; ``theta`` holds this term's nonlinear parameters."""

    def columns_jet(self, sig: Signals, theta: Float[Array, " q"]
                    ) -> tuple[Float[Array, "n 3 p"], Float[Array, "q n 3 p"],
                               Float[Array, "q q n 3 p"]]:
        """Columns and their first and second derivatives in ``theta``: arrays (n, 3, p),
        (q, n, 3, p) and (q, q, n, 3, p). Forward mode by default; a term whose columns
        come from a recursion can give a cheaper exact form (one pass for all three)."""
        def f(th):
            x = self.columns(sig, th)
            return x, x

        def df(th):
            d, x = jax.jacfwd(f, has_aux=True)(th)
            return d, (d, x)

        dd, (d, x) = jax.jacfwd(df, has_aux=True)(theta)
        return x, jnp.moveaxis(d, -1, 0), jnp.moveaxis(dd, (-2, -1), (0, 1))

    def range_problem(self, sig: Signals) -> Float[Array, ""]:
        """A positive number when the data cannot support this term (e.g. too small a
        temperature span for the order); zero otherwise. Traceable."""
        return jnp.zeros(())

    def range_need(self) -> str:
        """What the data must show for this term, in plain words (the reason given
        when :meth:`range_problem` is positive)."""
        return "data that excite it"

    @property
    def min_temp_span(self) -> float:
        """Temperature span (°C) the term needs; 0 when it needs none."""
        return 0.0

    @property
    def n_params(self) -> int:
        return len(self.param_names())

    @property
    def n_nonlinear(self) -> int:
        return len(self.nonlinear_names())


_REGISTRY: dict[str, type[AbstractTerm]] = {}


def register(cls: type[AbstractTerm]) -> type[AbstractTerm]:
    """Class decorator: make an effect or a noise process usable by name in model specs
    everywhere.

    Registering a name twice replaces the earlier class (so a notebook can be
    re-run); built-in names cannot be replaced by a different class.

    **Arguments:**

    - ``cls``: a subclass of :class:`AbstractEffect` or :class:`AbstractNoise` with a
      lower_snake_case ``name``.

    **Returns:** ``cls``, so that ``@register`` decorates it.
    """
    if not (isinstance(cls, type) and issubclass(cls, (AbstractEffect, AbstractNoise))):
        raise TypeError("register() takes a subclass of AbstractEffect or AbstractNoise")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", name):
        raise TypeError(f"effect name {name!r} must be lower_snake_case")
    old = _REGISTRY.get(name)
    if old is not None and old.__module__.startswith("diffgyro.") and old is not cls:
        raise ValueError(f"{name!r} is a built-in effect and cannot be replaced")
    _REGISTRY[name] = cls
    return cls


def registry() -> dict[str, type[AbstractTerm]]:
    """All registered effect and noise classes by name (built-ins first, then user terms)."""
    return dict(_REGISTRY)


_TERM = re.compile(r"^\s*([a-z][a-z0-9_]*)\s*(?:\((.*)\))?\s*$", re.S)
_INT = re.compile(r"[0-9]+")
#: A column argument: the names :func:`diffgyro.io.parse_columns` may give extra columns.
_COLUMN = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")
MAX_ORDER = 9
MAX_SPEC_LENGTH = 1000


def is_column_name(text: str) -> bool:
    """Whether ``text`` can be written as a term's column argument (``aux(NAME)``).

    **Arguments:**

    - ``text``: the candidate column name.
    """
    return bool(_COLUMN.fullmatch(text))


def _did_you_mean(name: str) -> str:
    """``"did you mean 'gradient'? "`` for a misspelt effect name, else ``""``."""
    close = difflib.get_close_matches(name, list(_REGISTRY), n=2, cutoff=0.6)
    return f"did you mean {' or '.join(repr(c) for c in close)}? " if close else ""


def spec_arguments(cls: type[AbstractTerm]) -> tuple[tuple[str, str], ...]:
    """The (field, kind) arguments a term's spec takes, in order.

    **Arguments:**

    - ``cls``: a registered term's class.
    """
    if cls.arguments:
        return tuple(cls.arguments)
    return (("order", "int"),) if cls.order_arg else ()


def _usage(name: str, args) -> str:
    shown = [{"column": "NAME", "expr": "EXPR"}.get(kind, "k") for _, kind in args]
    return f"{name}({','.join(shown)})" if shown else name


def _argument(name: str, field: str, kind: str, text: str, cls) -> object:
    if kind == "expr":  # the term grammar (effects/_grammar.py) reads its own argument
        return cls.parse_argument(text)
    if kind == "column":
        if not is_column_name(text):
            raise SpecError(f"{text!r} is not a column name (argument {field} of {name!r})",
                            hint="letters, digits, _ and ., starting with a letter or _; "
                                 "rename a column with --columns new=old")
        return text
    if not _INT.fullmatch(text):
        raise SpecError(f"argument {field} of {name!r} must be a whole number, not {text!r}")
    order = int(text)
    if order > MAX_ORDER:
        raise SpecError(f"order {order} of {name!r} is above the maximum {MAX_ORDER}")
    if order < cls.min_order:
        raise SpecError(f"order {order} of {name!r} is below the minimum {cls.min_order}")
    return order


def parse_term(text: str) -> AbstractTerm:
    """``"bias_poly(2)"`` -> ``BiasPoly(order=2)``, ``"aux(vdd,2)"`` -> ``Aux(column="vdd",
    order=2)``; clear errors for bad text.

    **Arguments:**

    - ``text``: one term of a spec.
    """
    m = _TERM.match(text)
    valid = ", ".join(sorted(_REGISTRY))
    if m is None:
        raise SpecError(f"cannot read model term {text.strip()!r}",
                        hint=f"write name or name(k) joined by '+'; valid names: {valid}")
    name, arg = m.group(1), m.group(2)
    cls = _REGISTRY.get(name)
    if cls is None:
        raise SpecError(f"unknown effect {name!r}", hint=_did_you_mean(name) + f"valid names: {valid}")
    kinds = spec_arguments(cls)
    given = [] if arg is None else [a.strip() for a in arg.split(",")]
    if given and not kinds:
        raise SpecError(f"effect {name!r} takes no argument", hint=f"write {name}")
    if len(given) > len(kinds):
        raise SpecError(f"effect {name!r} takes at most {len(kinds)} argument"
                        f"{'s' if len(kinds) > 1 else ''}", hint=f"write {_usage(name, kinds)}")
    values = {}
    for k, (field, kind) in enumerate(kinds):
        if k < len(given):
            values[field] = _argument(name, field, kind, given[k], cls)
        elif field == "order" and cls.default_order is not None:
            values[field] = cls.default_order
        else:
            what = {"int": "an order", "expr": "a product of signals"}.get(kind, "a column name")
            raise SpecError(f"effect {name!r} needs {what}",
                            hint=f"write {_usage(name, kinds)}, e.g. "
                                 f"{name}({ {'column': 'vdd', 'expr': 'temp*az'}.get(kind, 2)})")
    return cls(**values)


def parse_spec(spec: str) -> tuple[AbstractTerm, ...]:
    """Split a spec on ``+`` and parse every term; a name may appear only once.

    **Arguments:**

    - ``spec``: the model spec (``"bias_poly(2)+gradient"``).
    """
    if not isinstance(spec, str) or not spec.strip():
        raise SpecError("empty model spec", hint="e.g. bias_poly(2)+gradient")
    if len(spec) > MAX_SPEC_LENGTH:
        raise SpecError(f"model spec is longer than {MAX_SPEC_LENGTH} characters")
    terms = tuple(parse_term(part) for part in spec.split("+"))
    ids = [t.identity for t in terms]
    for t, i in zip(terms, ids):
        if ids.count(i) > 1:
            what = t.name if len(i) == 1 else f"{t.name}({','.join(i[1:])})"
            raise SpecError(f"effect {what!r} appears more than once in {spec!r}")
    return terms


def format_spec(terms) -> str:
    """Canonical spec text of a sequence of terms.

    **Arguments:**

    - ``terms``: the terms, in spec order.
    """
    return "+".join(t.spec for t in terms)
