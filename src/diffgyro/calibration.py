"""Calibration files: versioned, strictly validated JSON; and compensation with them.

A calibration file holds, per device, everything needed to turn measured
rates into true rates: the model spec, the temperature centring, the
calibrated temperature range, the per-axis coefficients (in model order, and
labelled with units for people), the shared time constants, the fit quality
and status. It never holds code: loading it parses plain JSON against a
fixed schema (no pickle, no eval), so a file from elsewhere is safe to read.

The formula (also in :mod:`diffgyro.apply`, numpy only)::

    T_s   = (clip(T, T_lo, T_hi) - centre) / scale      (an extra column x of an aux
                                                          term likewise, with its own)
    gyro  = Ω + Σ_terms columns(Ω, T_s, dT/dt, ...) @ beta      (per axis)

and compensation solves it for Ω.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from . import __version__, apply
from ._jsonio import atomic_write_text, dumps, to_json_safe
from ._term_info import KINDS, ModelInfo, model_info
from ._vocabulary import CHANNELS, MAX_INTERVALS, STATUS_NAMES, UNITS, VERDICT_NAMES, aux_names
from .data import SIGNALS, Batch, Recording, as_batch
from .errors import DataError, SpecError

if TYPE_CHECKING:
    from ._fit_result import AbstractFitResult
    from .model import ErrorModel

__all__ = ["from_fit", "save", "load", "compensate", "Calibration", "DeviceCalibration",
           "from_json", "units_of", "entry_json", "data_hash", "FORMAT", "FORMAT_VERSION"]

FORMAT = "diffgyro-calibration"
FORMAT_VERSION = 1
MAX_FILE_BYTES = 256 * 1024 * 1024


@dataclass
class DeviceCalibration:
    """One device's calibration (plain Python values, JSON-ready)."""

    device: str
    status: str
    beta: list[list[float]]            # 3 axes × p, model order
    theta: list[float]                 # shared nonlinear parameters, solver space (log τ)
    temp_centre: float = 0.0
    temp_scale: float = 1.0
    temp_range: list[float] | None = None
    quality: dict = field(default_factory=dict)
    params: dict = field(default_factory=dict)   # labelled copy for people (units in `units`)
    status_detail: str = ""
    #: Per extra column an ``aux(NAME)`` term reads: {"centre", "scale", "range": [lo, hi]}.
    aux: dict = field(default_factory=dict)
    #: Pass/fail against a limits file (:mod:`diffgyro.limits`): {"result", "broken"}.
    limits: dict = field(default_factory=dict)
    #: The motion check of the recording (:mod:`diffgyro.motion`; rad/s, fractions 0..1).
    motion: dict = field(default_factory=dict)
    #: Fitted from the detected static intervals only.
    static_only: bool = False
    #: Accelerometer channel: the gravity reference subtracted before the fit (m/s², the
    #: median reading at rest; :mod:`diffgyro.channel`), None for the gyro.
    reference: list[float] | None = None
    #: The sensor's id where the log gives one (PX4's ``device_id``), else None.
    device_id: int | None = None


