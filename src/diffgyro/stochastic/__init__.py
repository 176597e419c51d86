"""The stochastic model of a gyro: components, wavelet variance, GMWM estimation, structure choice.

* :mod:`.components`: white noise, quantization, first-order Gauss–Markov, random walk and
  rate ramp, each with its theoretical Allan / Haar wavelet variance;
* :mod:`.wavelet_variance`: the empirical Haar wavelet variance on dyadic scales;
* :mod:`.covariance`: the covariance of that estimate under a model (the efficient weight);
* :mod:`.estimator`: the GMWM fit of one structure;
* :mod:`.selection`: the catalogue of structures and the criterion;
* :mod:`.block_likelihood`: the slow part chosen by the exact likelihood of the block means;
  :mod:`.slow_bootstrap`: its close calls settled by a parametric bootstrap;
* :mod:`.intervals`: asymptotic confidence intervals;
* :mod:`.resolution`: what a record resolves (Gauss–Markov times too short or too long for
  it, parameters it does not determine, the smallest walk it would see) and the units;
* :mod:`.identify`: all of it for a batch of series; :mod:`.simulate`: known truth;
* :mod:`.bias_filter`: a Kalman filter of the bias that carries the identified model.
"""

from ._bias_filter import bias_filter, state_space
from ._block_likelihood import PENALTY as SLOW_PENALTY
from ._devices import identify_ahead, identify_devices
from ._identify import NoiseModels, components_of, identify
from ._resolution import DISPLAY, INTERVAL_LEVEL, SHORT_SAMPLES, SPAN_LIMIT, gm_white_power
from ._selection import catalogue, label, structure_mask
from ._simulate import simulate_noise

__all__ = ["identify", "SLOW_PENALTY", "identify_devices", "identify_ahead", "NoiseModels", "label", "bias_filter", "catalogue",
           "components_of", "simulate_noise", "state_space", "structure_mask", "DISPLAY",
           "INTERVAL_LEVEL", "SHORT_SAMPLES", "SPAN_LIMIT", "gm_white_power"]
