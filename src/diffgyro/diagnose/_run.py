"""diagnose(model, batch): the base fit, every device scored, then each device's diagnosis.

The plan (:mod:`._plan`) is formed, and its programs started, before the base fit where
the fit's setting can be foreseen; the devices are scored in chunks (:mod:`._chunks`) and
the residuals' Allan deviation taken (:mod:`._residual_allan`); here each device's scores
become its decision, then the greedy pair, the synthesis and the residual's noise model.
"""

from __future__ import annotations

import numpy as np

from .. import _noise as noise
from .._jit import filter_jit, release_compiled_if_crowded
from .._temperature import suggest_dtemp_window
from ..channel import GRAVITY, UNITS, as_channel, check_channel, reads_gravity
from ..data import Batch, Recording, as_batch
from ..errors import SpecError
from ..fit import fit as fit_fn
from ..model import ErrorModel
from ._candidates import term_column
from ._chunks import put, score
from ._decision import allan_slope, decide, not_judged
from ._evidence import evidence
from ._greedy import pairs as greedy_pairs
from ._noise_model import attach_noise, residual_floor
from ._plan import first_programs, plan_of_fit, planned_ahead
from ._residual_allan import allan
from ._results import Diagnosis
from ._synthesis import apply as synthesise
from ._synthesis import apply_one as synthesise_one
from ._thresholds import Thresholds
from ._unsupported import reason as unsupported_reason


@filter_jit
def _nonlinear_values(term, theta):
    """``term.nonlinear_values(theta)`` as one program (run eagerly, its clip and exp were
    two, each compiled, or read from the cache, in every process; the same bits)."""
    return term.nonlinear_values(theta)


def _taus(cands, theta_row) -> list:
    """The chosen time constant (s) of every candidate with one, else None."""
    taus = []
    for c, th in zip(cands, theta_row):
        if c.old is None and c.term.n_nonlinear == 1 and np.isfinite(th).all():
            taus.append(float(np.asarray(_nonlinear_values(c.term, put(th)))[0]))
        else:
            taus.append(None)
    return taus


def _reported_floor(batch: Batch, res) -> list[tuple[float, list[float]]]:
    """(noise floor, per axis) of every device: the base fit's (``_noise``),
    computed here when that fit was run without it, so ``diagnose`` and ``fit`` report
    the same floor for the same device."""

    if res.options.noise_floor:
        axes = np.asarray(res.noise_axes, float)
    else:
        axes = noise.noise_axes(np.asarray(batch.gyro), None if batch.rate is None
                                else np.asarray(batch.rate), np.asarray(batch.mask, bool))
    return [(float(f), [float(v) for v in a]) for f, a in zip(noise.noise_floor(axes), axes)]


def _device(i, batch, res, out, cands, ranges, floors, al, rw_spec, th, model, unsupported,
            skips: dict, pair=None):
    """One device's :class:`DeviceDiagnosis` from its scores (floors: the white-noise level
    the decision uses); slope and floor_allan too. ``skips``: the column candidates it skips
    and why (:func:`._plan._column_skips`), listed by term; ``pair``: :class:`.greedy.Pair`."""
    nv = int(batch.n_valid[i])
    total = float(batch.t[i, nv - 1] - batch.t[i, 0])
    adev, tau = al.adev[i], al.tau[i]
    slope = allan_slope(adev, tau, total)
    first = np.isfinite(adev[:, 0])
    floor_allan = float(np.sqrt(np.mean(adev[first, 0] ** 2))) if first.any() else float("nan")
    status = res.status_name(i)
    if status != "ok" or not (np.all(np.isfinite(np.asarray(res.params.beta[i])))
                              and np.all(np.isfinite(np.asarray(res.params.theta[i])))):
        d = not_judged(batch.devices[i], status, res.status_detail(i), floors[i],
                       float(res.rms[i]), float(res.heldout_rms[i]))
        d.skipped.update(skips)
        return d, slope, floor_allan
    sd = {k: (out[k][i, :nv] if k in out else None) for k in ("dtemp", "heating")}
    rec = batch.recording(i)
    ev = evidence(out["residual"][i, :nv], rec, sd, floors[i])
    ok = ranges[i] <= 0 if ranges.size else np.zeros(0, bool)
    why = {j: unsupported_reason(c.term, rec, sd["dtemp"], sd["heating"])
           for j, c in enumerate(cands) if not ok[j] and term_column(c.term) is None}
    d = decide(
        batch.devices[i], res.status_name(i), out["base_sse"][i], out["cnt"][i],
        out["base_full"][i], [c.effect for c in cands], [c.spec for c in cands],
        out["cand_sse"][i], out["cand_full"][i], ok, _taus(cands, out["cand_theta"][i]), rw_spec,
        out["rw_interp"][i], out["rw_full"][i], floors[i], floor_allan, slope, nv, th, ev,
        blocks={"cnt": out["blk_cnt"][i], "base": out["base_blk"][i], "cand": out["cand_blk"][i]},
        edge=out["cand_edge"][i], base_spec=model.spec, pair=pair, why=why)
    d.status_detail = res.status_detail(i)
    for c in unsupported:  # column candidates are listed by term (aux(vdd)), in skips
        d.skipped[c.effect] = unsupported_reason(c.term, rec, sd["dtemp"], sd["heating"])
    d.skipped.update(skips)
    return d, slope, floor_allan