@dataclass
class Calibration:
    """A calibration of one or many devices with one error model."""

    model: str
    devices: list[DeviceCalibration]
    dtemp_window: float = 60.0
    created: str = ""
    diffgyro_version: str = ""
    input_hash: str | None = None
    units: dict = field(default_factory=dict)
    format: str = FORMAT
    format_version: int = FORMAT_VERSION
    #: The batch's pass/fail summary (:func:`diffgyro.limits.summary`), when checked.
    limits: dict = field(default_factory=dict)
    #: The sensor calibrated: ``gyro`` or ``accel`` (:mod:`diffgyro.channel`).
    channel: str = "gyro"
    #: Accelerometer in several orientations: the gravity (m/s²) its scale is relative to.
    gravity: float | None = None

    @property
    def error_model(self) -> ErrorModel:
        """The model as the fit and compensation run it (imports JAX)."""
        from .model import ErrorModel

        return ErrorModel.from_spec(self.model)

    @property
    def model_info(self) -> ModelInfo:
        """The model's terms as export and the file's checks read them (without JAX)."""
        return model_info(self.model)

    def device(self, name: str) -> DeviceCalibration:
        for d in self.devices:
            if d.device == name:
                return d
        raise SpecError(f"device {name!r} is not in the calibration",
                        hint=f"it has {', '.join(d.device for d in self.devices[:10])}")

    def to_json(self) -> dict:
        return {
            "format": self.format, "format_version": self.format_version,
            "model": self.model, "dtemp_window": self.dtemp_window,
            "created": self.created, "diffgyro_version": self.diffgyro_version,
            "input_hash": self.input_hash, "units": self.units,
            "devices": [entry_json(d.__dict__) for d in self.devices],
        } | ({"limits": self.limits} if self.limits else {}) | (
            {"channel": self.channel} if self.channel != "gyro" else {}) | (
            {"gravity": self.gravity} if self.gravity is not None else {})


def entry_json(fields: dict) -> dict:
    """A device entry as written: JSON-safe, without an empty ``aux``, ``limits`` or ``motion``
    block and without ``static_only`` when false.

    **Arguments:**

    - ``fields``: the device entry's fields."""
    return to_json_safe({k: v for k, v in fields.items()
                         if k not in ("aux", "limits", "motion", "static_only", "reference",
                                      "device_id") or v is not None and v is not False and v != {}})


def data_hash(batch: Batch) -> str:
    """SHA-256 of the valid samples of every device (order of devices included).

    **Arguments:**

    - ``batch``: the batch.
    """
    h = hashlib.sha256()
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        h.update(batch.devices[i].encode())
        for s in batch.signals:
            arr = getattr(batch, s)
            h.update(s.encode())
            h.update(np.ascontiguousarray(np.asarray(arr[i, :n], np.float64)).tobytes())
        for s, arr in batch.aux.items():
            h.update(("aux:" + s).encode())
            h.update(np.ascontiguousarray(np.asarray(arr[i, :n], np.float64)).tobytes())
    return "sha256:" + h.hexdigest()


def units_of(model: ErrorModel | ModelInfo, channel: str = "gyro") -> dict:
    """The unit of each term's coefficients, and of tau, rates and temperature (the
    accelerometer channel's measurement is in m/s² where the gyro's is in rad/s).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``channel``: ``"gyro"`` or ``"accel"``.
    """
    def unit(text: str) -> str:
        return text if channel == "gyro" else text.replace("rad/s", UNITS[channel])

    out = {t.spec: unit(t.unit) for t in model.terms} | {"tau": "s", "rates": "rad/s",
                                                          "temperature": "°C"}
    return out if channel == "gyro" else out | {"measurement": UNITS[channel]}


def aux_entries(result: AbstractFitResult, i: int) -> dict:
    """Device ``i``'s centre, scale and calibrated range of every extra column the fit read."""
    return {k: {"centre": float(nm.centre[i]), "scale": float(nm.scale[i]),
                "range": np.asarray(result.aux_range[k][i], float).tolist()}
            for k, nm in result.aux_norm.items()}


