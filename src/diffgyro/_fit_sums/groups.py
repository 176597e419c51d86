"""Sizes of the compiled calls: devices per group, the chunk of the reduction, and each
device's valid-sample count."""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool

from ..data import valid_samples

#: Longest sample chunk of the variadic reduction (shortened to the shortest fold block).
CHUNK = 32
#: About this many samples (devices × samples) go into one compiled call.
GROUP_SAMPLES = 1 << 17
#: Models whose columns are all shared by the three axes and pointwise (temperature
#: polynomials, gradient, temp_diff) sum in one fused pass with no group-sized
#: temporaries: their groups are this many times larger (fewer calls). Others
#: materialise per-axis columns and run fastest with the group in cache: on a
#: 2-core CPU with 32 MB L3, fog-one-run's regression at 10 000 samples runs about twice as fast
#: in groups of 8 devices as of 16, and bias_poly(3) fastest in groups of 64.
FUSED_GROUP_FACTOR = 8
#: Models with time constants run batched Newton loops in lockstep: a group takes as
#: many passes as its slowest device needs for the full fit and the folds' refits.
#: Their groups hold this many times fewer samples (at least 2 devices): at 10 000
#: samples per device that is 2 devices, which fits bias_poly(1)+thermal_lag fastest
#: (smaller groups wait less for their slowest device; a single device per call pays
#: the call overhead); at 2000 samples the group size hardly matters.
NONLINEAR_GROUP_DIVISOR = 4
#: Most devices in one compiled call. XLA's CPU runtime (jax 0.10) can hang on very
#: large groups (1024 devices × 640 samples on one CPU device; two groups of 256 side
#: by side on two CPU devices), all threads idle; groups of 128 run at every length from
#: 200 to 10 000 samples. Short recordings would otherwise ask for such groups.
MAX_GROUP_DEVICES = 128
#: On an accelerator a compiled call runs its devices side by side and costs a launch and
#: a transfer whatever its size, and no slowest device holds the others back by more than
#: its own steps: a group there holds about this many samples (a few hundred MB of
#: float64 inputs), at most ACCELERATOR_MAX_GROUP_DEVICES devices.
ACCELERATOR_GROUP_SAMPLES = 1 << 24
ACCELERATOR_MAX_GROUP_DEVICES = 1 << 14


def pow2_floor(x: int) -> int:
    """The largest power of two not above ``x`` (1 for x ≤ 1)."""
    return 1 << (max(int(x), 1).bit_length() - 1)


def group_size(n_devices: int, length: int, samples: int | None = None,
               most: int | None = None) -> int:
    """Devices per compiled call: a power of two, about ``samples`` (GROUP_SAMPLES)
    samples, at most ``most`` (MAX_GROUP_DEVICES), ≥ 8 devices only when the batch has
    them (5 and 7 devices share a group size of 8). Independent of the device count
    beyond one group: no recompilation."""
    samples = GROUP_SAMPLES if samples is None else samples
    cap = pow2_floor(max(samples // max(length, 1), 1))
    want = 1 << max(int(n_devices) - 1, 7).bit_length()  # next power of two ≥ n, at least 8
    return max(1, min(cap, want, MAX_GROUP_DEVICES if most is None else most))


def devices_per_call(n_devices: int, length: int, nonlinear: bool, fused: bool,
                     platform: str = "cpu", senders: int = 4) -> int:
    """The group size of a model on ``platform``: on a CPU smaller with time constants (at
    least 2 devices) and larger for a fused linear model; on an accelerator as large as
    ACCELERATOR_GROUP_SAMPLES allows, a linear model's batch spread over two groups per
    sending thread (``senders``, :mod:`.transfer`: its transfers are what it waits for), a
    model with time constants in as few calls as can be (its Newton loop is a sequence of
    launches, whatever the group's size). The constants are read here, at the call."""
    if platform != "cpu":
        spread = n_devices if nonlinear else -(-n_devices // (2 * max(senders, 1)))
        return group_size(spread, length, ACCELERATOR_GROUP_SAMPLES, ACCELERATOR_MAX_GROUP_DEVICES)
    if nonlinear:
        return max(group_size(n_devices, length, GROUP_SAMPLES // NONLINEAR_GROUP_DIVISOR),
                   min(2, n_devices))
    return group_size(n_devices, length, GROUP_SAMPLES * (FUSED_GROUP_FACTOR if fused else 1))


def chunk_size(min_valid: int, n_blocks: int, length: int) -> int:
    """Chunk of the reduction: a power of two dividing the length, no longer than the
    shortest fold block (so a chunk holds at most one block boundary)."""
    c = min(CHUNK, pow2_floor(max(min_valid // max(n_blocks, 1), 1)), length & -length)
    return max(c, 1)


def valid_counts(mask: Bool[np.ndarray, "d n"]) -> tuple[np.ndarray, np.ndarray]:
    """Valid samples of every device, and whether they come first (a prefix mask).

    One pass of fast reads: counts by popcount of the mask's bytes read as
    64-bit words; the valid samples come first when the first invalid one is
    at the count.
    """
    mask = np.asarray(mask, bool)
    d, n = mask.shape
    nv = valid_samples(mask)
    first_invalid = np.argmin(mask, axis=1) if n else np.zeros(d, np.int64)
    return nv, (nv == n) | (first_invalid == nv)
