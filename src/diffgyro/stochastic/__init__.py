"""The stochastic model of a gyro: components, wavelet variance, GMWM estimation, structure choice.

* :mod:`.components`: white noise, quantization, first-order Gauss–Markov, random walk and
  rate ramp, each with its theoretical Allan / Haar wavelet variance;
* :mod:`.wavelet_variance`: the empirical Haar wavelet variance on dyadic scales;
* :mod:`.covariance`: the covariance of that estimate under a model (the efficient weight);
* :mod:`.estimator`: the GMWM fit of one structure;
* :mod:`.selection`: the catalogue of structures and the criterion;
* :mod:`.intervals`: asymptotic confidence intervals;
* :mod:`.identify`: all of it for a batch of series; :mod:`.simulate`: known truth;
* :mod:`.bias_filter`: a Kalman filter of the bias that carries the identified model.
"""

from .identify import NoiseModels, components_of, identify
from .selection import catalogue, label, structure_mask
from .simulate import simulate_noise

__all__ = ["NoiseModels", "catalogue", "components_of", "identify", "label", "simulate_noise",
           "structure_mask"]
