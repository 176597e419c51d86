"""Effect terms: one small module per physical effect, the noise process (random_walk), a
registry and the spec grammar."""

from .._signal_catalogue import SignalInfo, register_signal
from ._aux import Aux
from ._base import (
    AXES,
    MAX_ORDER,
    AbstractEffect,
    AbstractNoise,
    AbstractTerm,
    format_spec,
    is_column_name,
    noise_fit,
    parse_spec,
    parse_term,
    register,
    register_noise_fit,
    registry,
    spec_arguments,
)
from ._bias_poly import BiasPoly
from ._g_sens import GSens
from ._gradient import Gradient
from ._grammar import RATES, STANDARD, Term, parse_factors, product_of, signal_value
from ._hysteresis import Hysteresis
from ._misalignment import Misalignment
from ._random_walk import RandomWalk
from ._scale_asym import ScaleAsym
from ._scale_nonlin import ScaleNonlin
from ._scale_poly import ScalePoly
from ._temp_diff import TempDiff
from ._thermal_lag import ThermalLag, first_order_lag
from ._warmup import Warmup

__all__ = ["register", "registry", "parse_spec", "format_spec", "AbstractEffect", "AbstractNoise",
           "AbstractTerm", "register_noise_fit", "noise_fit", "register_signal", "SignalInfo", "AXES", "MAX_ORDER", "RATES",
           "STANDARD", "Aux", "BiasPoly", "GSens", "Gradient", "Hysteresis", "Misalignment",
           "RandomWalk", "ScaleAsym", "ScaleNonlin", "ScalePoly", "TempDiff", "Term", "ThermalLag",
           "Warmup", "first_order_lag", "is_column_name", "parse_factors", "product_of",
           "parse_term", "signal_value", "spec_arguments"]