def from_fit(result: AbstractFitResult, batch: Batch | None = None,
             device_ids: dict[str, int] | None = None) -> Calibration:
    """A calibration file's content from a fit.

    **Arguments:**

    - ``result``: the fit's result (:func:`diffgyro.fit.fit`).
    - ``batch``: the data fitted; adds the input hash.
    - ``device_ids``: the sensors' ids by device, as a log gives them.
    """
    result = result.on_host()  # numpy copies: indexing a JAX array compiles a program
    ref = getattr(result, "reference", None)
    ids = device_ids or {}

    devices = []
    for i in range(result.n_devices):
        s = result.summary(i)
        devices.append(DeviceCalibration(
            device=result.devices[i], status=s["status"], status_detail=s["status_detail"],
            beta=np.asarray(result.params.beta[i], float).tolist(),
            theta=np.asarray(result.params.theta[i], float).tolist(),
            temp_centre=float(result.norm.centre[i]), temp_scale=float(result.norm.scale[i]),
            temp_range=None if result.temp_range is None else
            np.asarray(result.temp_range[i], float).tolist(),
            quality={k: s[k] for k in ("rms", "heldout_rms", "noise_floor", "n_samples", "steps")},
            params=s["params"],
            aux=aux_entries(result, i), motion=s.get("motion") or {},
            static_only=bool(s.get("static_only", False)),
            reference=None if ref is None else np.asarray(ref[i], float).tolist(),
            device_id=ids.get(result.devices[i])))
    return Calibration(
        model=result.model.spec, devices=devices, dtemp_window=float(result.options.dtemp_window),
        created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        diffgyro_version=__version__, input_hash=None if batch is None else data_hash(batch),
        units=units_of(result.model, getattr(result, "channel", "gyro")),
        channel=getattr(result, "channel", "gyro"), gravity=getattr(result, "gravity", None))


def save(cal: Calibration, path: str | os.PathLike) -> None:
    """Write ``cal`` as JSON in one atomic step (a reader never sees half a file).

    **Arguments:**

    - ``cal``: the :class:`Calibration`.
    - ``path``: the file to write.
    """
    atomic_write_text(path, dumps(cal.to_json(), indent=1) + "\n")


# --------------------------------------------------------------------------- strict loading


def _req(obj: dict, key: str, kind, where: str):
    if not isinstance(obj, dict) or key not in obj:
        raise SpecError(f"calibration file: missing {key!r} in {where}")
    val = obj[key]
    if kind is float:
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise SpecError(f"calibration file: {where}.{key} must be a number")
        return _finite(val, f"{where}.{key}")
    if not isinstance(val, kind) or isinstance(val, bool) and kind is not bool:
        raise SpecError(f"calibration file: {where}.{key} must be {kind.__name__}")
    return val


def _floats(val, shape: tuple[int, ...], where: str, allow_null: bool = False) -> list:
    arr = val
    try:
        a = np.array([[np.nan if (x is None and allow_null) else x for x in row] for row in arr]
                     if len(shape) == 2 else [np.nan if (x is None and allow_null) else x
                                              for x in arr], dtype=object)
    except TypeError:
        raise SpecError(f"calibration file: {where} must be a list of numbers") from None
    if a.shape != shape or any(isinstance(x, bool) or not isinstance(x, (int, float))
                               for x in a.ravel()):
        raise SpecError(f"calibration file: {where} must be numbers of shape {list(shape)}")
    return np.array([_finite(x, where, allow_nan=True) for x in a.ravel()],
                    float).reshape(shape).tolist()


def _finite(x, where: str, allow_nan: bool = False) -> float:
    """A JSON number as a float; integers too large for a float are an error, not a crash."""
    try:
        v = float(x)
    except OverflowError:
        raise SpecError(f"calibration file: {where} holds a number too large") from None
    if not math.isfinite(v) and not (allow_nan and math.isnan(v)):
        raise SpecError(f"calibration file: {where} holds a non-finite number")
    return v


_FILE_KEYS = frozenset({"format", "format_version", "model", "dtemp_window", "created",
                        "diffgyro_version", "input_hash", "units", "devices", "limits",
                        "channel", "gravity"})
_DEVICE_KEYS = frozenset({"device", "status", "beta", "theta", "temp_centre", "temp_scale",
                          "temp_range", "quality", "params", "status_detail", "aux", "limits",
                          "motion", "static_only", "reference", "device_id"})
MAX_THETA = 700.0        # |log τ|: beyond this exp() overflows
MAX_DTEMP_WINDOW = 1e6   # s
MAX_NAME = 1000


def _known_keys(obj: dict, allowed: frozenset, where: str) -> None:
    unknown = sorted(str(k) for k in obj if k not in allowed)
    if unknown:
        raise SpecError(f"calibration file: unknown key {unknown[0][:40]!r} in {where}",
                        hint="a calibration file holds only the fields diffgyro writes")


