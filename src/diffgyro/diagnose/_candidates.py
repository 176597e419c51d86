"""The candidate terms: every registered effect the data supports and the model lacks."""

from __future__ import annotations

from dataclasses import dataclass

from ..effects import (
    MAX_ORDER,
    AbstractNoise,
    AbstractTerm,
    is_column_name,
    parse_term,
    registry,
    spec_arguments,
)
from ..model import ErrorModel


@dataclass(frozen=True)
class CandidateSpec:
    """One candidate: the model with ``term`` added (or ``old`` raised to ``term``)."""

    effect: str
    term: AbstractTerm
    model: ErrorModel
    old: AbstractTerm | None = None  # the term it replaces (order raised)

    @property
    def spec(self) -> str:
        return self.model.spec


def _new_terms(cls, present: AbstractTerm | None) -> list[AbstractTerm]:
    """The terms to try for one effect: an absent one at its default order, or at orders 0
    and 1 when it has no default (a constant and a temperature-dependent one); a present
    one with its order raised by one."""
    if present is None:
        if cls.order_arg:
            if cls.default_order is not None:
                return [cls(order=cls.default_order)]
            return [cls(order=0), cls(order=1)]
        return [cls()]
    if cls.order_arg and present.order < MAX_ORDER:
        return [cls(order=present.order + 1)]
    return []


def column_field(cls) -> str | None:
    """The field of an effect's column argument (``aux(NAME)``: ``column``), or None."""
    return next((f for f, kind in spec_arguments(cls) if kind == "column"), None)


def term_column(term: AbstractTerm) -> str | None:
    """The extra column a term reads through its column argument (``aux(vdd)``: vdd)."""
    field = column_field(type(term))
    return getattr(term, field) if field else None


def _column_terms(cls, model: ErrorModel, columns, explicit) -> list[AbstractTerm]:
    """Terms of a column effect: one per extra column the model does not read with it yet
    (``explicit``: those of the given terms)."""
    field = column_field(cls)
    used = {getattr(t, field) for t in model.terms if t.name == cls.name}
    terms = explicit if explicit is not None else [cls(**{field: c}) for c in columns]
    return [t for t in terms if getattr(t, field) not in used]


def unnamed_columns(columns, names: list[str] | None = None) -> dict[str, str]:
    """The column terms that cannot be written for extra columns whose names are not valid
    term arguments (``Magnetometer X (uT)``), each with the reason and the way to try it:
    listed under a device's ``skipped``, never an error (``names``: the effects tried)."""
    bad = [c for c in columns if not is_column_name(c)]
    wanted = None if names is None else {n.strip().split("(")[0] for n in names}
    out = {}
    for name, cls in registry().items():
        if column_field(cls) is None or (wanted is not None and name not in wanted):
            continue
        for c in bad:
            out[f"{name}({c})"] = (f"extra column name {c!r} cannot be written in a model term "
                                   f"(letters, digits, _ and ., starting with a letter or _); to "
                                   f"try it, rename it with --columns 'NEW={c}'")
    return out


def candidate_specs(model: ErrorModel, available: frozenset[str],
                    names: list[str] | None = None,
                    columns: tuple[str, ...] = ()) -> list[CandidateSpec]:
    """Every registered effect the data supports and ``model`` lacks (or can raise).

    An effect already in the model with an order (``bias_poly(2)``) is offered
    one order higher; an absent one at its default order, or at orders 0 and 1
    when it has none (a scale factor that drifts with temperature is
    ``scale_poly(1)``; ``scale_poly(0)`` alone can be worse than nothing
    there). ``names`` limits the search to those effect names (or full terms
    such as ``bias_poly(3)``). Order-k columns must be the first columns of
    order k+1 (true of the built-in polynomial terms) for a raised candidate
    to be scored. An effect with a column argument (``aux``) is offered once per
    extra column in ``columns`` the model does not read with it yet. A noise process
    (``random_walk``) is offered as the model plus that noise component when the model
    has none.

    **Arguments:**

    - ``model``: the base :class:`~diffgyro.model.ErrorModel`.
    - ``available``: the signals the data holds (``temp``, ``rate``, ``accel``, …).
    - ``names``: effect names or full terms to limit the search to; None: every registered
      effect.
    - ``columns``: the extra columns the data holds (for terms with a column argument).
    """

    present = {t.name: t for t in model.terms}
    wanted: dict[str, list[AbstractTerm] | None] = {}
    if names is None:
        wanted = {n: None for n in registry()}
    else:
        for text in names:
            text = text.strip()
            if text in registry():  # a bare name: the default candidates of that effect
                wanted[text] = None
                continue
            term = parse_term(text)
            wanted.setdefault(term.name, [])
            if wanted[term.name] is not None:
                wanted[term.name].append(term)
    out = []
    for name, explicit in wanted.items():
        cls = registry()[name]
        if getattr(cls, "grammar", False) and explicit is None:
            continue  # grammar terms are synthesised (diagnose/_synthesis.py), not enumerated
        if issubclass(cls, AbstractNoise) and model.noise is not None:
            continue  # one noise component per model
        if column_field(cls):
            old, terms = None, _column_terms(cls, model, columns, explicit)
        else:  # a grammar term (term(EXPR)) is added beside those of the model, never raised
            old = None if getattr(cls, "grammar", False) else present.get(name)
            terms = explicit if explicit is not None else _new_terms(cls, old)
        for term in terms:
            if old is not None and (term == old or not cls.order_arg or term.order <= old.order):
                continue
            if not term.requires() <= available | {"t", "gyro"}:
                continue
            if old is None:
                new_model = model + term
            else:
                new_model = ErrorModel(tuple(term if t is old else t for t in model.terms),
                                       model.noise)
            out.append(CandidateSpec(effect=name, term=term, model=new_model, old=old))
    return out


# --------------------------------------------------------------------------- the engine (one device)


def added_term(old: str, new: str) -> str:
    """The term text that ``new`` has and ``old`` lacks (``scale_poly(1)``, ``bias_poly(3)``)."""
    extra = [t for t in new.split("+") if t not in old.split("+")]
    return "+".join(extra) or new
