"""Effect terms: one small module per physical effect, the noise process (random_walk), a
registry and the spec grammar."""

from . import (  # noqa: F401  (importing registers the built-in terms)
    aux,
    bias_poly,
    g_sens,
    gradient,
    grammar,
    hysteresis,
    misalignment,
    random_walk,
    scale_asym,
    scale_nonlin,
    scale_poly,
    temp_diff,
    thermal_lag,
    warmup,
)
from .aux import Aux
from .base import (
    AXES,
    AbstractEffect,
    AbstractNoise,
    AbstractTerm,
    format_spec,
    noise_fit,
    parse_spec,
    parse_term,
    register,
    register_noise_fit,
    registry,
    spec_arguments,
)
from .bias_poly import BiasPoly
from .g_sens import GSens
from .gradient import Gradient
from .grammar import Term
from .hysteresis import Hysteresis
from .misalignment import Misalignment
from .random_walk import RandomWalk
from .scale_asym import ScaleAsym
from .scale_nonlin import ScaleNonlin
from .scale_poly import ScalePoly
from .temp_diff import TempDiff
from .thermal_lag import ThermalLag, first_order_lag
from .warmup import Warmup

__all__ = [
    "AXES", "AbstractEffect", "AbstractNoise", "AbstractTerm", "Aux", "BiasPoly", "GSens",
    "Gradient", "Hysteresis", "Misalignment", "RandomWalk",
    "ScaleAsym", "ScaleNonlin", "ScalePoly", "TempDiff", "Term", "ThermalLag", "Warmup",
    "first_order_lag", "format_spec", "noise_fit", "parse_spec", "parse_term", "register",
    "register_noise_fit", "registry", "spec_arguments",
]