def _text(obj: dict, key: str, where: str, default: str = "") -> str:
    val = obj.get(key, default)
    if not isinstance(val, str):
        raise SpecError(f"calibration file: {where}.{key} must be text")
    return val


def _flat_numbers(val, where: str, max_items: int = 256) -> dict:
    """An object of name -> finite number or null (fit quality, labelled parameters)."""
    if not isinstance(val, dict) or len(val) > max_items:
        raise SpecError(f"calibration file: {where} must be an object of numbers")
    out = {}
    for k, v in val.items():
        if not isinstance(k, str) or len(k) > MAX_NAME:
            raise SpecError(f"calibration file: {where} has a bad key")
        if v is None:
            out[k] = None
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SpecError(f"calibration file: {where}.{k[:40]} must be a number or null")
        elif isinstance(v, int):
            _finite(v, f"{where}.{k[:40]}")
            out[k] = v
        else:
            out[k] = None if math.isnan(v) else _finite(v, f"{where}.{k[:40]}")
    return out


def _motion_record(val, where: str) -> dict:
    """A ``motion`` object (:meth:`diffgyro.motion.Motion.record`): numbers, the verdict's
    name, its reason in words, and the intervals of rest a fit kept."""
    if not isinstance(val, dict):
        raise SpecError(f"calibration file: {where} must be an object")
    text = {k: val[k] for k in ("verdict", "reason") if k in val}
    spans = val.get("rest_intervals")
    out = _flat_numbers({k: v for k, v in val.items() if k not in text and k != "rest_intervals"},
                        where, 24)
    if "verdict" in text and text["verdict"] not in VERDICT_NAMES:
        raise SpecError(f"calibration file: {where}.verdict must be one of {VERDICT_NAMES}")
    if "reason" in text and (not isinstance(text["reason"], str) or len(text["reason"]) > 2000):
        raise SpecError(f"calibration file: {where}.reason must be a text of at most 2000 characters")
    if spans is not None:
        if (not isinstance(spans, list) or len(spans) > MAX_INTERVALS
                or not all(isinstance(x, list) and len(x) == 3 for x in spans)):
            raise SpecError(f"calibration file: {where}.rest_intervals must be a list of at most "
                            f"{MAX_INTERVALS} [start, end, length] triples")
        out["rest_intervals"] = [list(_flat_numbers(dict(zip("abc", x)), f"{where}.rest_intervals",
                                                    3).values()) for x in spans]
    return out | text


def _flag(obj: dict, key: str, where: str) -> bool:
    val = obj.get(key, False)
    if not isinstance(val, bool):
        raise SpecError(f"calibration file: {where}.{key} must be true or false")
    return val


def _device_name(name: str, where: str) -> str:
    if not name.strip() or len(name) > MAX_NAME:
        raise SpecError(f"calibration file: {where}.device must be 1 to {MAX_NAME} characters")
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in name):
        raise SpecError(f"calibration file: {where}.device holds control characters")
    return name


def _channel(obj: dict, devices: list[DeviceCalibration]) -> str:
    """The file's channel, validated (an accelerometer's devices each need a reference)."""
    channel = obj.get("channel", "gyro")
    if channel not in CHANNELS:
        raise SpecError(f"calibration file: channel must be one of {', '.join(CHANNELS)}")
    if channel != "gyro" and any(d.reference is None for d in devices):
        raise SpecError("calibration file: an accelerometer calibration needs each device's "
                        "reference")
    return channel


def _gravity(obj: dict) -> float | None:
    """The file's gravity (an accelerometer's in several orientations), validated."""
    if "gravity" not in obj:
        return None
    g = _req(obj, "gravity", float, "file")
    if obj.get("channel") != "accel" or not (math.isfinite(g) and 1.0 < g < 30.0):
        raise SpecError("calibration file: gravity must be an accelerometer calibration's "
                        "local gravity in m/s² (between 1 and 30)")
    return g


