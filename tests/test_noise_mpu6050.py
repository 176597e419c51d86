"""The noise model of a real static MPU-6050 recording against its datasheet.

``tests/data/mpu6050/mpu6050_static.csv.gz``: an unmoved MPU-6050 logged for 655 s
(t in s, gyro in °/s). Its time stamps are the host's read times, in bursts (median
step 2 ms, gaps up to 0.5 s), while the sensor samples evenly at about 99.3 Hz (the
sample count over the span): the model is identified at the mean interval. The
datasheet (InvenSense PS-MPU-6000A-00 rev. 3.4, section 6.1, gyroscope
specifications) gives a rate noise spectral density of 0.005 °/s/√Hz, typical.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from diffgyro.stochastic import identify_devices

DATA = Path(__file__).parent / "data" / "mpu6050" / "mpu6050_static.csv.gz"
#: Datasheet rate noise spectral density, °/s/√Hz (typical).
DENSITY = 0.005
N = 8192  # the first 82 s: the length test_diagnose_noise compiles for


@pytest.fixture(scope="module")
def recording():
    a = np.loadtxt(DATA, delimiter=",", skiprows=1)[:N]
    return np.deg2rad(a[:, 1:4]), (a[-1, 0] - a[0, 0]) / (N - 1)


@pytest.fixture(scope="module")
def entry(recording):
    rates, dt = recording
    entries, _ = identify_devices(rates[None], np.array([N]), (np.arange(N) * dt)[None], ["mpu6050"])
    return entries[0]


def test_arw_near_the_datasheet_density(entry):
    """The identified white noise is the datasheet's density within a factor of three (a
    typical figure; this unit's filter setting is not logged), its interval tight."""
    assert entry["status"] == "ok"
    for ax, axis in entry["axes"].items():
        white = axis["components"][0]
        assert white["kind"] == "white"
        arw = np.rad2deg(white["params"]["arw"]["value"])  # °/s/√Hz
        lo, hi = np.rad2deg(white["params"]["arw"]["ci"])
        assert DENSITY / 3 < arw < 3 * DENSITY, (ax, arw)
        assert lo < arw < hi and hi / lo < 1.1, (ax, lo, hi)


def test_no_walk_in_82_seconds_at_rest(entry):
    """No component is a random walk over 82 s of a unit at rest: a walk there would be
    the identification following a drift the recording does not hold."""
    for axis in entry["axes"].values():
        assert "random_walk" not in axis["structure"] and "rate_ramp" not in axis["structure"]


def test_nothing_below_resolution_and_white_as_allantools_reads_it(entry, recording):
    """No component the record cannot resolve (no process merged into the white part, every
    Gauss–Markov time inside the resolvable range, every parameter identified), and the white
    density within 10 % of allantools' read-out: the overlapping Allan deviation on the −1/2
    line, σ(τ)·√τ over τ = 0.1 … 1 s (geometric mean at octave τ)."""
    import allantools

    rates, dt = recording
    taus = dt * 2.0 ** np.arange(12)
    for k, (ax, axis) in enumerate(entry["axes"].items()):
        res = axis["resolution"]
        assert not res["merged"] and "fitted_structure" not in axis, ax
        lo, hi = res["gauss_markov_tau"]["min"], res["gauss_markov_tau"]["max"]
        for c in axis["components"]:
            assert all(p["status"] == "identified" for p in c["params"].values()), (ax, c)
            if c["kind"] == "gauss_markov":
                assert lo <= c["params"]["tau"]["value"] <= hi, (ax, c)
        t, adev, _, _ = allantools.oadev(rates[:, k], rate=1.0 / dt, data_type="freq", taus=taus)
        line = adev * np.sqrt(t)
        readout = float(np.exp(np.mean(np.log(line[(t >= 0.1) & (t <= 1.01)]))))
        arw = axis["components"][0]["params"]["arw"]["value"]
        assert arw == pytest.approx(readout, rel=0.10), (ax, arw, readout)
