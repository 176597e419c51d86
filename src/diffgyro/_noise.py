"""The model-free white-noise floor of a batch, on the host.

Per device and axis, from the successive differences ``Δy`` of ``gyro − rate``
over pairs of valid samples: the truncation-corrected RMS of the deviations
from their median inside a ±4σ₀ window (σ₀ = 1.4826 · MAD), over √2
(:func:`sigma_from_differences`). Slow drift hardly changes from one sample to
the next, so the differences see the white noise; the window keeps rate-table
steps and outliers out. The same numbers as :func:`diffgyro._noise_jax.device_noise_floor`
(the pure-JAX version the differentiable paths use).

Rows of more than :data:`SUBSAMPLE` differences: the median and the MAD only
place the window, so they are taken from an even subsample of :data:`SUBSAMPLE`
of the row's differences, and the spread is measured about the mean of the
differences inside the window (where the row's median lies for noise symmetric
about it, while the subsample's median is off by about 4 % of σ): one compiled
pass over the row (:mod:`diffgyro._noise_passes`, in batches of at least
:data:`COMPILED_SAMPLES` device-samples; numpy's operations in smaller ones)
counts and sums them. The floor then stays
within 1 % of the exact statistic: at most 0.4 % over every axis of the
diagnose catalogue's recordings, about 0.1 % for white noise
(``tests/test_diagnose.py``). Rows whose window the subsample cannot place
(fewer than 95 % of the differences inside it, or a quarter of the subsample
tied at its median, as on coarsely quantised output) keep the exact statistic.

Why on the host: the exact statistic needs two order statistics per device and
axis (three where the MAD collapses). XLA has no selection primitive, so a
compiled version sorts every axis of every device, and its program costs half
a second of compile per group shape. numpy's introselect
(``ndarray.partition``) selects in linear time without a sort; the compiled passes
select a long row's subsample without a branch per value (:func:`diffgyro._select.select`,
the same order statistics in about a third of the time). A block of a
few devices' differences, small enough to stay in a core's cache, is
differenced, its subsamples selected, and passed over once. Threads claim
chunks of devices in turn while the compiled fits run (one core's worth is left to the
caller until it asks for the floor, then its thread claims chunks too); numpy and the
compiled pass release the GIL.
"""

from __future__ import annotations

import functools
import itertools
import math
import threading
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np
from jaxtyping import Bool, Float

from ._jit import available_cores, host_pool

#: Most differences of a row its window is placed from (:func:`subsample_ranks`); odd,
#: so that the subsample's median is one order statistic.
SUBSAMPLE = 1023
#: A long row keeps the exact statistic where fewer than this share of its differences
#: fall inside the subsample's window (heavy tails, a collapsing MAD) ...
EXACT_INSIDE = 0.95
#: ... or where this share of its subsample equals the subsample's median (output
#: quantised to about its noise or coarser: the MAD locks to whole LSBs).
EXACT_TIES = 0.25
#: Device-samples of a batch from which its long rows take the compiled passes
#: (:mod:`diffgyro._noise_passes`; numba's import and first call cost a process about
#: 0.35 s, repaid by about 4 million device-samples); smaller batches take numpy's,
#: the same statistic to rounding.
COMPILED_SAMPLES = 1 << 22
#: Device-samples per chunk of work given to a thread.
CHUNK_SAMPLES = 1 << 18
#: Device-samples per block a thread differences and selects in its cache (3 axes ×
#: 8 bytes each: about 1.5 MB, within a core's L2).
BLOCK_SAMPLES = 1 << 16
#: Device-samples per block of long rows through the compiled passes, which read them
#: twice and select only the subsample: larger blocks (about 6 MB, from the L3 cache)
#: save numpy's calls per block.
PASS_SAMPLES = 1 << 18


