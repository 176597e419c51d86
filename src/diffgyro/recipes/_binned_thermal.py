"""binned-thermal (CN102230806): zero-rate bias vs temperature by binning and a line.

The published procedure, step by step:

1. a static recording of temperature and the three rates over as wide a
   temperature range as possible;
2. sort by temperature and cut the range into equal bins (0.1 °C);
3. sample every bin evenly — keep every k-th sample — so that each bin
   carries about the same number of samples (the raw data crowd where the
   temperature changes slowly);
4. average each bin; its temperature is the bin's low edge, centre or high
   edge (a choice);
5. least-squares line ``bias(T) = a + b·T`` per axis, accepted only if the
   correlation coefficient satisfies ``|r| > 0.999``;
6. at run time ``ω = ω_measured − (a + b·T)``.

Step 5 is the toolkit's ``bias_poly(1)`` fitted to the bin means (its
coefficients are reported back as ``a + b·T`` in °C). Bins with fewer than
``min_count`` samples are dropped before the equal count is chosen (a
single stray sample would otherwise set the count to one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from ..model import ErrorModel
from ._common import RecipeResult, least_squares_params, signals_for

EDGES = ("low", "centre", "high")


@dataclass(frozen=True)
class BinnedThermalResult(RecipeResult):
    """Per axis ``bias(T) = offset + slope·T`` (rate units, °C) and the evidence."""

    offset: np.ndarray        # (3,) a
    slope: np.ndarray         # (3,) b, per °C
    r: np.ndarray             # (3,) correlation of bin temperature and bin mean
    accepted: np.ndarray      # (3,) |r| > r_min
    bin_temp: np.ndarray      # (bins,) representative temperature
    bin_mean: np.ndarray      # (bins, 3)
    bin_count: np.ndarray     # (bins,) samples kept per bin after even sub-sampling
    per_bin: int
    bin_width: float
    edge: str
    r_min: float

    name = "binned-thermal"

    def bias(self, temp: np.ndarray) -> np.ndarray:
        return self.offset + np.asarray(temp)[:, None] * self.slope

    def compensate(self, gyro: np.ndarray, temp: np.ndarray) -> np.ndarray:
        return np.asarray(gyro) - self.bias(temp)


def even_subsample(order: np.ndarray, count: int) -> np.ndarray:
    """``count`` indices spread evenly through ``order`` (every k-th, k fractional)."""
    if order.size <= count:
        return order
    return order[np.round(np.linspace(0, order.size - 1, count)).astype(int)]


def binned_thermal(
    gyro: np.ndarray,
    temp: np.ndarray,
    *,
    bin_width: float = 0.1,
    edge: str = "low",
    per_bin: int | None = None,
    min_count: int = 10,
    r_min: float = 0.999,
) -> BinnedThermalResult:
    """Fit the published straight line ``bias(T) = a + b·T`` to one static recording.

    ``per_bin``: samples kept in every bin (default: the smallest count among
    bins holding at least ``min_count``; fuller bins are sub-sampled evenly).

    **Arguments:**

    - ``gyro``: the measured rate at rest (n, 3).
    - ``temp``: the die temperature (n,), °C.
    - ``bin_width``: the temperature bins' width, °C.
    - ``edge``: the temperature a bin stands for: ``"low"``, ``"centre"`` or ``"high"``.
    - ``per_bin``: samples kept in every bin (default: as above).
    - ``min_count``: the fewest samples a bin holds to be kept.
    - ``r_min``: the correlation ``|r|`` above which an axis's line is accepted.
    """
    gyro = np.asarray(gyro, float)
    temp = np.asarray(temp, float)
    if edge not in EDGES:
        raise DataError(f"edge must be one of {', '.join(EDGES)}, not {edge!r}")
    if bin_width <= 0:
        raise DataError("bin width must be positive")
    order = np.argsort(temp, kind="stable")
    t_sorted = temp[order]
    lo = np.floor(t_sorted[0] / bin_width) * bin_width
    idx = np.floor((t_sorted - lo) / bin_width + 1e-9).astype(int)
    starts = np.flatnonzero(np.diff(np.concatenate([[-1], idx])))
    stops = np.concatenate([starts[1:], [idx.size]])
    counts = stops - starts
    full = counts >= min_count
    if full.sum() < 3:
        raise DataError(f"only {int(full.sum())} temperature bins of {bin_width} °C hold "
                        f"{min_count} samples or more",
                        hint="the temperature span is too small for this bin width")
    count = int(per_bin) if per_bin else int(counts[full].min())
    temps, means, kept = [], [], []
    for s, e, ok in zip(starts, stops, full):
        if not ok:
            continue
        pick = even_subsample(order[s:e], count)
        k = idx[s]
        low = lo + k * bin_width
        temps.append({"low": low, "centre": low + bin_width / 2, "high": low + bin_width}[edge])
        means.append(gyro[pick].mean(0))
        kept.append(pick.size)
    bin_temp = np.asarray(temps)
    bin_mean = np.asarray(means)
    # Step 5 with the toolkit's bias_poly(1) on the bin means, reported as a + b·T.
    model = ErrorModel.from_spec("bias_poly(1)")
    sig = signals_for(bin_mean, temp=bin_temp)
    beta = least_squares_params(model, sig, bin_mean)
    centre, scale = float(sig.norm.centre), float(sig.norm.scale)
    slope = beta[:, 1] / scale
    offset = beta[:, 0] - slope * centre
    r = np.array([np.corrcoef(bin_temp, bin_mean[:, i])[0, 1] for i in range(3)])
    return BinnedThermalResult(
        offset=offset, slope=slope, r=r, accepted=np.abs(r) > r_min, bin_temp=bin_temp,
        bin_mean=bin_mean, bin_count=np.asarray(kept), per_bin=count, bin_width=float(bin_width),
        edge=edge, r_min=float(r_min))