def _rescorer(devices, batch, res, out, cands, ranges, floors, al, rw_spec, th, model,
              unsupported, skips, reported, synthesis: bool):
    """``rescore(i, floor_axes, builtin)``: device i's decision against another per-axis
    floor (the white level + the identified Gauss–Markov power, :mod:`.noise_model`), then,
    where no built-in term closes the gap, the synthesis judged against the noise its terms
    leave. Without ``builtin`` the white-floor decision is kept and only the synthesis runs
    (None unless it proposes a term)."""
    def rescore(i, floor_axes, builtin=True):
        if builtin:
            fl = np.array(floors, copy=True)
            fl[i] = floor_axes
            alt = _device(i, batch, res, out, cands, ranges, fl, al, rw_spec, th, model,
                          unsupported, skips[i])[0]
            alt.noise_floor, alt.noise_axes = reported[i]
        else:
            alt = devices[i]
        prop = synthesise_one(i, alt, batch, res, model, cands, ranges <= 0, th,
                              devices[i].white_noise_rms,
                              lambda k, e: residual_floor(e, batch.t[k], floors[k])) \
            if synthesis else None
        return alt if builtin or prop is not None else None

    return rescore


def _nested_options(opts, fit_options: dict) -> dict:
    """The nested diagnosis's options: the base fit's folds and dT/dt window (``opts``), the
    caller's fit options, no synthesis, and no second motion check (:func:`_nested`)."""
    nested = {"n_blocks": opts.n_blocks, "n_folds": opts.n_folds,
              "dtemp_window": opts.dtemp_window, "synthesis": False, **fit_options}
    if not fit_options.get("static_only"):  # (static_only fits the check's rests)
        nested["check_motion"] = False
    return nested


def _nested(*args, **kwargs) -> Diagnosis:
    """The greedy pair's nested diagnosis: its residual's noise is not reported, and its
    fit does not check the recordings for motion again: a pair is formed only for a device
    the base fit's check found fit to judge."""
    return diagnose(*args, noise=False, **kwargs)


def _in_units(devices, channel: str) -> None:
    """The explanations in the channel's unit (the accelerometer's measurement is in m/s²,
    where the wording is the gyro's rad/s)."""
    if channel != "gyro":
        for d in devices:
            d.explanation = d.explanation.replace("rad/s", UNITS[channel])


def _base_fit(model, batch: Batch, base_fit, channel: str, fit_options: dict):
    """The fit the diagnosis starts from and the batch its candidates are scored on (the
    accelerometer less its gravity reference, on that channel)."""
    extra = {} if channel == "gyro" else {"channel": channel}
    res = base_fit if base_fit is not None else fit_fn(model, batch, **fit_options, **extra)
    if channel != "gyro":  # several orientations: the rests the fit read, gravity their input
        static = res.motion.static if reads_gravity(model) else None
        batch, _ = as_channel(batch, channel, getattr(res, "reference", None), static=static,
                              gravity=fit_options.get("gravity", GRAVITY))
    return res, batch


