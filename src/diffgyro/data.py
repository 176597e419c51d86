"""Recordings of one device and batches of many, as pytrees.

A :class:`Recording` holds one device's samples in the standard schema
(docs/formats.md; SI units, rad/s, m/s², °C). A :class:`Batch` stacks many
recordings along a leading device axis, padded to a bucket length with a
sample mask, so that batches of slightly different lengths reuse one compiled
function; fits pad the device axis the same way (:func:`pad_devices`). Arrays are host
numpy arrays here; fits move them to JAX. Both are frozen dataclasses that become JAX
pytrees (the arrays children, the names static) when JAX is imported, so that reading a
file needs no JAX.

Extra numeric columns of a file (supply voltage, a second board temperature,
heater duty, ...) travel beside the standard signals in ``aux``, a dict from
column name to a (n,) array; an ``aux(NAME)`` effect term reads them. In
signal sets (:func:`inputs_of`, ``ErrorModel.requires``) they are named
``aux:NAME`` (:func:`aux_key`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from jaxtyping import Bool, Float, Int

from ._jax_setup import when_jax_imported
from ._vocabulary import AUX_PREFIX
from .errors import DataError

__all__ = ["Batch", "Recording", "as_batch", "pad_devices", "device_bucket", "bucket_length",
           "sampling_intervals", "valid_samples", "as_slice", "aux_key", "STANDARD_COLUMNS", "SIGNALS",
           "OPTIONAL_SIGNALS", "COLUMN_TO_SIGNAL", "AUX_PREFIX"]

# Signal name -> standard column names (the standard schema, contract).
SIGNALS: dict[str, tuple[str, ...]] = {
    "gyro": ("gx", "gy", "gz"),
    "temp": ("temp",),
    "temp_ext": ("temp_ext",),
    "accel": ("ax", "ay", "az"),
    "mag": ("mx", "my", "mz"),
    "rate": ("rx", "ry", "rz"),
    "quat": ("qw", "qx", "qy", "qz"),
}
OPTIONAL_SIGNALS = ("temp", "temp_ext", "accel", "mag", "rate", "quat")
COLUMN_TO_SIGNAL = {c: s for s, cols in SIGNALS.items() for c in cols}
STANDARD_COLUMNS = ("device", "t", *[c for cols in SIGNALS.values() for c in cols])


def aux_key(name: str) -> str:
    """The signal name of extra column ``name`` (as effect terms declare it in ``requires``).

    **Arguments:**

    - ``name``: the extra column's name.
    """
    return AUX_PREFIX + name


def inputs_of(data) -> frozenset[str]:
    """Signals of a Recording or Batch, extra columns included as ``aux:NAME``."""
    return frozenset(data.signals) | {aux_key(k) for k in data.aux}


def _aux_dict(aux) -> dict:
    """Extra columns in name order (a static order: the pytree flattens dicts sorted)."""
    return {str(k): aux[k] for k in sorted(aux or {})}


@dataclasses.dataclass(frozen=True, eq=False)
class Recording:
    """One device's samples; optional signals are ``None`` when not recorded."""

    t: Float[np.ndarray, " n"]
    gyro: Float[np.ndarray, "n 3"]
    temp: Float[np.ndarray, " n"] | None = None
    temp_ext: Float[np.ndarray, " n"] | None = None
    accel: Float[np.ndarray, "n 3"] | None = None
    mag: Float[np.ndarray, "n 3"] | None = None
    rate: Float[np.ndarray, "n 3"] | None = None
    quat: Float[np.ndarray, "n 4"] | None = None
    device: str = "device"
    source: str | None = None
    #: Extra numeric columns by name, each (n,).
    aux: dict[str, Float[np.ndarray, " n"]] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "aux", _aux_dict(self.aux))

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def signals(self) -> tuple[str, ...]:
        """Names of the signals present (always includes ``t`` and ``gyro``)."""
        return ("t", "gyro") + tuple(s for s in OPTIONAL_SIGNALS if getattr(self, s) is not None)

    def to_frame(self):
        """This recording as a pandas DataFrame in the standard schema."""
        import pandas as pd  # a slow import that only a table needs

        cols: dict[str, np.ndarray | str] = {"device": self.device, "t": self.t}
        for sig, names in SIGNALS.items():
            arr = getattr(self, sig)
            if arr is None:
                continue
            arr = np.asarray(arr).reshape(self.n, len(names))
            for k, name in enumerate(names):
                cols[name] = arr[:, k]
        for name, arr in self.aux.items():
            cols[name] = np.asarray(arr)
        return pd.DataFrame(cols)

    def slice(self, start: int, stop: int) -> Recording:
        """Samples ``start:stop`` as a new recording of the same device."""
        kw = {s: (None if getattr(self, s) is None else getattr(self, s)[start:stop])
              for s in ("t", "gyro", *OPTIONAL_SIGNALS)}
        return Recording(**kw, device=self.device, source=self.source,
                         aux={k: v[start:stop] for k, v in self.aux.items()})