def noise_axes(gyro: Float[np.ndarray, "d n 3"], rate: Float[np.ndarray, "d n 3"] | None,
               mask: Bool[np.ndarray, "d n"], dtype=np.float64,
               compiled: bool | None = None) -> Float[np.ndarray, "d 3"]:
    """White-noise σ per device and axis from successive differences of ``gyro − rate``
    over pairs of valid samples (NaN differences left out), NaN where no pair is valid:
    :func:`sigma_from_differences` of the lag-1 differences. ``compiled``: long rows
    through the compiled passes (default: from :data:`COMPILED_SAMPLES`)."""
    d, n = np.shape(mask)
    compiled = d * n >= COMPILED_SAMPLES if compiled is None else compiled
    out = np.full((d, 3), np.nan, dtype)
    if n < 2:
        return out
    step = max(1, (PASS_SAMPLES if compiled and n - 1 > SUBSAMPLE else BLOCK_SAMPLES) // n)
    for a in range(0, d, step):
        b = min(a + step, d)
        valid = np.asarray(mask[a:b], bool)
        # (every pair is valid where every sample is: no mask of the pairs)
        sigma = _sigma_every_pair(gyro, rate, a, b, dtype, compiled) if valid.all() else None
        if sigma is None or np.isnan(sigma).any():  # pairs left out, or NaN differences
            pair = valid[:, 1:] & valid[:, :-1]
            sigma = sigma_from_differences(_differences(gyro, rate, a, b, dtype), pair, compiled)
        out[a:b] = sigma.reshape(-1, 3)
    return out


def _sigma_every_pair(gyro: Float[np.ndarray, "d n 3"], rate: Float[np.ndarray, "d n 3"] | None,
                      a: int, b: int, dtype, compiled: bool) -> Float[np.ndarray, " r"]:
    """:func:`sigma_from_differences` of devices ``a:b`` where every pair is valid (fit's
    usual case; NaN for a row holding a NaN): long rows differenced and subsampled in one
    compiled pass when ``compiled``."""
    m = np.shape(gyro)[1] - 1
    if m <= SUBSAMPLE:
        return _sigma_equal(_differences(gyro, rate, a, b, dtype), m)
    if not compiled:
        r = _differences(gyro, rate, a, b, dtype)
        return _sigma_rows(r, r[:, subsample_ranks(m)])
    from ._noise_passes import differences

    r = None if rate is None else np.asarray(rate[a:b], dtype)
    return _sigma_rows(*differences(np.asarray(gyro[a:b], dtype), r, subsample_ranks(m)),
                       compiled=True)


def _differences(gyro: Float[np.ndarray, "d n 3"], rate: Float[np.ndarray, "d n 3"] | None,
                 a: int, b: int, dtype) -> Float[np.ndarray, "r m"]:
    """Lag-1 differences of ``gyro − rate`` of devices ``a:b``, a row per device and axis."""
    y = np.asarray(gyro[a:b], dtype)
    if rate is not None:
        y = y - np.asarray(rate[a:b], dtype)
    n = y.shape[1]
    rows = np.empty((b - a, 3, n - 1), dtype)
    np.subtract(y[:, 1:].transpose(0, 2, 1), y[:, :-1].transpose(0, 2, 1), out=rows)
    return rows.reshape(-1, n - 1)


def sigma_from_differences(rows: Float[np.ndarray, "r m"], valid: Bool[np.ndarray, "c m"],
                           compiled: bool = False) -> Float[np.ndarray, " r"]:
    """White-noise σ behind each row of differences ``Δy`` (``valid`` masks every
    group of ``r / c`` consecutive rows alike), in place; NaN for a row without one.

    The root mean square of the deviations from the median inside ±4σ₀, where σ₀
    is 1.4826 × their median (MAD), corrected for the truncation, over √2. The
    window keeps the steps of a rate table and outliers out, as a median would,
    but the RMS stays continuous when the output is quantised to about its noise
    (where the MAD of differences locks to whole LSBs). Past ~2σ per LSB most
    differences are exactly zero and the MAD collapses: then the RMS of all but
    the largest 0.5 % of the deviations is used. A row of more than
    :data:`SUBSAMPLE` valid differences: see :func:`_sigma_subsampled` (through the
    compiled passes when ``compiled``).
    """
    per = rows.shape[0] // max(valid.shape[0], 1)
    if valid.all() and not np.isnan(rows.sum()):  # every difference counts (the usual case)
        return _sigma_rows(rows, compiled=compiled)
    ok = np.repeat(valid, per, axis=0) & ~np.isnan(rows)
    counts = np.count_nonzero(ok, axis=1)
    out = np.full(rows.shape[0], np.nan, rows.dtype)
    for count in np.unique(counts):  # rows with as many valid differences, packed
        if count:
            sel = counts == count
            out[sel] = _sigma_rows(rows[sel][ok[sel]].reshape(-1, count), compiled=compiled)
    return out


@functools.lru_cache(maxsize=16)
def subsample_ranks(count: int) -> np.ndarray:
    """Ranks, among a row's ``count`` valid differences in their order, of those its
    window is placed from: all of them up to :data:`SUBSAMPLE`, else :data:`SUBSAMPLE`
    evenly spread (the middle one of as many equal strata)."""
    k = min(count, SUBSAMPLE)
    ranks = (2 * np.arange(k) + 1) * count // (2 * k)
    ranks.flags.writeable = False  # shared by the calls with this count
    return ranks


def _sigma_rows(r: Float[np.ndarray, "r m"], sub: Float[np.ndarray, "r k"] | None = None,
                compiled: bool = False) -> Float[np.ndarray, " r"]:
    """:func:`sigma_from_differences` of rows of valid differences (NaN for a row holding
    a NaN), given their :func:`subsample_ranks` columns or not: exact up to
    :data:`SUBSAMPLE` differences and on the rows the subsample cannot place the window
    of; ``r`` is overwritten."""
    count = r.shape[1]
    if count <= SUBSAMPLE:
        return _sigma_equal(r, count)
    if sub is None:
        sub = r[:, subsample_ranks(count)]
    sigma = _sigma_subsampled(r, sub, compiled)
    exact = np.isnan(sigma)
    if exact.any():
        sigma[exact] = _sigma_equal(r[exact], count)
    return sigma


def _sigma_subsampled(r: Float[np.ndarray, "r m"], sub: Float[np.ndarray, "r k"],
                      compiled: bool = False) -> Float[np.ndarray, " r"]:
    """The floor of long rows (every difference valid) with the window placed from the
    subsample: its median and MAD (numpy's introselect, or with ``compiled`` and an odd
    subsample the compiled selection, :func:`diffgyro._noise_passes.place`: the same
    values); then one compiled pass over
    every difference (:func:`diffgyro._noise_passes.window_sums` when ``compiled``, else
    numpy's operations, the same numbers to rounding) for the standard
    deviation of those inside the window, truncation-corrected, over √2. NaN where the
    exact statistic is needed: a NaN or an infinite difference, fewer than
    :data:`EXACT_INSIDE` inside, :data:`EXACT_TIES` of the subsample at its median.

    Error: the subsample's median drops out (the spread is about the window's mean);
    its MAD, off by about 3 % (1σ) for :data:`SUBSAMPLE` differences, moves only the
    window's edge, where a normal has little mass: about 0.1 % on the floor for white
    noise, at most 0.4 % over the diagnose catalogue (heavy tails put more mass at the
    edge), held under 1 % by ``tests/test_diagnose.py`` and ``tests/test_noise.py``.
    """
    m, k = r.shape[1], sub.shape[1]
    if compiled and k % 2:  # the window's two order statistics without a branch per value
        from ._noise_passes import place, window_sums

        centre, half_width, ties = place(sub)
    else:
        window_sums = _window_sums
        if compiled:
            from ._noise_passes import window_sums
        centre = _middle(sub, k)
        dev, ties = _deviations(sub, centre)
        half_width = 4.0 * 1.4826 * _middle(dev, k, bits=True)
    count, s1, s2 = window_sums(r, centre, half_width).T
    inside = np.maximum(count, 1)
    mean = s1 / inside
    ms = np.maximum(s2 / inside - mean * mean, 0.0) / TRUNC4
    exact = (count < EXACT_INSIDE * m) | (ties >= EXACT_TIES * k)
    return np.where(exact, np.nan, np.sqrt(ms / 2.0))


def _deviations(sub: Float[np.ndarray, "r k"], centre: Float[np.ndarray, " r"]
                ) -> tuple[Float[np.ndarray, "r k"], np.ndarray]:
    """``|sub − centre|`` per row, and how many of them are 0."""
    dev = np.abs(sub - centre[:, None])
    return dev, np.count_nonzero(dev == 0, axis=1)


def _window_sums(rows: Float[np.ndarray, "r m"], centre: Float[np.ndarray, " r"],
                 half_width: Float[np.ndarray, " r"]) -> Float[np.ndarray, "r 3"]:
    """:func:`diffgyro._noise_passes.window_sums` with numpy."""
    s = rows - centre[:, None]
    q = s * s
    inside = (q <= (half_width * half_width)[:, None]).astype(rows.dtype)
    return np.stack([inside.sum(axis=1), np.einsum("ij,ij->i", s, inside),
                     np.einsum("ij,ij->i", q, inside)], axis=1)


def _sigma_equal(r: Float[np.ndarray, "r m"], count: int) -> Float[np.ndarray, " r"]:
    """:func:`sigma_from_differences` of the first ``count`` order statistics of each
    row (the rest are +inf), in place; NaN for a row holding a NaN.

    The deviations' order statistics are selected on the integer view of the
    floats (see :func:`_middle`), where a selection costs about half what it
    costs on floats. Left of the median's place the values are ≤ it and right of it ≥, so the
    deviations are ``median − Δy`` and ``Δy − median`` (the numbers
    ``|Δy − median|`` gives). After the MAD's selection the lower half of each row
    lies below its upper middle (≤ 2 · MAD), inside the window, so only the upper
    half is compared with it; the few deviations outside are zeroed and each row's
    squares summed.
    """
    k = count // 2
    med = _middle(r, count)[:, None]
    np.subtract(med, r[:, :k], out=r[:, :k])
    np.subtract(r[:, k:], med, out=r[:, k:])
    window = 4.0 * 1.4826 * _middle(r, count, bits=True)
    top = r[:, k:]
    outside = top > window[:, None]
    inside = r.shape[1] - np.array([np.count_nonzero(o) for o in outside])
    collapsed = inside < COLLAPSED * count
    trimmed = _trimmed_ms(r[collapsed], count) if collapsed.any() else None
    top[outside] = 0.0
    ms = np.array([np.dot(row, row) for row in r])  # NaN stays: never outside
    ms /= np.maximum(inside, 1)
    ms /= TRUNC4
    if trimmed is not None:
        ms[collapsed] = np.where(np.isnan(ms[collapsed]), np.nan, trimmed)
    return np.sqrt(ms / 2.0)


def _trimmed_ms(r: Float[np.ndarray, "r m"], count: int) -> Float[np.ndarray, " r"]:
    """Mean square of all but the largest TRIM of each row's ``count`` deviations
    (the rest are +inf), or of all of them when that is 0 (a nearly constant output)."""
    lo, frac = trim_rank(count)
    hi = min(lo + 1, count - 1)
    r.view(f"i{r.itemsize}").partition((lo, hi) if hi > lo else lo, axis=1)
    trim = lerp(r[:, lo], r[:, hi], frac)
    sq = np.where(np.isfinite(r), r * r, 0.0)
    keep = r <= trim[:, None]
    ms = np.where(keep, sq, 0.0).sum(axis=1) / np.count_nonzero(keep, axis=1)
    return np.where(ms > 0, ms, sq.sum(axis=1) / count)


#: Share of the largest deviations the quantised fallback leaves out.
TRIM = 0.005
#: Below this share of the deviations inside the window the MAD has collapsed.
COLLAPSED = 0.9
#: E[Z² | |Z| ≤ 4] for a standard normal Z (the ±4σ₀ window's truncation correction).
TRUNC4 = 1.0 - 8.0 * math.exp(-8.0) / math.sqrt(2.0 * math.pi) / math.erf(4.0 / math.sqrt(2.0))


def trim_rank(count: int) -> tuple[int, float]:
    """Rank ``lo`` and fraction of the (1 − TRIM) quantile of ``count`` values, linear
    between order statistics ``lo`` and ``lo + 1`` as ``numpy.quantile`` places it."""
    h = (1.0 - TRIM) * (count - 1)
    return math.floor(h), h - math.floor(h)


def lerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    """``a + (b − a)·t``, from the nearer end (as ``numpy.quantile`` interpolates)."""
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


def _middle(r: np.ndarray, count: int, bits: bool = False) -> Float[np.ndarray, " r"]:
    """Median of the ``count`` smallest of each row: the middle one, or the mean of the
    middle two (one selection: the lower of the two is the largest below the upper).

    ``bits``: the rows are ≥ 0 and are selected on their integer view (the bit
    patterns of non-negative IEEE-754 numbers, +inf and NaN last, order as integers
    of their width do).
    """
    k = count // 2
    (r.view(f"i{r.itemsize}") if bits else r).partition(k, axis=1)
    upper = r[:, k].copy()
    if count % 2 == 0:
        return 0.5 * (r[:, :k].max(axis=1) + upper)
    return upper


def noise_floor(axes: Float[np.ndarray, "d 3"]) -> Float[np.ndarray, " d"]:
    """One σ per device: the root mean square over the axes."""
    return np.sqrt(np.mean(axes**2, axis=-1))


def start(gyro: Float[np.ndarray, "d n 3"], rate: Float[np.ndarray, "d n 3"] | None,
          mask: Bool[np.ndarray, "d n"], dtype=np.float64, threads: int | None = None,
          after: Future | None = None) -> Callable[[], tuple[np.ndarray, np.ndarray]]:
    """Start the noise floor of every device on threads (chunks of devices); the
    returned function waits and gives ``(noise_floor (d,), noise_axes (d, 3))``.

    numpy releases the GIL while it partitions and subtracts, so the chunks run
    beside each other and beside compiled programs. The chunks are claimed in turn by
    one worker fewer than ``threads`` (default: the cores), and by the caller once it
    asks for the result: a caller with work of its own first (a fit's motion check, on
    one core at a time) keeps a core for it, and its core joins the floor when it is done.
    ``after``: the chunks are handed to the threads once this work is done (work the
    caller waits for first, such as a motion check's read beside a fit: on two cores the
    floor would take a core from it).
    """
    d, n = np.shape(mask)
    step = max(1, CHUNK_SAMPLES // max(n, 1))
    compiled = d * n >= COMPILED_SAMPLES  # the whole batch's choice, whatever its chunks
    threads = threads or available_cores()
    # a thread per core this process may run on (kept for the process), one of them the caller's
    pool = host_pool("noise", threads)
    starts = range(0, d, step)
    axes = np.full((d, 3), np.nan, dtype)
    claims = itertools.count()  # (next() on a count is atomic: each chunk is claimed once)
    jobs: list = []
    handed = threading.Event()

    def work() -> None:
        while (c := next(claims)) < len(starts):
            a = starts[c]
            axes[a:a + step] = noise_axes(gyro[a:a + step],
                                          None if rate is None else rate[a:a + step],
                                          mask[a:a + step], dtype, compiled)

    def hand_out(_=None) -> None:
        jobs.extend(pool.submit(work) for _ in range(min(max(threads - 1, 1), len(starts))))
        handed.set()

    if after is None:
        hand_out()
    else:  # (at once where it is done already)
        after.add_done_callback(hand_out)

    def result() -> tuple[np.ndarray, np.ndarray]:
        handed.wait()
        work()  # the chunks no worker has claimed yet
        for job in jobs:
            job.result()
        return noise_floor(axes), axes

    return result