def _sensor_fields(d: dict, where: str) -> tuple[list[float] | None, int | None]:
    """A device entry's gravity reference and sensor id, validated (None where absent)."""
    ref = d.get("reference")
    if ref is not None:
        ref = _floats(ref, (3,), f"{where}.reference")
        if not all(math.isfinite(x) for x in ref):
            raise SpecError(f"calibration file: {where}.reference must be finite")
    dev_id = d.get("device_id")
    if dev_id is not None and (isinstance(dev_id, bool) or not isinstance(dev_id, int)
                               or not 0 <= dev_id < 2**32):
        raise SpecError(f"calibration file: {where}.device_id must be an integer 0..2^32-1")
    return ref, dev_id


def from_json(obj) -> Calibration:
    """Validate a parsed calibration file against the schema; SpecError on anything odd.

    **Arguments:**

    - ``obj``: the parsed JSON (any value: whatever is not a valid file is refused).
    """
    if not isinstance(obj, dict):
        raise SpecError("calibration file: top level must be a JSON object")
    if obj.get("format") != FORMAT:
        raise SpecError(f"calibration file: 'format' must be {FORMAT!r}")
    _known_keys(obj, _FILE_KEYS, "the file")
    version = _req(obj, "format_version", int, "file")
    if version > FORMAT_VERSION or version < 1:
        raise SpecError(f"calibration file: format_version {version} is not supported "
                        f"(this diffgyro reads 1..{FORMAT_VERSION})")
    spec = _req(obj, "model", str, "file")
    model = model_info(spec)
    p, q = model.n_params, model.n_nonlinear
    devs = _req(obj, "devices", list, "file")
    if not devs:
        raise SpecError("calibration file: no devices")
    out, seen = [], set()
    for k, d in enumerate(devs):
        where = f"devices[{k}]"
        name = _device_name(_req(d, "device", str, where), where)
        _known_keys(d, _DEVICE_KEYS, where)
        if name in seen:
            raise SpecError(f"calibration file: device {name!r} appears twice")
        seen.add(name)
        status = _req(d, "status", str, where)
        if status not in STATUS_NAMES:
            raise SpecError(f"calibration file: {where}.status {status!r} is not one of {STATUS_NAMES}")
        ok = status == "ok"
        beta = _floats(_req(d, "beta", list, where), (3, p), f"{where}.beta", allow_null=not ok)
        theta = _floats(_req(d, "theta", list, where), (q,), f"{where}.theta", allow_null=not ok)
        centre = _req(d, "temp_centre", float, where)
        scale = _req(d, "temp_scale", float, where)
        if not (math.isfinite(centre) and math.isfinite(scale) and scale > 0):
            raise SpecError(f"calibration file: {where} temperature centring is invalid")
        tr = d.get("temp_range")
        if tr is not None:
            tr = _floats(tr, (2,), f"{where}.temp_range")
            if not all(math.isfinite(x) for x in tr):
                raise SpecError(f"calibration file: {where}.temp_range must be finite")
            if not tr[0] <= tr[1]:
                raise SpecError(f"calibration file: {where}.temp_range is reversed")
        if ok and not (np.all(np.isfinite(beta)) and np.all(np.isfinite(theta))):
            raise SpecError(f"calibration file: {where} has status ok but non-finite coefficients")
        if np.any(np.abs(np.asarray(theta, float)) > MAX_THETA):
            raise SpecError(f"calibration file: {where}.theta: a time constant is out of range "
                            f"(|log τ| > {MAX_THETA:g})")
        quality = _flat_numbers(d.get("quality", {}), f"{where}.quality")
        params = d.get("params", {})
        if not isinstance(params, dict) or len(params) > 16:
            raise SpecError(f"calibration file: {where}.params must be an object of groups")
        params = {g: _flat_numbers(v, f"{where}.params.{str(g)[:40]}") for g, v in params.items()}
        ref, dev_id = _sensor_fields(d, where)
        out.append(DeviceCalibration(device=name, status=status, beta=beta, theta=theta,
                                     temp_centre=centre, temp_scale=scale, temp_range=tr,
                                     quality=quality, params=params,
                                     status_detail=_text(d, "status_detail", where),
                                     aux=_aux_entries(d.get("aux", {}), model, where),
                                     limits=_limits_entry(d.get("limits", {}), where),
                                     motion=_motion_record(d.get("motion", {}), f"{where}.motion"),
                                     static_only=_flag(d, "static_only", where),
                                     reference=ref, device_id=dev_id))
    window = _req(obj, "dtemp_window", float, "file")
    if not (0 < window <= MAX_DTEMP_WINDOW):
        raise SpecError(f"calibration file: dtemp_window must be a positive number of seconds "
                        f"up to {MAX_DTEMP_WINDOW:g}")
    ih = obj.get("input_hash")
    if ih is not None and not isinstance(ih, str):
        raise SpecError("calibration file: input_hash must be text or null")
    units = obj.get("units", {})
    if not isinstance(units, dict) or len(units) > 256 or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in units.items()):
        raise SpecError("calibration file: units must be an object of texts")
    lim = obj.get("limits", {})
    if not isinstance(lim, dict):
        raise SpecError("calibration file: limits must be an object")
    return Calibration(model=model.spec, devices=out, dtemp_window=window,
                       channel=_channel(obj, out), gravity=_gravity(obj),
                       created=_text(obj, "created", "file"),
                       diffgyro_version=_text(obj, "diffgyro_version", "file"),
                       input_hash=ih, units=dict(units), limits=lim)


