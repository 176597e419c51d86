"""The private helpers that tests (and a reader checking a result by hand) reach, in one
namespace, as optimistix's ``internal``: not the public API. Nothing here is promised to
stay between versions; it is not in :data:`diffgyro.PUBLIC_MODULES` nor on the API pages.

The test suite reaches the package through its public names and this module only; a test
of one private module itself (``_jit``, ``_jsonio``, ``_program_cache``, …) imports that
module. This is the one module that may import another package's private modules
(``tests/test_architecture.py`` allows it alone). Grouped by where each name lives:

- signals and terms: :func:`batch_signals` and :func:`stacked_signals` (loaded data to
  signals), the signal catalogue's built-in names (``BUILT_IN``) and ``present``, the
  effect registry's tables (``REGISTRY``, and ``NOISE_FITS`` of the noise processes'
  fits), ``per_axis`` (one column per gyro axis);
- the fit's engines: ``filter_jit``, the JAX noise floor (``device_noise_floor``,
  ``masked_median``), the temperature read-out step and dT/dt window
  (``temperature_quantum``, ``suggest_dtemp_window``), ``window_stats`` and
  ``check_windows`` (the motion check's statistics, and its compiled judgement of them:
  numba), ``judge_on_host`` (a small batch's judgement in numpy), the sums path's ``pack`` and
  ``unpack_results``;
- attitude references: quaternion helpers and gyro integration (``_reference``);
- diagnose: ``candidate_grid``, ``residual_floor``, term synthesis (``describe``,
  ``library``, ``propose_all``, ``synthesise``) and ``reason`` (why a candidate is skipped);
- files: unit headers (``header_units``, ``merge_units``, ``split_header``),
  ``unit_scale`` of limits files, the command line's ``load_from_cli``;
- streaming: ``ReadConfig``, ``expand_inputs``, ``index_dataset``, ``WorkDir``,
  ``calibration_entries``, ``ChunkFitter``, ``local_mesh``;
- recipes: ``joint_affine``, ``s2_design``, ``sign_change_mask``, ``offset_filter``;
- the simulator: motion constants and quaternions (``DEG``, ``EARTH_RATE``, ``G0``,
  ``qconj``, ``qlog``, ``qmul``), ``first_order_hold_lag``, noise (``flicker``,
  ``gyro_noise``), populations (``FOG``, ``MEMS``, ``draw_params``);
- the stochastic model: ``LAYOUT``, ``avar_gauss_markov``, ``model_wv`` (and
  ``model_wv_jac``, with its derivative), ``psd``, ``wv_covariance`` (its quadrature's
  ``COV_GRID``), ``dyadic_m``, ``haar_wv``; the block means' likelihood
  (``BlockLikelihood``, ``gm_acov``, ``short_acov``).
"""

from __future__ import annotations

from . import _xla_options as xla_options
from ._fit_sums import groups as fit_groups
from ._fit_sums import pack, unpack_results
from ._jit import filter_jit
from ._judgement_pass import judge as check_windows
from ._motion_host import judge as judge_on_host
from ._noise_jax import device_noise_floor, masked_median
from ._reference import (
    attitude_from_accel_mag,
    heading_error,
    integrate_gyro,
    quat_conj,
    quat_mul,
    rates_from_quaternions,
    rotvec_from_quat,
)
from ._signal_builder import batch_signals, stacked_signals
from ._signal_catalogue import BUILT_IN, present
from ._temperature import suggest_dtemp_window, temperature_quantum
from ._window_stats import window_stats
from .cli._load import load_from_cli
from .diagnose._noise_model import residual_floor
from .diagnose._scoring import candidate_grid
from .diagnose._synthesis import apply as synthesise
from .diagnose._synthesis import describe, library, propose_all
from .diagnose._unsupported import reason
from .effects._base import _NOISE_FITS as NOISE_FITS
from .effects._base import _REGISTRY as REGISTRY
from .effects._common import LOG_TAU_RANGE, per_axis, time_constant
from .effects._thermal_lag import _jet_parallel as jet_parallel
from .effects._thermal_lag import _jet_sequential as jet_sequential
from .effects._thermal_lag import _lag_parallel as lag_parallel
from .effects._thermal_lag import _lag_sequential as lag_sequential
from .io._headers import header_units, merge_units, split_header
from .limits._units import unit_scale
from .pipeline._chunk import calibration_entries
from .pipeline._chunkfit import ChunkFitter, local_mesh
from .pipeline._dataset import ReadConfig, expand_inputs, index_dataset
from .pipeline._workdir import WorkDir
from .recipes._attitude_reference import joint_affine
from .recipes._fog_one_run import s2_design, sign_change_mask
from .recipes._static_kalman import offset_filter
from .simulate._motion import DEG, EARTH_RATE, G0, qconj, qlog, qmul
from .simulate._noise import flicker, gyro_noise
from .simulate._population import FOG, MEMS, draw_params
from .simulate._thermal import first_order_hold_lag
from .stochastic._block_likelihood import BlockLikelihood, gm_acov, short_acov
from .stochastic._components import LAYOUT, avar_gauss_markov, model_wv, model_wv_jac
from .stochastic._covariance import GRID as COV_GRID
from .stochastic._covariance import psd, wv_covariance
from .stochastic._wavelet_variance import dyadic_m, haar_wv

__all__ = [
    "batch_signals", "stacked_signals", "BUILT_IN", "present", "REGISTRY", "NOISE_FITS",
    "per_axis", "fit_groups", "LOG_TAU_RANGE", "time_constant", "jet_parallel", "jet_sequential", "lag_parallel", "lag_sequential",
    "filter_jit", "xla_options", "device_noise_floor", "masked_median", "temperature_quantum",
    "suggest_dtemp_window", "window_stats", "check_windows", "judge_on_host", "pack", "unpack_results",
    "attitude_from_accel_mag", "heading_error", "integrate_gyro", "quat_conj", "quat_mul",
    "rates_from_quaternions", "rotvec_from_quat",
    "candidate_grid", "residual_floor", "describe", "library", "propose_all", "synthesise",
    "reason",
    "header_units", "merge_units", "split_header", "unit_scale", "load_from_cli",
    "ReadConfig", "expand_inputs", "index_dataset", "WorkDir", "calibration_entries",
    "ChunkFitter", "local_mesh",
    "joint_affine", "s2_design", "sign_change_mask", "offset_filter",
    "DEG", "EARTH_RATE", "G0", "qconj", "qlog", "qmul", "first_order_hold_lag", "flicker",
    "gyro_noise", "FOG", "MEMS", "draw_params",
    "LAYOUT", "avar_gauss_markov", "model_wv", "model_wv_jac", "psd", "wv_covariance", "COV_GRID",
    "dyadic_m", "haar_wv",
    "BlockLikelihood", "gm_acov", "short_acov",
]
