"""The known truth of a simulated batch: coefficients, noise levels, plan details.

Coefficients are in the error model's basis: ``beta[d, i, :]`` are device
``d``'s per-axis linear coefficients of the effect terms in model order, and
temperature polynomials are in ``T_s = (T − norm.centre) / norm.scale`` with
the truth's fixed :class:`~diffgyro.signals.TempNorm`. A fit given the same
norm (``fit(spec, batch, norm=truth.norm)``) estimates these numbers
directly; :meth:`Truth.params_for` re-expresses them for any other norm
(for example a fit's own per-device norm).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from .._jsonio import atomic_write_text, dumps, to_json_safe
from ..effects import BiasPoly, ScalePoly, ThermalLag
from ..errors import SpecError
from ..model import ErrorModel, Params
from ..signals import TempNorm
from ._noise import NoiseLevels

FORMAT = "diffgyro-truth"
VERSION = 1


def rebase(model: ErrorModel, params: Params, old: TempNorm, new: TempNorm) -> Params:
    """The same device physics with temperature polynomials in another TempNorm.

    ``T_s,old = A·T_s,new + B`` with ``A = s_new/s_old``, ``B = (c_new − c_old)/s_old``;
    every polynomial ``Σ_j β_j T_s,old^j`` (bias_poly, scale_poly and the
    lag differences of thermal_lag) is expanded in ``T_s,new``. Norms may be
    scalars or per device (leading axis of ``params``).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel` of ``params``.
    - ``params``: the coefficients in the ``old`` normalisation.
    - ``old``: the :class:`~diffgyro.signals.TempNorm` they refer to.
    - ``new``: the one to express them in.
    """
    beta = np.array(params.beta, dtype=float, copy=True)
    lead = beta.shape[:-2]
    c0, s0 = (np.broadcast_to(np.asarray(x, float), lead) for x in (old.centre, old.scale))
    c1, s1 = (np.broadcast_to(np.asarray(x, float), lead) for x in (new.centre, new.scale))
    a = s1 / s0
    b = (c1 - c0) / s0
    for term, sl, _ in model.slices():
        if isinstance(term, BiasPoly | ScalePoly):
            lo = 0
        elif isinstance(term, ThermalLag):
            lo = 1
        else:
            continue
        k = term.order
        j = np.arange(k + 1)
        # M[..., j, m] = C(j, m) A^m B^(j−m) for m ≤ j
        comb = np.array([[math.comb(jj, m) if m <= jj else 0 for m in range(k + 1)] for jj in j])
        expo = np.clip(j[:, None] - j[None, :], 0, None)
        mat = comb * (a[..., None, None] ** j[None, :]) * (b[..., None, None] ** expo)
        mat = np.where(j[None, :] <= j[:, None], mat, 0.0)
        old_c = np.zeros(beta.shape[:-1] + (k + 1,))
        old_c[..., lo:] = beta[..., sl]
        new_c = np.einsum("...ij,...jm->...im", old_c, mat)
        beta[..., sl] = new_c[..., lo:]
    return Params(beta=beta, theta=np.asarray(params.theta, float).copy())


@dataclass(frozen=True)
class Truth:
    """Everything known about a simulated batch (see the module docstring for the basis).

    Fields: ``plan`` and its resolved ``options``; ``spec`` (the effects
    present); ``preset``; ``seed``; ``devices``; ``params`` (beta (d, 3, P),
    theta (d, Q) = log τ); ``norm``; ``noise`` (:class:`NoiseLevels`);
    ``thermal`` (per device ``tau_sensor``, ``self_heating``,
    ``tau_heating``: s, °C, s); ``accel`` (``bias`` (d, 3) m/s²,
    ``error_matrix`` K (d, 3, 3) with ``a_raw = (I + K)·f + bias``, and
    ``matrix`` = (I + K)⁻¹ in imucal's convention); ``outputs`` (optional
    columns written); ``segments`` (labelled windows with sample ranges);
    ``info`` (plan details: latitude, tilt, sections ...); ``env`` (true
    arrays, not saved to JSON: ``t``, ``temp``, ``dtemp``, ``chamber``,
    ``power_state`` and, if kept, ``error``, ``specific_force`` and noise parts).
    """

    plan: str
    options: dict
    spec: str
    preset: str
    seed: int
    devices: tuple[str, ...]
    params: Params
    norm: TempNorm
    noise: NoiseLevels
    thermal: dict
    accel: dict
    outputs: tuple[str, ...] = ()
    segments: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    env: dict = field(default_factory=dict, repr=False, compare=False)
    #: Centring of each extra column the true coefficients refer to (``aux(NAME)`` terms).
    aux_norm: dict = field(default_factory=dict)

    @property
    def model(self) -> ErrorModel:
        return ErrorModel.from_spec(self.spec)

    @property
    def n_devices(self) -> int:
        return len(self.devices)

    def device_params(self, i: int) -> Params:
        return Params(beta=np.asarray(self.params.beta)[i], theta=np.asarray(self.params.theta)[i])

    def params_for(self, norm: TempNorm) -> Params:
        """All devices' params with temperature polynomials in ``norm`` (scalar or per device)."""
        return rebase(self.model, self.params, self.norm, norm)

    def time_constants(self, i: int) -> dict[str, float]:
        """Device ``i``'s nonlinear parameters in seconds, by label."""
        labels = self.model.nonlinear_labels()
        return {lab: float(np.exp(v)) for lab, v in zip(labels, np.asarray(self.params.theta)[i])}

    def coefficients(self, i: int) -> dict:
        """Device ``i``'s coefficients by label (``term.coefficient``) per axis, in the
        same shape as a fit's ``param_dict`` (time constants under ``shared``)."""
        labels = self.model.param_labels()
        beta = np.asarray(self.params.beta)[i]
        out = {ax: {lab: float(v) for lab, v in zip(labels[k], beta[k])} for k, ax in enumerate("xyz")}
        tc = self.time_constants(i)
        if tc:
            out["shared"] = tc
        return out

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict:
        """JSON-ready truth (without the ``env`` arrays)."""
        model = self.model
        devices = []
        for i, dev in enumerate(self.devices):
            devices.append({
                "device": dev,
                "beta": np.asarray(self.params.beta)[i].tolist(),
                "theta": np.asarray(self.params.theta)[i].tolist(),
                "coefficients": self.coefficients(i),
                "noise": self.noise.device(i),
                "thermal": {k: float(np.asarray(v)[i]) for k, v in self.thermal.items()},
                "accel": {k: np.asarray(v)[i].tolist() for k, v in self.accel.items()},
            })
        return {
            "format": FORMAT, "version": VERSION,
            "plan": self.plan, "options": to_json_safe(self.options), "spec": self.spec,
            "preset": self.preset, "seed": int(self.seed),
            "norm": {"centre": float(self.norm.centre), "scale": float(self.norm.scale)},
            "labels": model.param_labels(), "nonlinear_labels": model.nonlinear_labels(),
            "units": {
                "beta": "model basis: rad/s per unit regressor; temperature polynomials in "
                        "T_s = (T - norm.centre) / norm.scale",
                "theta": "log of time constants in seconds",
                "arw": "rad/s/sqrt(Hz)", "rrw": "rad/s^2/sqrt(Hz)",
                "bias_instability": "rad/s (IEEE: Allan deviation floor = 0.664 * B)",
                "quantum": "rad/s", "accel_noise": "m/s^2/sqrt(Hz)", "temp": "degC",
            },
            "outputs": list(self.outputs),
            "devices": devices,
            "segments": to_json_safe(self.segments),
            "info": to_json_safe(self.info),
        }

    def to_json(self, path: str | Path | None = None, indent: int | None = 1) -> str:
        """The truth as JSON text; also written to ``path`` if given."""
        text = dumps(self.to_dict(), indent=indent)
        if path is not None:
            atomic_write_text(path, text + "\n")
        return text

    @classmethod
    def from_dict(cls, data: dict) -> Truth:
        if data.get("format") != FORMAT:
            raise SpecError("not a diffgyro truth file", hint=f"expected format {FORMAT!r}")
        devs = data["devices"]
        params = Params(beta=np.array([d["beta"] for d in devs], float).reshape(len(devs), 3, -1),
                        theta=np.array([d["theta"] for d in devs], float).reshape(len(devs), -1))
        noise_kw = {}
        for f in fields(NoiseLevels):
            vals = [d["noise"][f.name] for d in devs]
            noise_kw[f.name] = (np.array(vals, float) if isinstance(vals[0], list)
                                or f.name in ("quantum", "accel_noise") else float(vals[0]))
        return cls(
            plan=data["plan"], options=data["options"], spec=data["spec"], preset=data["preset"],
            seed=int(data["seed"]), devices=tuple(d["device"] for d in devs), params=params,
            norm=TempNorm(centre=np.float64(data["norm"]["centre"]),
                          scale=np.float64(data["norm"]["scale"])),
            noise=NoiseLevels(**noise_kw),
            thermal={k: np.array([d["thermal"][k] for d in devs]) for k in devs[0]["thermal"]},
            accel={k: np.array([d["accel"][k] for d in devs]) for k in devs[0]["accel"]},
            outputs=tuple(data.get("outputs", ())), segments=data.get("segments", []),
            info=data.get("info", {}),
        )

    @classmethod
    def load(cls, path: str | Path) -> Truth:
        """Read a truth file written by :meth:`to_json` (or ``diffgyro simulate``)."""
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
            raise SpecError(f"cannot read truth file ({err})", file=str(path)) from None


def truth_path(out: str | Path) -> Path:
    """Where the truth of data file ``out`` goes: ``x.csv`` -> ``x.truth.json``.

    **Arguments:**

    - ``out``: the data file's path.
    """
    out = Path(out)
    return out.with_name(out.name[: -len(out.suffix)] + ".truth.json" if out.suffix else out.name
                         + ".truth.json")