def _limits_entry(val, where: str) -> dict:
    """A device's pass/fail against a limits file: ``{"result": "pass"|"fail", "broken": [...]}``."""
    if val == {}:
        return {}
    if (not isinstance(val, dict) or val.get("result") not in ("pass", "fail")
            or not isinstance(val.get("broken"), list)
            or not all(isinstance(b, dict) for b in val["broken"])):
        raise SpecError(f"calibration file: {where}.limits must be {{'result': 'pass' or 'fail', "
                        f"'broken': [...]}}")
    return val


def _aux_entries(val, model: ModelInfo, where: str) -> dict:
    """The extra columns' centring and calibrated range: exactly those the model reads."""

    names = aux_names(model.requires())
    if not isinstance(val, dict) or sorted(val) != list(names):
        raise SpecError(f"calibration file: {where}.aux must describe the extra columns "
                        f"{', '.join(names) or '(none)'} of the model")
    out = {}
    for name in names:
        w = f"{where}.aux.{name}"
        e = val[name]
        _known_keys(e, frozenset({"centre", "scale", "range"}), w)
        centre, scale = _req(e, "centre", float, w), _req(e, "scale", float, w)
        rng = _floats(_req(e, "range", list, w), (2,), f"{w}.range")
        if not scale > 0 or not all(math.isfinite(x) for x in rng) or not rng[0] <= rng[1]:
            raise SpecError(f"calibration file: {w} centring or range is invalid")
        out[name] = {"centre": centre, "scale": scale, "range": rng}
    return out


def load(path: str | os.PathLike) -> Calibration:
    """Read and validate a calibration file (SpecError naming the file on any problem).

    **Arguments:**

    - ``path``: the calibration file.
    """
    path = os.fspath(path)
    try:
        if os.path.getsize(path) > MAX_FILE_BYTES:
            raise SpecError("calibration file is too large", file=path)
        with open(path, encoding="utf-8") as f:
            obj = json.load(f, parse_constant=_reject_constant,
                            object_pairs_hook=_reject_duplicate_keys)
    except SpecError as err:
        raise SpecError(err.problem, file=path, hint=err.hint) from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        raise SpecError(f"cannot read calibration file: {err}".splitlines()[0], file=path) from None
    try:
        return from_json(obj)
    except SpecError as err:
        raise SpecError(err.problem, file=path, hint=err.hint) from None


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def _reject_duplicate_keys(pairs: list) -> dict:
    """JSON objects with a key twice are refused: two readers could see two different files."""
    out = {}
    for k, v in pairs:
        if k in out:
            raise SpecError(f"calibration file: key {k[:40]!r} appears twice in one object")
        out[k] = v
    return out