def bucket_length(n: int, minimum: int = 64) -> int:
    """Smallest bucket length ≥ ``n``: ``m·2^k`` with m in 4..7 (≤ 25 % padding).

    A handful of bucket lengths per decade keeps recompilation rare when
    devices have slightly different numbers of samples.

    **Arguments:**

    - ``n``: the number of samples.
    - ``minimum``: the smallest bucket length.
    """
    n = max(int(n), minimum)
    k = max(0, math.floor(math.log2(n)) - 2)
    while True:
        for m in (4, 5, 6, 7):
            if m * 2**k >= n:
                return m * 2**k
        k += 1


def device_bucket(n: int, minimum: int = 8) -> int:
    """Padded device count of ``n`` devices: powers of two from ``minimum`` up to 64, then
    multiples of 64, so that a few more or fewer devices reuse a compiled program.

    The direct-path fit pads to at least 8 (few compiled sizes for small batches);
    diagnose's chunks and Allan curves pass ``minimum=1``, so that one device is not
    computed eight times over in its larger per-device work.

    **Arguments:**

    - ``n``: the number of devices.
    - ``minimum``: the smallest padded count.
    """
    n = max(int(n), 1)
    if n <= 64:
        return max(minimum, 1 << (n - 1).bit_length())
    return -(-n // 64) * 64


def _pad_into(out: np.ndarray, arr: np.ndarray, mode: str) -> None:
    """``arr`` into the start of ``out``, the rest zeros (``mode="zero"``) or held at the
    last value (keeps temperatures and times in a sane range)."""
    n = arr.shape[0]
    out[:n] = arr
    if n < out.shape[0]:
        out[n:] = 0 if mode == "zero" else arr[-1]


def as_slice(idx: np.ndarray) -> slice | np.ndarray:
    """``idx`` as a slice where it is one run of consecutive indices (indexing with it then
    gives a view, not a copy), else ``idx`` itself.

    **Arguments:**

    - ``idx``: sorted integer indices."""
    if idx.size and np.array_equal(idx, np.arange(idx[0], idx[0] + idx.size)):
        return slice(int(idx[0]), int(idx[0]) + idx.size)
    return idx


#: Alignment of batch arrays in bytes: XLA's CPU client reads aligned host memory in place.
ALIGN = 64


def aligned_empty(shape, dtype) -> np.ndarray:
    """An uninitialised C-contiguous array whose data starts on an :data:`ALIGN`-byte boundary."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    buf = np.empty(nbytes + ALIGN, np.uint8)
    off = (-buf.ctypes.data) % ALIGN
    return buf[off:off + nbytes].view(dtype).reshape(shape)


def _aligned(a):
    """``a`` itself when it is a C-contiguous, aligned numpy array (or small, or broadcast),
    otherwise an aligned copy: fits then hand device-sized slices to JAX without a copy."""
    if not isinstance(a, np.ndarray) or a.nbytes < (1 << 16) or 0 in a.strides:
        return a
    if a.flags.c_contiguous and a.ctypes.data % ALIGN == 0:
        return a
    out = aligned_empty(a.shape, a.dtype)
    out[...] = a
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class Batch:
    """Many devices stacked on a leading axis, padded with a sample mask.

    Padded samples have ``mask == False``; their time continues at the last
    sampling interval and other signals hold their last value so derived
    signals (dT/dt, lags) stay finite. Sample arrays are stored C-contiguous
    and 64-byte aligned (copied once here if they are not), so the fits read
    them in place.
    """

    t: Float[np.ndarray, "d n"]
    gyro: Float[np.ndarray, "d n 3"]
    mask: Bool[np.ndarray, "d n"]
    n_valid: Int[np.ndarray, " d"]
    temp: Float[np.ndarray, "d n"] | None = None
    temp_ext: Float[np.ndarray, "d n"] | None = None
    accel: Float[np.ndarray, "d n 3"] | None = None
    mag: Float[np.ndarray, "d n 3"] | None = None
    rate: Float[np.ndarray, "d n 3"] | None = None
    quat: Float[np.ndarray, "d n 4"] | None = None
    devices: tuple[str, ...] = ()
    sources: tuple[str | None, ...] = ()
    #: Extra numeric columns by name, each (d, n), padded by holding the last value.
    aux: dict[str, Float[np.ndarray, "d n"]] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        for name in ("t", "gyro", "mask", "temp", "temp_ext", "accel", "mag", "rate", "quat"):
            object.__setattr__(self, name, _aligned(getattr(self, name)))
        object.__setattr__(self, "aux", {k: _aligned(v) for k, v in _aux_dict(self.aux).items()})

    @property
    def n_devices(self) -> int:
        return int(self.t.shape[0])

    @property
    def length(self) -> int:
        return int(self.t.shape[1])

    @property
    def signals(self) -> tuple[str, ...]:
        return ("t", "gyro") + tuple(s for s in OPTIONAL_SIGNALS if getattr(self, s) is not None)

    @classmethod
    def from_recordings(
        cls,
        recordings: Sequence[Recording],
        length: int | None = None,
        bucket: bool = True,
        dtype=np.float64,
    ) -> Batch:
        """Stack recordings, padding each to a common (bucketed) length.

        A signal (or extra column) is kept only if every recording has it.
        Device ids must be unique within the batch.
        """
        recordings = list(recordings)
        if not recordings:
            raise DataError("no devices to batch")
        seen: dict[str, str | None] = {}
        for r in recordings:
            if r.device in seen:
                raise DataError(
                    "device id appears more than once",
                    file=r.source, device=r.device,
                    hint=f"also in {seen[r.device]}" if seen[r.device] else None,
                )
            seen[r.device] = r.source
        n_max = max(r.n for r in recordings)
        if length is None:
            length = bucket_length(n_max) if bucket else n_max
        if length < n_max:
            raise DataError(f"batch length {length} is shorter than a device's {n_max} samples")
        fields: dict[str, np.ndarray | None] = {}
        dts = []
        for r in recordings:
            dt = float(r.t[-1] - r.t[-2]) if r.n >= 2 else 1.0
            dts.append(dt if dt > 0 else 1.0)
        t = aligned_empty((len(recordings), length), dtype)
        for row, r, dt in zip(t, recordings, dts, strict=True):
            row[:r.n] = r.t
            row[r.n:] = r.t[-1] + dt * np.arange(1, length - r.n + 1)
        fields["t"] = t

        def stack(arrays, mode="hold"):
            out = aligned_empty((len(arrays), length, *arrays[0].shape[1:]), dtype)
            for row, a in zip(out, arrays, strict=True):
                _pad_into(row, a, mode)
            return out

        fields["gyro"] = stack([r.gyro for r in recordings], "zero")
        for s in OPTIONAL_SIGNALS:
            if all(getattr(r, s) is not None for r in recordings):
                fields[s] = stack([getattr(r, s) for r in recordings])
            else:
                fields[s] = None
        common = set.intersection(*(set(r.aux) for r in recordings))
        aux = {k: stack([r.aux[k] for r in recordings])
               for k in sorted(common)}
        n_valid = np.array([r.n for r in recordings], dtype=np.int64)
        mask = np.arange(length)[None, :] < n_valid[:, None]
        return cls(**fields, mask=mask, n_valid=n_valid,
                   devices=tuple(r.device for r in recordings),
                   sources=tuple(r.source for r in recordings), aux=aux)

    def recording(self, i: int) -> Recording:
        """Device ``i`` as an unpadded :class:`Recording`."""
        n = int(self.n_valid[i])
        kw = {s: (None if getattr(self, s) is None else np.asarray(getattr(self, s)[i, :n]))
              for s in ("t", "gyro", *OPTIONAL_SIGNALS)}
        return Recording(**kw, device=self.devices[i],
                         source=self.sources[i] if self.sources else None,
                         aux={k: np.asarray(v[i, :n]) for k, v in self.aux.items()})

    def recordings(self) -> list[Recording]:
        return [self.recording(i) for i in range(self.n_devices)]

    def select(self, index: Sequence[int] | slice) -> Batch:
        """A sub-batch of the given device indices (same padded length)."""
        idx = np.arange(self.n_devices)[index]
        kw = {s: (None if getattr(self, s) is None else np.asarray(getattr(self, s))[idx])
              for s in ("t", "gyro", "mask", "n_valid", *OPTIONAL_SIGNALS)}
        return Batch(**kw, devices=tuple(self.devices[i] for i in idx),
                     sources=tuple(self.sources[i] for i in idx) if self.sources else (),
                     aux={k: np.asarray(v)[idx] for k, v in self.aux.items()})

    def to_frame(self):
        """Every device's recording as one pandas DataFrame in the standard schema."""
        import pandas as pd

        return pd.concat([r.to_frame() for r in self.recordings()], ignore_index=True)


def _register_pytrees(jax) -> None:
    """Recording and Batch as JAX pytrees: the arrays (and ``aux``) are children, the names
    static; unflattening sets the fields as given, as an equinox module's does (no copy, no
    check). Run when JAX is imported (:func:`diffgyro._jax_setup.when_jax_imported`)."""
    for cls, static in ((Recording, ("device", "source")), (Batch, ("devices", "sources"))):
        names = tuple(f.name for f in dataclasses.fields(cls) if f.name not in static)

        def flatten(obj, names=names, static=static):
            return ([(jax.tree_util.GetAttrKey(n), getattr(obj, n)) for n in names],
                    tuple(getattr(obj, n) for n in static))

        def unflatten(meta, children, cls=cls, names=names, static=static):
            obj = object.__new__(cls)
            for n, v in (*zip(names, children, strict=True), *zip(static, meta, strict=True)):
                object.__setattr__(obj, n, v)
            return obj

        jax.tree_util.register_pytree_with_keys(
            cls, flatten, unflatten,
            lambda obj, names=names, static=static: ([getattr(obj, n) for n in names],
                                                     tuple(getattr(obj, n) for n in static)))


when_jax_imported(_register_pytrees)


def as_batch(data: Batch | Recording | list[Recording]) -> Batch:
    """A Batch of ``data``.

    **Arguments:**

    - ``data``: a Batch (returned as it is), one Recording or a list of them.
    """
    if isinstance(data, Batch):
        return data
    if isinstance(data, Recording):
        return Batch.from_recordings([data])
    return Batch.from_recordings(list(data))


def pad_devices(batch: Batch) -> Batch:
    """The batch with its last device repeated up to :func:`device_bucket` devices.

    **Arguments:**

    - ``batch``: the batch to pad.
    """
    n = batch.n_devices
    m = device_bucket(n)
    if m == n:
        return batch
    return batch.select(np.minimum(np.arange(m), n - 1))


def valid_samples(mask: Bool[np.ndarray, "d n"]) -> Int[np.ndarray, " d"]:
    """Valid samples of every device (int64): the mask's bytes read as 64-bit words and
    counted by popcount where its layout allows (numpy ≥ 2.0), a count of the flags
    otherwise; the numbers ``mask.sum(axis=1)`` gives, in a fraction of its time.

    **Arguments:**

    - ``mask``: the devices' valid samples (devices × samples).
    """
    mask = np.asarray(mask, bool)
    if (hasattr(np, "bitwise_count") and mask.ndim == 2 and mask.shape[1] % 8 == 0
            and mask.flags.c_contiguous and mask.ctypes.data % 8 == 0):
        return np.bitwise_count(mask.view(np.uint64)).sum(axis=1, dtype=np.int64)
    return np.count_nonzero(mask, axis=1).astype(np.int64)


def sampling_intervals(batch: Batch) -> np.ndarray:
    """Median interval between each device's first ``n_valid`` samples (s; 1 where it
    has fewer than two). Devices of one length share one vectorised median.

    **Arguments:**

    - ``batch``: the batch.
    """
    out = np.ones(batch.n_devices)
    n_valid = np.asarray(batch.n_valid, int)
    t = np.asarray(batch.t)
    for n in np.unique(n_valid[n_valid >= 2]):
        rows = np.flatnonzero(n_valid == n)
        out[rows] = np.median(np.diff(t[rows, :n], axis=1), axis=1)
    return out
