"""The built-in terms' table (``diffgyro._term_info``), which reads calibration files and
lists the vocabulary without JAX, says what each registered class says: the same names in
the registry's order, descriptions, units, arguments, coefficients, time constants,
signals and canonical spec at every order; a spec beyond the table is read by the full
parser, and a spec it refuses fails with the parser's own error."""

from __future__ import annotations

import pytest

from diffgyro._term_info import _MAX_ORDER, KINDS, _fast, info_of, model_info
from diffgyro.effects import MAX_ORDER, registry, spec_arguments
from diffgyro.errors import SpecError
from diffgyro.model import ErrorModel


def _built_ins():
    return {n: c for n, c in registry().items() if c.__module__.startswith("diffgyro.")}


def test_table_lists_every_built_in_term_in_registry_order():
    assert list(KINDS) == list(_built_ins())
    assert _MAX_ORDER == MAX_ORDER


@pytest.mark.parametrize("name", sorted(KINDS))
def test_each_kind_matches_its_class(name):
    cls, kind = _built_ins()[name], KINDS[name]
    assert (kind.description, kind.unit, kind.arguments, kind.default_order, kind.min_order) == (
        cls.description, cls.unit, spec_arguments(cls), cls.default_order, cls.min_order)
    assert kind.noise == (not hasattr(cls, "param_names"))
    if name == "term":  # the grammar's terms are read by the full parser
        return
    orders = range(cls.min_order, MAX_ORDER + 1) if kind.arguments else [None]
    for order in orders:
        args = {f: ("vdd" if what == "column" else order) for f, what in kind.arguments}
        want = info_of(cls(**args))
        got = _fast(want.spec)
        assert got is not None and got.parts == (want,), (name, order)
        assert kind.requires(args) == want.required


SPECS = ["bias_poly(2)+gradient", "bias_poly(3)", "random_walk+bias_poly(1)", "thermal_lag",
         "thermal_lag(1)+warmup", "aux(vdd)+aux(v.2,3)+bias_poly(0)", "scale_poly(2)+misalignment"
         "+scale_asym+scale_nonlin+g_sens+temp_diff+hysteresis", "bias_poly(1)+aux(vdd,1)"]


@pytest.mark.parametrize("spec", SPECS)
def test_model_info_reads_specs_as_the_model_does(spec):
    model = ErrorModel.from_spec(spec)
    info = _fast(spec)
    assert info is not None
    assert (info.spec, info.n_params, info.n_nonlinear, info.requires()) == (
        model.spec, model.n_params, model.n_nonlinear, model.requires())
    assert info.parts == tuple(info_of(t) for t in model.parts)


@pytest.mark.parametrize("spec", ["term(temp*az)+bias_poly(1)", "bias_poly( 2 )", "bias_poly(02)"])
def test_specs_beyond_the_table_go_to_the_parser(spec):
    assert _fast(spec) is None
    model = ErrorModel.from_spec(spec)
    assert model_info(spec).spec == model.spec


@pytest.mark.parametrize("spec", ["", "bias_poly", "bias_poly(10)", "gradient(1)", "gradien",
                                  "aux(1x)", "bias_poly(1)+bias_poly(2)", "aux(a)+aux(a,2)",
                                  "random_walk+random_walk", "thermal_lag(0)+bias_poly(1)+"])
def test_refused_specs_fail_as_the_parser_fails(spec):
    with pytest.raises(SpecError) as want:
        ErrorModel.from_spec(spec)
    with pytest.raises(SpecError) as got:
        model_info(spec)
    assert str(got.value) == str(want.value)
