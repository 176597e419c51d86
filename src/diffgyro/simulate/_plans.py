"""Test plans: the environment a batch of devices goes through, with known truth.

A plan turns its options into an :class:`Environment`: sample times, the
chamber temperature, the dissipated-power schedule, the true body rate, the
true specific force and the attitude (NWU frame, quaternions body → nav).
The simulator then adds the devices' thermal response, error model and
noise. Options are validated by name; every plan takes

* ``sample_rate`` (Hz), ``latitude`` (degrees; ``None`` = no Earth rate,
  except ``six_face`` which always includes it), ``g`` (m/s²) and
  ``temp_ext`` (report the chamber temperature as ``temp_ext``: bool).

The rate column carries the true inertial rate the gyro sees wherever it is
known: zero (plus Earth rate if a latitude is given) for static plans, the
table rate for rate tables, the Earth-rate projection (plus the turns) for
``six_face`` unless ``include_rate=False`` (a user of the cube-bias method would not know it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..errors import DataError
from ..signals import TempNorm
from ._motion import DEG, G0, Timeline, earth_rate_nav, face_quat, qexp, qmul, rotate, to_body
from ._population import stream

FACES = ("+z", "-z", "+y", "-y", "+x", "-x")


@dataclass
class Environment:
    """What every device of a plan experiences (arrays shared by all devices
    have no device axis; ``attitude`` gives each device its own motion)."""

    t: np.ndarray                     # (n,) s
    chamber: np.ndarray               # (n,) °C, chamber air = outside temperature
    power: np.ndarray                 # (n,) dissipated-power level (1 = nominal)
    settled: bool                     # powered long before t = 0 (no power-on transient)
    rate: np.ndarray                  # (n, 3) or (d, n, 3) true inertial body rate, rad/s
    specific_force: np.ndarray        # (n, 3) or (d, n, 3) true specific force, m/s²
    quat: np.ndarray                  # (n, 4) or (d, n, 4) attitude, body → NWU
    outputs: frozenset[str]           # optional columns reported: rate, quat, temp_ext, mag
    mag_field: np.ndarray | None = None  # NWU field vector (µT) when a magnetometer is simulated
    segments: list[dict] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])


class Plan:
    """Base of all test plans: option handling and the common options."""

    name: ClassVar[str]
    description: ClassVar[str]
    default_effects: ClassVar[str]
    default_preset: ClassVar[str] = "mems"
    default_accel_errors: ClassVar[bool] = False
    defaults: ClassVar[dict[str, Any]] = {}
    common: ClassVar[dict[str, Any]] = {"sample_rate": 2.0, "latitude": None, "g": G0,
                                        "temp_ext": True}

    def __init__(self, **options):
        valid = {**self.common, **self.defaults}
        unknown = sorted(set(options) - set(valid))
        if unknown:
            raise DataError(f"unknown option {unknown[0]!r} for plan {self.name!r}",
                            hint="valid: " + ", ".join(sorted(valid)))
        self.options = {**valid, **{k: v for k, v in options.items() if v is not None}}
        if options.get("latitude", "unset") is None:
            self.options["latitude"] = None
        if not float(self.options["sample_rate"]) > 0:
            raise DataError("sample_rate must be positive")

    @property
    def dt(self) -> float:
        return 1.0 / float(self.options["sample_rate"])

    def outputs(self, *extra: str) -> frozenset[str]:
        out = {"rate", *extra}
        if self.options["temp_ext"]:
            out.add("temp_ext")
        return frozenset(out)

    def temp_norm(self, env: Environment) -> TempNorm:
        """Fixed temperature normalisation of the truth: (25, 50) °C when the
        chamber stays within −25..75 °C, else the chamber's mid-range and a
        half-range rounded up to 5 °C plus a 5 °C margin for self-heating."""
        lo, hi = float(np.min(env.chamber)), float(np.max(env.chamber))
        if lo >= -25.0 and hi <= 75.0:
            return TempNorm(centre=np.float64(25.0), scale=np.float64(50.0))
        centre = 5.0 * round((lo + hi) / 10.0)
        half = max(abs(hi - centre), abs(centre - lo))
        return TempNorm(centre=np.float64(centre), scale=np.float64(5.0 * math.ceil(half / 5.0) + 5.0))

    def build(self, n_devices: int, seed: int) -> Environment:
        raise NotImplementedError

    def _from_timeline(self, tl: Timeline, settled: bool, outputs, info=None) -> Environment:
        o = self.options
        r = tl.render(self.dt, latitude=o["latitude"], g=float(o["g"]))
        return Environment(t=r["t"], chamber=r["chamber"], power=r["power"], settled=settled,
                           rate=r["rate"], specific_force=r["specific_force"], quat=r["quat"],
                           outputs=outputs, segments=tl.windows(self.dt), info=info or {})

    def resolved(self) -> dict:
        """The options in effect (JSON-ready)."""
        def plain(v):
            if isinstance(v, tuple | list):
                return [plain(x) for x in v]
            if isinstance(v, np.generic):
                return v.item()
            return v
        return {k: plain(v) for k, v in self.options.items()}


# ----------------------------------------------------------------------------- thermal


#: Default chamber profile after the start: (target °C, ramp °C/min, soak min).
THERMAL_PROFILE = ((-10.0, 1.0, 20.0), (60.0, 2.0, 20.0), (40.0, 0.5, 10.0),
                   (10.0, 2.0, 10.0), (25.0, 0.5, 10.0))


class Thermal(Plan):
    """Static device in a chamber: ramps at several rates (0.5, 1, 2 °C/min),
    heating and cooling, soaks between; the sensor lags the chamber and
    self-heats; dissipated power steps up and back down mid-run (so the
    inside–outside difference is not a function of dT/dt alone).

    Options: ``start_temp`` (°C), ``initial_soak`` (min), ``profile``
    ((target °C, rate °C/min, soak min), ...), ``power_steps`` ((fraction of
    the run, level), ...), ``face`` (axis up), ``duration`` (s: stretches or
    compresses every ramp and soak of the profile by the same factor, so ramp
    rates scale inversely; default: the profile's own length, ≈ 3.9 h).
    ``faces`` (e.g. ``"+z,+x,-y"``; default none: ``face`` throughout) turns the
    device on a fixture inside the chamber: every soak is shared equally among
    the faces, each held in turn after a ``move_time`` (s) rotation, and the
    ramps keep the last face, so the specific force changes at every soak
    temperature (a g-sensitivity that changes with temperature is then seen).
    """

    name = "thermal"
    description = "chamber ramps and soaks (static), sensor lag and self-heating"
    default_effects = "bias_poly(2)"
    defaults = {"sample_rate": 2.0, "duration": None, "start_temp": 25.0, "initial_soak": 10.0,
                "profile": THERMAL_PROFILE, "power_steps": ((0.43, 1.6), (0.75, 1.0)),
                "face": "+z", "faces": None, "move_time": 5.0}

    def natural_minutes(self) -> float:
        o = self.options
        total, temp = float(o["initial_soak"]), float(o["start_temp"])
        for target, rate, soak in o["profile"]:
            total += abs(target - temp) / abs(rate) + soak
            temp = target
        return total

    def build(self, n_devices, seed):
        o = self.options
        f = 1.0 if o["duration"] is None else float(o["duration"]) / (60.0 * self.natural_minutes())
        faces = _faces(o["faces"]) if o["faces"] else [o["face"]]
        tl = Timeline(start_temp=float(o["start_temp"]), pose=_face(faces[0]))
        move = float(o["move_time"])
        faces = self._soak(tl, 60.0 * f * o["initial_soak"], faces, float(o["start_temp"]), move)
        for target, rate, soak in o["profile"]:
            sign = 1.0 if target > tl.temp else -1.0
            tl.ramp(float(target), float(rate) / f, "ramp", ramp_rate=sign * float(rate) / f)
            faces = self._soak(tl, 60.0 * f * soak, faces, float(target), move)
        total = tl.now
        for frac, level in o["power_steps"]:
            tl.power.append((float(frac) * total, float(level)))
        tl.power.sort(key=lambda step: step[0])  # stable: a step at the same time wins
        info = {"chamber_breakpoints": [list(p) for p in tl.chamber],
                "power_steps": [list(p) for p in tl.power]}
        return self._from_timeline(tl, settled=False, outputs=self.outputs(), info=info)

    @staticmethod
    def _soak(tl: Timeline, duration: float, faces: list[str], temp: float, move: float) -> list[str]:
        """A soak of ``duration`` s shared among ``faces``, from the face held (the first);
        returns the faces in the order the next soak takes them (the last held first)."""
        move = move if len(faces) > 1 else 0.0
        share = max(duration - move * (len(faces) - 1), 0.0) / len(faces)
        for k, face in enumerate(faces):
            if k:
                tl.move(move, _face(face), "move")
            tl.hold(share, "soak", temp=temp, face=face)
        return faces[-1:] + faces[:-1]


def _faces(faces) -> list[str]:
    """The ``faces`` option as a list (``"+z,+x"`` or a sequence), each face checked."""
    out = [f.strip() for f in faces.split(",")] if isinstance(faces, str) else list(faces)
    for f in out:
        _face(f)
    return out


# ----------------------------------------------------------------------------- rate tables


class RateTable(Plan):
    """Rate table in a chamber: ± rates about each axis at several soak temperatures.

    At each soak temperature (reached by a ramp, then ``settle`` minutes) the
    device is turned to have each axis up in turn and spun at every rate of
    ``rates`` (°/s) in both directions for ``hold`` seconds at full rate,
    with ``pause`` seconds static between spins; the table accelerates at
    ``accel`` (°/s²). Options: ``start_temp``, ``temps``, ``ramp`` (°C/min),
    ``settle`` (min), ``rates``, ``axes`` (e.g. ``"xyz"``), ``hold``,
    ``pause``, ``accel``, ``move_time`` (s, re-orientation between axes).
    """

    name = "rate_table"
    description = "± rates about each axis at several soak temperatures"
    default_effects = "bias_poly(1)+scale_poly(1)+misalignment"
    defaults = {"sample_rate": 2.0, "start_temp": 20.0, "temps": (20.0, -20.0, 60.0), "ramp": 1.0,
                "settle": 15.0, "rates": (5.0, 30.0, 100.0, 300.0), "axes": "xyz", "hold": 20.0,
                "pause": 10.0, "accel": 100.0, "move_time": 5.0}

    def build(self, n_devices, seed):
        o = self.options
        accel = float(o["accel"]) * DEG
        tl = Timeline(start_temp=float(o["start_temp"]), pose=face_quat("+z"))
        for temp in o["temps"]:
            tl.ramp(float(temp), float(o["ramp"]), "ramp")
            tl.hold(60.0 * float(o["settle"]), "settle", temp=float(temp))
            for ax in o["axes"]:
                if ax not in "xyz":
                    raise DataError(f"unknown axis {ax!r} in axes {o['axes']!r}", hint="use x, y, z")
                target = face_quat("+" + ax)
                if not np.allclose(np.abs(np.dot(tl.pose, target)), 1.0):
                    tl.move(float(o["move_time"]), target, "move")
                tl.hold(float(o["pause"]), "static", about=ax, temp=float(temp))
                for r in o["rates"]:
                    for sign in (1.0, -1.0):
                        rate = sign * float(r) * DEG
                        dur = float(o["hold"]) + 2.0 * abs(rate) / accel
                        tl.spin(dur, rate, accel, label="spin", about=ax, temp=float(temp))
                        tl.hold(float(o["pause"]), "static", about=ax, temp=float(temp))
        return self._from_timeline(tl, settled=False, outputs=self.outputs())


class FogChamber(Plan):
    """The fog-one-run thermal-chamber profile (fibre-optic gyro, single axis z).

    Power on at room temperature (``start_temp``), cool at ``ramp`` °C/min
    to ``t_min``, soak ``settle`` minutes, turn the table +``turn_rate`` °/s
    for ``turn_time`` s then −``turn_rate`` for ``turn_time``; step up by
    ``step`` °C (same ramp rate) and repeat up to ``t_max``. The table
    accelerates at ``accel`` °/s². The device's z axis is the table axis.
    """

    name = "s2"
    description = "fog-one-run chamber: −40…70 °C in 10 °C steps, ±10 °/s turns of 1 min at each soak (z axis)"
    default_effects = "bias_poly(1)+scale_poly(2)+temp_diff+gradient"
    default_preset = "fog"
    defaults = {"sample_rate": 1.0, "start_temp": 20.0, "t_min": -40.0, "t_max": 70.0, "step": 10.0,
                "ramp": 1.5, "settle": 30.0, "turn_rate": 10.0, "turn_time": 60.0, "accel": 10.0}

    def build(self, n_devices, seed):
        o = self.options
        accel = float(o["accel"]) * DEG
        rate = float(o["turn_rate"]) * DEG
        temps = np.arange(float(o["t_min"]), float(o["t_max"]) + 1e-9, float(o["step"]))
        tl = Timeline(start_temp=float(o["start_temp"]), pose=face_quat("+z"))
        for temp in temps:
            tl.ramp(float(temp), float(o["ramp"]), "ramp")
            tl.hold(60.0 * float(o["settle"]), "soak", temp=float(temp))
            for sign in (1.0, -1.0):
                tl.spin(float(o["turn_time"]), sign * rate, accel, label="turn", about="z",
                        temp=float(temp))
        info = {"soak_temps": temps.tolist()}
        return self._from_timeline(tl, settled=False, outputs=self.outputs(), info=info)


# ----------------------------------------------------------------------------- six faces (cube-bias)


class SixFace(Plan):
    """The cube-bias fixture: faces × headings on a tilted table at a latitude (static).

    Each face in ``faces`` points up in turn; at each face the cube rests at
    ``headings`` headings, turned 90° clockwise (about the table normal)
    between them, ``dwell`` s each. The table is tilted by ``tilt`` degrees
    about the horizontal axis at azimuth ``tilt_azimuth`` (degrees from
    north). Faces change by a smooth ``move_time`` rotation. With ``turns``,
    a full clockwise turn (−360°) about the table normal follows the headings
    of every ``+`` face (Ferraris' rotations); the truth then carries imucal
    sections (``x_p`` ... ``z_rot``). Earth rate is always present; the rate
    column carries it unless ``include_rate=False``.
    """

    name = "six_face"
    description = "cube-bias fixture: six faces × four headings on a tilted table, Earth rate included"
    default_effects = "bias_poly(0)+g_sens+scale_poly(0)+misalignment"
    default_accel_errors = True
    defaults = {"sample_rate": 10.0, "latitude": 45.0, "tilt": 0.5, "tilt_azimuth": 30.0,
                "faces": FACES, "headings": 4, "heading0": 0.0, "dwell": 60.0, "move_time": 5.0,
                "include_rate": True, "turns": True, "turn_rate": 30.0, "turn_accel": 60.0,
                "temp": 25.0}

    def build(self, n_devices, seed):
        o = self.options
        faces = o["faces"].split(",") if isinstance(o["faces"], str) else list(o["faces"])
        for f in faces:
            if f not in FACES:
                raise DataError(f"unknown face {f!r}", hint="use " + ", ".join(FACES))
        az = float(o["tilt_azimuth"]) * DEG
        # Tilt axis: horizontal, at azimuth az from north (x) towards west (y), NWU.
        q_tilt = qexp(float(o["tilt"]) * DEG * np.array([math.cos(az), math.sin(az), 0.0]))
        normal = rotate(q_tilt, np.array([0.0, 0.0, 1.0]))
        rate, acc = float(o["turn_rate"]) * DEG, float(o["turn_accel"]) * DEG
        step = -90.0 * DEG  # clockwise seen from above

        def pose(face, k):
            heading = float(o["heading0"]) * DEG + k * step
            return qmul(q_tilt, qmul(qexp(np.array([0.0, 0.0, heading])), face_quat(face)))

        tl = Timeline(start_temp=float(o["temp"]), pose=pose(faces[0], 0))
        for i, face in enumerate(faces):
            if i:
                tl.move(float(o["move_time"]), pose(face, 0), "move")
            for k in range(int(o["headings"])):
                if k:
                    tl.turn(step, rate, acc, normal, "heading_turn", face=face)
                tl.hold(float(o["dwell"]), "face", face=face, heading=k * -90.0, index=k)
            if o["turns"] and face.startswith("+"):
                t0, _ = tl.hold(2.0)
                tl.turn(-2 * math.pi, rate, acc, normal, "turn", face=face)
                _, t1 = tl.hold(2.0)
                tl.segment("rotation", t0, t1, face=face, angle=-360.0)
        info = {"latitude": float(o["latitude"]), "tilt": float(o["tilt"]),
                "tilt_azimuth": float(o["tilt_azimuth"]), "table_normal": normal.tolist(),
                "earth_rate": 7.292115e-5, "frame": "NWU"}
        env = self._from_timeline(tl, settled=True,
                                  outputs=self.outputs() - ({"rate"} if not o["include_rate"] else set()),
                                  info=info)
        env.info["sections"] = _imucal_sections(env.segments)
        return env

    def __init__(self, **options):
        super().__init__(**options)
        if options.get("latitude", "unset") is None:
            raise DataError("plan six_face needs a latitude (Earth rate is what it is about)")


def _imucal_sections(segments: list[dict]) -> dict:
    """imucal's section names -> sample ranges: first heading of each face, and the turns."""
    out = {}
    for s in segments:
        if s["label"] == "face" and s.get("index") == 0:
            key = f"{s['face'][1]}_{'p' if s['face'][0] == '+' else 'a'}"
            out.setdefault(key, {"start": s["start"], "end": s["end"]})
        elif s["label"] == "rotation":
            out.setdefault(f"{s['face'][1]}_rot", {"start": s["start"], "end": s["end"]})
    return out


# ----------------------------------------------------------------------------- static and warm-up


class Static(Plan):
    """Long static run at constant chamber temperature for noise analysis
    (device already warm). Options: ``duration`` (s), ``temp`` (°C), ``face``."""

    name = "static"
    description = "long static run at constant temperature (noise analysis)"
    default_effects = "bias_poly(0)"
    defaults = {"sample_rate": 100.0, "duration": 600.0, "temp": 25.0, "face": "+z"}
    settled = True

    def build(self, n_devices, seed):
        o = self.options
        tl = Timeline(start_temp=float(o["temp"]), pose=_face(o["face"]))
        tl.hold(float(o["duration"]), "static")
        return self._from_timeline(tl, settled=self.settled, outputs=self.outputs())


class WarmupPlan(Static):
    """Power-on transient: constant chamber temperature, the device switched on
    at t = 0 and self-heating. Options as ``static``."""

    name = "warmup"
    description = "power-on transient at constant chamber temperature"
    default_effects = "bias_poly(1)+warmup"
    defaults = {"sample_rate": 2.0, "duration": 3600.0, "temp": 25.0, "face": "+z"}
    settled = False


# ----------------------------------------------------------------------------- attitude-reference


class Attitude(Plan):
    """Free motion for attitude references (attitude-reference): smooth random rotations with pauses.

    Each device moves on its own: pauses of ``pause`` s (range) alternate with
    rotations of ``move`` s about random axes with a sin² rate profile peaking
    at up to ``max_rate`` °/s. A share ``accel_share`` of the moves also
    carries a horizontal linear acceleration episode of up to ``lin_accel``
    m/s². The accelerometer sees gravity plus that acceleration, the
    magnetometer the Earth field (``field`` µT, ``dip`` degrees, magnetic
    north = x). The reference quaternion is integrated exactly enough
    (midpoint rule on the sample grid) from the true rate.
    """

    name = "attitude"
    description = "free motion with accelerometer and magnetometer (attitude-reference)"
    default_effects = "bias_poly(0)+scale_poly(0)"
    defaults = {"sample_rate": 50.0, "duration": 300.0, "max_rate": 180.0, "pause": (1.0, 4.0),
                "move": (2.0, 6.0), "lin_accel": 2.0, "accel_share": 0.3, "field": 50.0,
                "dip": 60.0, "max_tilt": 10.0, "temp": 25.0}

    def build(self, n_devices, seed):

        o = self.options
        rng = stream(seed, "attitude")
        dt = self.dt
        n = max(int(math.ceil(float(o["duration"]) / dt)), 2)
        t = np.arange(n) * dt
        d = n_devices
        motion = np.zeros((d, n, 3))
        lin = np.zeros((d, n, 3))
        segments = []
        for i in range(d):
            now = 0.0
            while True:
                now += rng.uniform(*o["pause"])
                dur = rng.uniform(*o["move"])
                if now + dur > t[-1]:
                    break
                axis = rng.standard_normal(3)
                axis /= np.linalg.norm(axis)
                peak = rng.uniform(0.3, 1.0) * float(o["max_rate"]) * DEG
                sel = (t >= now) & (t < now + dur)
                s = (t[sel] - now) / dur
                motion[i, sel] = peak * np.sin(math.pi * s)[:, None] ** 2 * axis
                episode = rng.uniform() < float(o["accel_share"])
                if episode:
                    ang = rng.uniform(0, 2 * math.pi)
                    amp = rng.uniform(0.5, 1.0) * float(o["lin_accel"])
                    lin[i, sel] = (amp * np.sin(2 * math.pi * s)[:, None]
                                   * np.array([math.cos(ang), math.sin(ang), 0.0]))
                start = int(np.argmax(sel))
                segments.append({"label": "move", "device": i, "t0": now, "t1": now + dur,
                                 "start": start, "end": start + int(sel.sum()),
                                 "peak_rate": peak, "linear_accel": bool(episode)})
                now += dur
        # Initial attitude: random heading, small tilt.
        tilt = float(o["max_tilt"]) * DEG
        q = qmul(qexp(np.stack([np.zeros(d), np.zeros(d), rng.uniform(-math.pi, math.pi, d)], -1)),
                 qexp(np.stack([rng.uniform(-tilt, tilt, d), rng.uniform(-tilt, tilt, d),
                                np.zeros(d)], -1)))
        quat = np.empty((d, n, 4))
        quat[:, 0] = q
        mid = 0.5 * (motion[:, 1:] + motion[:, :-1]) * dt
        for k in range(n - 1):
            q = qmul(q, qexp(mid[:, k]))
            quat[:, k + 1] = q
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
        rate = motion.copy()
        if o["latitude"] is not None:
            rate += to_body(quat, earth_rate_nav(float(o["latitude"])))
        force = to_body(quat, lin + np.array([0.0, 0.0, float(o["g"])]))
        dip = float(o["dip"]) * DEG
        mag_field = float(o["field"]) * np.array([math.cos(dip), 0.0, -math.sin(dip)])
        chamber = np.full(n, float(o["temp"]))
        return Environment(t=t, chamber=chamber, power=np.ones(n), settled=True, rate=rate,
                           specific_force=force, quat=quat,
                           outputs=self.outputs("quat", "mag"), mag_field=mag_field,
                           segments=segments, info={"mag_field": mag_field.tolist(), "frame": "NWU"})


def _face(face: str) -> np.ndarray:
    if face not in FACES:
        raise DataError(f"unknown face {face!r}", hint="use " + ", ".join(FACES))
    return face_quat(face)


PLANS: dict[str, type[Plan]] = {
    "thermal": Thermal,
    "rate_table": RateTable,
    "s2": FogChamber,
    "rate_table_s2": FogChamber,
    "six_face": SixFace,
    "static": Static,
    "attitude": Attitude,
    "warmup": WarmupPlan,
}


def get_plan(plan: str | Plan, **options) -> Plan:
    """A plan object from its name and options (or the plan itself).

    **Arguments:**

    - ``plan``: the plan's name, or a plan object (returned as it is).
    - ``**options``: the plan's options (``duration``, ``sample_rate``, …).
    """
    if isinstance(plan, Plan):
        if options:
            raise DataError("give options either to the Plan object or to simulate(), not both")
        return plan
    cls = PLANS.get(str(plan).lower().replace("-", "_"))
    if cls is None:
        raise DataError(f"unknown plan {plan!r}", hint="use one of " + ", ".join(PLANS))
    return cls(**options)