def diagnose(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    candidates: list[str] | None = None,
    *,
    thresholds: Thresholds | None = None,
    base_fit=None,
    greedy: bool = True,
    synthesis: bool = True,
    noise="auto",
    progress=None,
    channel: str = "gyro",
    **fit_options,
) -> Diagnosis:
    """Diagnose every device of ``batch`` against ``model``.

    ``candidates`` limits the effects tried (names or terms, default: every
    registered effect the data supports). ``base_fit`` reuses a
    :class:`~diffgyro.fit.FitResult` of ``model`` on this batch. Other
    keywords are fit options (``n_folds``, ``n_blocks``, ``dtemp_window``...).
    ``greedy``: before a random walk is named, try the best term followed by the
    best second term (:mod:`.greedy`). ``synthesis``: where no built-in term closes the
    gap, propose a term built from the recording's signals (:mod:`.synthesis`).
    ``noise``: identify the residual's stochastic model ("auto": where the residual is not
    white and no term explains it, ``adequate`` included; True: every judged device; False:
    none; :mod:`.noise_model`).
    ``progress`` is called with a line of text before each stage (the base fit, the
    candidates' ranges, each chunk of devices scored, the pairs, synthesis, noise).
    ``channel="accel"`` diagnoses the accelerometer's thermal offset (relative to its
    gravity reference, :mod:`diffgyro.channel`): the base fit judges rest on the IMU as
    loaded, and the candidates are scored on the accelerometer less its reference.
    Returns a :class:`Diagnosis`; ``.to_json()`` is the ``diagnose --json``
    object.

    **Arguments:**

    - ``model``: the base model: a spec string or an :class:`~diffgyro.model.ErrorModel`.
    - ``batch``: a Batch, one Recording or a list of them.
    - ``candidates``: the effects tried, names or terms (default: every registered effect
      the data supports).
    - ``thresholds``: the decision's :class:`Thresholds` (default: the calibrated ones).
    - ``base_fit``: a :class:`~diffgyro.fit.FitResult` of ``model`` on this batch, reused
      instead of fitting again.
    - ``greedy``: try the best term followed by the best second term before a random walk is
      named.
    - ``synthesis``: propose a term built from the recording's signals where no built-in
      term closes the gap.
    - ``noise``: identify the residual's stochastic model: ``"auto"``, True (every judged
      device) or False.
    - ``progress``: called with a line of text before each stage.
    - ``channel``: ``"gyro"`` or ``"accel"`` (the accelerometer's thermal offset).
    - ``**fit_options``: fit options (``n_folds``, ``n_blocks``, ``dtemp_window``, …).
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    if model.noise is not None:
        raise SpecError(f"diagnose takes a deterministic model, not {model.spec!r}",
                        hint=f"drop {model.noise.spec} from --model: it is tried as a candidate")
    batch = as_batch(batch)
    say = progress or (lambda _text: None)
    th = thresholds or Thresholds()
    if "dtemp_window" not in fit_options and base_fit is None:
        fit_options["dtemp_window"] = suggest_dtemp_window(batch)
    channel = check_channel(channel)
    # on the gyro the batch scored is the one fitted: the plan can be formed before the fit
    plan = None
    if base_fit is None and channel == "gyro":
        first = first_programs(batch)
        plan = planned_ahead(model, batch, candidates, fit_options, say, first)
        first()  # (where no plan was formed ahead)
    if base_fit is None:
        say(f"fitting {model.spec} on {batch.n_devices} device(s)")
    res, batch = _base_fit(model, batch, base_fit, channel, fit_options)
    plan = plan_of_fit(plan, model, batch, res, candidates, say)
    cands, unsupported, rw_spec, floors, skips = (plan.cands, plan.unsupported, plan.rw_spec,
                                                  plan.floors, plan.skips)
    ahead = plan.ahead or (None, None, None)
    out = score(model, cands, batch, plan.setting, res.params, floors, plan.aux, say,
                 None if ahead[1] is None else ahead[:2])
    ranges = plan.all_ranges[:, plan.usable]
    say("Allan deviation of the residuals")
    al = allan(out["residual"], batch, ahead[2])
    reported = _reported_floor(batch, res)
    devices, slopes, floor_allans = [], [], []
    host = res.on_host()  # read device by device: indexing JAX arrays compiles programs
    for i in range(batch.n_devices):
        d, slope, fa = _device(i, batch, host, out, cands, ranges, floors, al, rw_spec, th, model,
                               unsupported, skips[i])
        d.noise_floor, d.noise_axes = reported[i]
        devices.append(d)
        slopes.append(slope)
        floor_allans.append(fa)
    opts = res.options
    if greedy:
        say("trying the best term followed by a second")
        pairs = greedy_pairs(devices, batch, candidates, th, _nested_options(opts, fit_options),
                             _nested)
        for i, pair in pairs.items():
            devices[i] = _device(i, batch, host, out, cands, ranges, floors, al, rw_spec, th,
                                 model, unsupported, skips[i], pair)[0]
            devices[i].noise_floor, devices[i].noise_axes = reported[i]
    if synthesis:
        say("proposing terms built from the recording's signals")
        synthesise(devices, batch, res, model, cands, ranges <= 0, th)
    rescore = _rescorer(devices, batch, res, out, cands, ranges, floors, al, rw_spec, th, model,
                        unsupported, skips, reported, synthesis)
    say("identifying the residual's noise")
    attach_noise(devices, out["residual"], batch.n_valid, batch.t, noise, rescore, th.excess_min)
    _in_units(devices, getattr(res, "channel", "gyro"))
    raw = {k: v for k, v in out.items() if k not in ("residual", "dtemp", "heating")}
    return Diagnosis(model=model, devices=devices, fit=res, residuals=out["residual"], allan=al,
                     thresholds=th, options={"n_blocks": opts.n_blocks, "n_folds": opts.n_folds,
                                             "dtemp_window": opts.dtemp_window},
                     raw={**raw, "floors": floors, "ok": ranges <= 0, "slope": np.asarray(slopes),
                          "floor_allan": np.asarray(floor_allans), "candidates": cands,
                          "n_valid": np.asarray(batch.n_valid)})