# --------------------------------------------------------------------------- compensation


def compensate(cal: Calibration, data: Batch | Recording | list[Recording],
               engine: str = "jax") -> tuple[Batch, dict]:
    """Corrected rates for every device of ``data`` that the calibration knows.

    Temperatures outside a device's calibrated range are clamped to it (as
    PX4 does) and counted; the counts come back in the second value, keyed
    by device. A device whose calibration is not ``ok`` is an error.

    **Arguments:**

    - ``cal``: the :class:`Calibration` (:func:`load`).
    - ``data``: a Batch, one Recording or a list of them, devices named as in ``cal``.
    - ``engine``: ``"jax"``, the error model itself (compiled, every device at once), or
      ``"numpy"``, :func:`diffgyro.apply.compensate` device by device, which needs no JAX
      (``diffgyro compensate`` runs it; the two agree to about 1e-13 rad/s, not to the
      last bit). A model with a user's registered term runs in JAX either way.
    """
    if engine not in ("jax", "numpy"):
        raise ValueError(f"engine must be 'jax' or 'numpy', not {engine!r}")
    batch = as_batch(data)
    if cal.channel != "gyro":
        raise SpecError(f"this is a calibration of the {cal.channel} channel; this "
                        "compensation applies gyro calibrations", hint="apply it with "
                        "diffgyro.apply.compensate_accel ('diffgyro compensate' does), or export "
                        "it to the autopilot (diffgyro export CAL --format px4|ardupilot)")
    info = cal.model_info
    # the true rate a scale term reads is what compensation solves for, not an input
    missing = {s for s in info.requires() if s in SIGNALS and s != "rate"} - set(batch.signals)
    if missing:
        raise DataError(f"model {cal.model!r} needs {', '.join(sorted(missing))}, not in the data",
                        file=batch.sources[0] if batch.sources else None)
    devs = [cal.device(name) for name in batch.devices]
    for d in devs:
        if d.status != "ok":
            why = d.status_detail if d.status_detail not in ("", d.status) else d.status
            raise SpecError(f"calibration of device {d.device!r} is not ok ({why}); "
                            "refusing to apply it", device=d.device)
    if engine == "jax" or any(t.name not in KINDS for t in info.parts):
        from ._compensate import compensate_batch

        return compensate_batch(cal, batch, devs)
    names = aux_names(info.requires())
    if names:
        from ._aux import check_columns

        check_columns(batch, names, vary=False)
    omega = np.zeros(np.shape(batch.gyro), np.float64)
    clamped: dict[str, int] = {}
    for i, d in enumerate(devs):
        n = int(batch.n_valid[i])
        rows = {s: None if getattr(batch, s) is None else np.asarray(getattr(batch, s)[i, :n],
                                                                       np.float64)
                for s in ("t", "gyro", "temp", "temp_ext", "accel")}
        if rows["temp"] is not None and "temp" in info.requires() and d.temp_range is not None:
            outside = int(np.sum((rows["temp"] < d.temp_range[0]) | (rows["temp"] > d.temp_range[1])))
            if outside:
                clamped[d.device] = outside
        doc = {"model": cal.model, "dtemp_window": cal.dtemp_window, "devices": [d.__dict__]}
        omega[i, :n] = apply.compensate(doc, d.device, **rows, aux={
            k: np.asarray(batch.aux[k][i, :n], np.float64) for k in names})
    if clamped:
        warnings.warn("temperature outside the calibrated range was clamped for "
                      + ", ".join(f"{k} ({v} samples)" for k, v in clamped.items()), stacklevel=2)
    return dataclasses.replace(batch, gyro=omega), clamped
