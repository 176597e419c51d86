"""Derived signals, computed once per recording and shared by every effect term.

Temperature is centred and scaled to about [-1, 1] (a cubic's design then has
a condition number near 10 instead of 1e5); dT/dt is a centred local-linear
slope over a time window, so 1 °C read-out steps give a smooth rate rather
than spikes; the heating/cooling state is latched through soaks.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .data import aux_key

__all__ = ["make_signals", "Signals", "TempNorm", "temp_norm_from", "local_slope",
           "latched_heating", "moving_average_difference", "masked_range", "prefix_sums",
           "HEATING_THRESHOLD"]

# |dT/dt| above which the sensor counts as heating or cooling (0.05 °C/min).
HEATING_THRESHOLD = 0.05 / 60.0


class TempNorm(eqx.Module):
    """Centre and half-range of temperature: ``temp_s = (temp - centre) / scale``."""

    centre: Float[Array, ""]
    scale: Float[Array, ""]


class Signals(eqx.Module):
    """Everything an effect term may read for one device (leading axes allowed).

    ``rate`` is the reference (true) angular rate, zero where none was given
    (a static device: Earth rate is then part of the bias).
    """

    t: Float[Array, " n"]
    gyro: Float[Array, "n 3"]
    mask: Bool[Array, " n"]
    rate: Float[Array, "n 3"]
    temp: Float[Array, " n"] | None
    temp_s: Float[Array, " n"] | None
    dtemp: Float[Array, " n"] | None
    heating: Float[Array, " n"] | None
    temp_ext: Float[Array, " n"] | None
    accel: Float[Array, "n 3"] | None
    norm: TempNorm | None
    has_rate: bool = eqx.field(static=True, default=False)
    #: Extra logged columns by name, centred and scaled (:mod:`diffgyro._aux`).
    aux: dict[str, Float[Array, " n"]] = eqx.field(default_factory=dict)

    @property
    def available(self) -> frozenset[str]:
        """Names of the data signals present, as effect terms declare them in ``needs``."""
        have = {"t", "gyro"}
        for name in ("temp", "temp_ext", "accel"):
            if getattr(self, name) is not None:
                have.add(name)
        if self.has_rate:
            have.add("rate")
        return frozenset(have) | {aux_key(k) for k in self.aux}

    def with_rate(self, rate: Float[Array, "n 3"]) -> Signals:
        """The same signals seen at another true rate (used to invert the model)."""
        return eqx.tree_at(lambda s: s.rate, self, rate)

    def with_temp(self, temp: Float[Array, " n"]) -> Signals:
        """The same signals with the temperature replaced (e.g. clamped to a range)."""
        temp_s = (temp - self.norm.centre) / self.norm.scale
        return eqx.tree_at(lambda s: (s.temp, s.temp_s), self, (temp, temp_s))


#: Samples per block of :func:`prefix_sums` (a triangular matmul per block).
PREFIX_BLOCK = 16


def prefix_sums(x: Float[Array, "n k"]) -> Float[Array, "n+1 k"]:
    """Exclusive-to-inclusive prefix sums of the columns of ``x``, with a leading row of 0.

    Blocks of :data:`PREFIX_BLOCK` samples are summed by one matmul with a
    triangular matrix of ones, then the block totals (n/16 rows) by a cumsum:
    on XLA CPU several times faster than ``jnp.cumsum`` of each column, with
    the rounding of an ordinary running sum.

    **Arguments:**

    - ``x``: the columns (n, k).
    """
    n, k = x.shape
    b = PREFIX_BLOCK
    rows = -(-n // b)
    blocks = jnp.pad(x, ((0, rows * b - n), (0, 0))).reshape(rows, b, k)
    lower = jnp.tril(jnp.ones((b, b), x.dtype))
    within = jnp.einsum("ij,rjk->rik", lower, blocks)
    total = within[:, -1]
    before = jnp.cumsum(total, axis=0) - total
    out = (within + before[:, None]).reshape(rows * b, k)[:n]
    return jnp.concatenate([jnp.zeros((1, k), x.dtype), out])


def local_slope(
    t: Float[Array, " n"], y: Float[Array, " n"], mask: Bool[Array, " n"], half_width
) -> Float[Array, " n"]:
    """Least-squares slope of ``y`` against ``t`` over samples ``i-h .. i+h`` (masked).

    Computed with prefix sums in O(n); near the ends the window is clipped.

    **Arguments:**

    - ``t``: sample times (n,).
    - ``y``: the samples (n,).
    - ``mask``: which samples are valid.
    - ``half_width``: ``h``, the window's half-width in samples.
    """
    w = mask.astype(y.dtype)
    n = t.shape[0]
    tc = t - jnp.sum(t * w) / jnp.maximum(jnp.sum(w), 1.0)
    yc = y - jnp.sum(y * w) / jnp.maximum(jnp.sum(w), 1.0)
    c = prefix_sums(jnp.stack([w, w * tc, w * yc, w * tc * tc, w * tc * yc], axis=-1))
    i = jnp.arange(n)
    lo = jnp.clip(i - half_width, 0, n)
    hi = jnp.clip(i + half_width + 1, 0, n)
    s = c[hi] - c[lo]
    s1, st, sy, stt, sty = (s[:, j] for j in range(5))
    s1 = jnp.maximum(s1, 1.0)
    var = stt - st * st / s1
    cov = sty - st * sy / s1
    return jnp.where(var > 0, cov / jnp.where(var > 0, var, 1.0), 0.0)


def moving_average_difference(y: Float[Array, " n"], n_avg: int) -> Float[Array, " n"]:
    """fog-one-run's dT: mean of the last ``n_avg`` samples minus the mean of the ``n_avg`` before.

    Defined from sample ``2·n_avg - 1`` on (earlier samples get 0), in units of
    ``y`` per ``n_avg`` samples, exactly as the published method uses it.

    **Arguments:**

    - ``y``: the samples (n,).
    - ``n_avg``: the samples in each mean.
    """
    c = jnp.concatenate([jnp.zeros((1,), y.dtype), jnp.cumsum(y)])
    i = jnp.arange(y.shape[0])
    recent = (c[i + 1] - c[jnp.clip(i + 1 - n_avg, 0)]) / n_avg
    before = (c[jnp.clip(i + 1 - n_avg, 0)] - c[jnp.clip(i + 1 - 2 * n_avg, 0)]) / n_avg
    return jnp.where(i >= 2 * n_avg - 1, recent - before, 0.0)


def latched_heating(dtemp: Float[Array, " n"], mask: Bool[Array, " n"], threshold: float) -> Float[Array, " n"]:
    """+1 while (last) heating, -1 while (last) cooling; the state is kept through soaks.

    Samples before the first heating or cooling take the first state seen.
    A device that never heats or cools gets 0 everywhere.

    **Arguments:**

    - ``dtemp``: dT/dt (n,), °C/s.
    - ``mask``: which samples are valid.
    - ``threshold``: the |dT/dt| (°C/s) above which the device heats or cools.
    """
    active = mask & (jnp.abs(dtemp) > threshold)
    idx = jnp.where(active, jnp.arange(dtemp.shape[0]), -1)
    last = jax.lax.cummax(idx)
    first = jnp.argmax(active)
    state = jnp.sign(dtemp[jnp.where(last >= 0, last, first)])
    return jnp.where(jnp.any(active), state, 0.0)


def masked_range(x: Float[Array, " n"], mask: Bool[Array, " n"]) -> tuple[Array, Array]:
    """Smallest and largest valid value.

    Two reductions, each fused with its mask. One variadic min/max reduction (one
    pass) compiled 10× slower on XLA CPU without fusion emitters: 100-170 ms for an
    unmasked (16, 2000) input (an ALIGNED group's constant mask folds away), against
    11 ms for the two.

    **Arguments:**

    - ``x``: the values (n,).
    - ``mask``: which of them are valid."""
    return (jnp.min(jnp.where(mask, x, jnp.inf), axis=-1),
            jnp.max(jnp.where(mask, x, -jnp.inf), axis=-1))


def temp_norm_from(temp: Float[Array, " n"], mask: Bool[Array, " n"]) -> TempNorm:
    """Centre and half-range of the masked temperature (half-range at least 0.5 °C).

    **Arguments:**

    - ``temp``: die temperature (n,), °C.
    - ``mask``: which samples are valid.
    """
    lo, hi = masked_range(temp, mask)
    return TempNorm(centre=0.5 * (lo + hi), scale=jnp.maximum(0.5 * (hi - lo), 0.5))


def make_signals(
    t: Float[Array, " n"],
    gyro: Float[Array, "n 3"],
    mask: Bool[Array, " n"],
    rate: Float[Array, "n 3"] | None = None,
    temp: Float[Array, " n"] | None = None,
    temp_ext: Float[Array, " n"] | None = None,
    accel: Float[Array, "n 3"] | None = None,
    norm: TempNorm | None = None,
    dtemp_window: float = 60.0,
    dt: Float[Array, ""] | None = None,
    slopes: bool = True,
    aux: dict[str, Float[Array, " n"]] | None = None,
) -> Signals:
    """Derived signals for one device; pure, so it vmaps over a batch.

    **Arguments:**

    - ``t``: sample times (n,), s.
    - ``gyro``: the measured rate (n, 3), rad/s.
    - ``mask``: which samples are valid (padding is not).
    - ``rate``: the reference rate (n, 3), rad/s, where the data has one.
    - ``temp``: die temperature (n,), °C.
    - ``temp_ext``: external temperature (n,), °C.
    - ``accel``: specific force (n, 3), m/s².
    - ``norm``: the temperature centring (default: the device's own range,
      :func:`temp_norm_from`).
    - ``dtemp_window``: the span (s) of the centred slope that gives dT/dt; widen it
      when the temperature read-out is coarsely quantised.
    - ``dt``: the nominal sampling interval (default: the median spacing of the valid
      samples).
    - ``slopes``: False leaves dT/dt and the heating state out (None): for a model that
      reads neither, they are not traced at all.
    - ``aux``: extra columns already centred and scaled (:func:`diffgyro._aux.scaled`).
    """
    t = jnp.asarray(t)
    t = t - t[0]
    has_rate = rate is not None
    rate = jnp.zeros_like(gyro) if rate is None else rate
    temp_s = dtemp = heating = None
    if temp is not None:
        if norm is None:
            norm = temp_norm_from(temp, mask)
        temp_s = (temp - norm.centre) / norm.scale
    if temp is not None and slopes:
        if dt is None:
            gaps = jnp.diff(t)
            dt = jnp.nanmedian(jnp.where(mask[1:], gaps, jnp.nan))
        half = jnp.maximum(1, jnp.round(0.5 * dtemp_window / dt)).astype(jnp.int32)
        dtemp = local_slope(t, temp, mask, half)
        heating = latched_heating(dtemp, mask, HEATING_THRESHOLD)
    return Signals(
        t=t, gyro=gyro, mask=mask, rate=rate, temp=temp, temp_s=temp_s, dtemp=dtemp,
        heating=heating, temp_ext=temp_ext, accel=accel, norm=norm, has_rate=has_rate,
        aux=dict(aux or {}),
    )
