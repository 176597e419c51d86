"""The signal catalogue: one description of every signal an effect term may read.

Each entry names a signal as the term grammar writes it (``term(temp*az)``), its unit as
a term reads it, how it is derived from the loaded data, the data signals it needs (an
effect's ``needs``), the :class:`~diffgyro.signals.Signals` fields it reads, and the
built-in effects that follow it. The entry's ``value`` is the one place the signal is
computed from the :class:`~diffgyro.signals.Signals` fields: the term grammar
(:mod:`diffgyro.effects._grammar`, whose figure overlays ``product_of`` read it too), term
synthesis (:mod:`diffgyro.diagnose._synthesis`) and the docs read this table; the fields
are made by :func:`diffgyro.signals.make_signals` (the fit, the simulator) or set directly
for steady state (``plan_design.operating_signals``) and the sums path's probe.
:mod:`diffgyro.apply` (numpy only, the firmware reference) keeps its own twin
(``apply.SIGNALS``), held to this table by tests/test_signal_catalogue.py; and
tests/test_architecture.py fails when any of these places lacks a catalogue signal.

A derived signal is a function of the fields of ``Signals``: adding one takes an entry
here (its ``value`` derives it), its numpy derivation in ``apply.SIGNALS`` (and the list
in apply's docstring), its line in docs/effects.md, and :mod:`diffgyro.signals` only for
a helper of its own or a field computed once in ``make_signals`` (docs/architecture.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from jaxtyping import Array, Float

from .signals import Signals

#: Standard gravity (m/s²): specific force enters a grammar term in g.
G = 9.80665


@dataclasses.dataclass(frozen=True)
class SignalInfo:
    """One signal: its grammar name, unit, derivation, needs and the effects that follow it."""

    name: str
    #: Unit as a term reads the signal.
    unit: str
    #: How it is derived from the loaded columns, in one line.
    derivation: str
    #: In words, for explanations ("the bias follows temperature × a_z").
    words: str
    #: Data signals it needs (as effect terms declare them in ``needs``).
    reads: frozenset[str]
    #: :class:`~diffgyro.signals.Signals` fields that must be present to read it.
    fields: tuple[str, ...]
    #: The value a term reads: (n,), or (n, 3) for a per-axis signal.
    value: Callable[[Signals], Float[Array, "..."]]
    #: Built-in effects that follow the signal (besides ``term``, which may read any).
    effects: tuple[str, ...] = ()
    #: Derived from the loaded columns (not a column itself, nor a scaling of one).
    derived: bool = False
    #: Depends on the true rate: compensation inverts it sample by sample, so no lag of it.
    rate: bool = False
    #: One value per gyro axis (the axis' own rate), not one per sample.
    per_axis: bool = False


def _force(k: int):
    return lambda sig: sig.accel[:, k] / G


def _rate(k: int):
    return lambda sig: sig.rate[:, k]


_ENTRIES = (
    SignalInfo("temp", "1 (°C scaled)", "T_s = (T − centre) / scale, the temperature norm",
               "temperature", frozenset({"temp"}), ("temp_s",), lambda sig: sig.temp_s,
               effects=("bias_poly", "scale_poly", "thermal_lag")),
    SignalInfo("temp_ext", "1 (°C scaled)", "(T_ext − centre) / scale, the temperature's norm",
               "external temperature", frozenset({"temp", "temp_ext"}), ("temp_ext", "norm"),
               lambda sig: (sig.temp_ext - sig.norm.centre) / sig.norm.scale,
               effects=("temp_diff",)),
    SignalInfo("dtemp", "°C/min", "least-squares slope of T over a centred window of "
               "dtemp_window seconds (signals.local_slope)", "dT/dt", frozenset({"temp"}),
               ("dtemp",), lambda sig: 60.0 * sig.dtemp, effects=("gradient", "thermal_lag"),
               derived=True),
    SignalInfo("heating", "±1", "+1 after heating, −1 after cooling (|dT/dt| > 0.05 °C/min), "
               "latched through soaks (signals.latched_heating)", "the heating/cooling state",
               frozenset({"temp"}), ("heating",), lambda sig: sig.heating,
               effects=("hysteresis",), derived=True),
    *(SignalInfo(f"a{c}", "g", f"specific force along {c} (m/s² / 9.80665)", f"a_{c}",
                 frozenset({"accel"}), ("accel",), _force(k), effects=("g_sens",))
      for k, c in enumerate("xyz")),
    *(SignalInfo(f"r{c}", "rad/s", f"reference rate about {c}", f"the {c} rate",
                 frozenset({"rate"}), (), _rate(k),
                 effects=("scale_poly", "scale_asym", "scale_nonlin", "misalignment"), rate=True)
      for k, c in enumerate("xyz")),
    SignalInfo("w", "rad/s", "each axis' own reference rate Ω_i", "the axis' own rate",
               frozenset({"rate"}), (), lambda sig: sig.rate,
               effects=("scale_poly", "scale_asym", "scale_nonlin"), rate=True, per_axis=True),
)

#: Every standard signal by grammar name, in canonical order (the order a term's factors
#: are written in). Extra columns (``aux``) are not listed: any column name is a signal,
#: centred and scaled by :mod:`diffgyro._aux`.
CATALOGUE: dict[str, SignalInfo] = {s.name: s for s in _ENTRIES}
#: The signals diffgyro itself defines (``register_signal`` adds others to
#: :data:`CATALOGUE` only): the ones :mod:`diffgyro.apply` derives in numpy too.
BUILT_IN: tuple[str, ...] = tuple(CATALOGUE)


def register_signal(info: SignalInfo) -> SignalInfo:
    """Add a signal to the catalogue (after the standard ones in canonical order).

    **Arguments:**

    - ``info``: the signal's :class:`SignalInfo` (its grammar name, unit and ``value``).

    **Returns:** ``info``.
    """
    if info.name in CATALOGUE:
        raise ValueError(f"signal {info.name!r} is already in the catalogue")
    CATALOGUE[info.name] = info
    return info


def present(sig: Signals, name: str) -> bool:
    """Whether ``sig`` holds the fields signal ``name`` reads (a standard signal)."""
    return all(getattr(sig, f) is not None for f in CATALOGUE[name].fields)
