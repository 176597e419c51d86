"""Allan deviations against NIST SP 1065's published 1000-point test (Handbook of Frequency
Stability Analysis, W. J. Riley, NIST Special Publication 1065, 2008, §12.4 and Table 31).

The data set is generated as SP 1065 prescribes: x₀ = 1234567890, xₙ₊₁ = 16807·xₙ mod
(2³¹ − 1), each divided by 2³¹ − 1, taken as 1000 fractional-frequency samples at τ₀ = 1 s.
The expected values are SP 1065's printed digits (seven significant), not another tool's
output; every computed value must round to them.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from diffgyro.allan import adev_nonoverlapping, cluster_sizes, mdev, oadev

TAUS = (1, 10, 100)
#: SP 1065 Table 31, rows "Allan Dev, Normal", "Overlapping", "Modified" (τ = 1, 10, 100 s).
PUBLISHED = {
    "adev": ("2.922319e-01", "9.965736e-02", "3.897804e-02"),
    "oadev": ("2.922319e-01", "9.159953e-02", "3.241343e-02"),
    "mdev": ("2.922319e-01", "6.172376e-02", "2.170921e-02"),
}


def park_miller(count: int) -> list[int]:
    """SP 1065's integer sequence: x₀ = 1234567890, xₙ₊₁ = 16807·xₙ mod (2³¹ − 1)."""
    x = [1234567890]
    for _ in range(count - 1):
        x.append(16807 * x[-1] % (2**31 - 1))
    return x


def nist_1000() -> np.ndarray:
    """SP 1065's 1000-point white-FM test data (fractional frequency)."""
    return np.array(park_miller(1000), dtype=np.float64) / (2**31 - 1)


def _digits(values) -> tuple[str, ...]:
    return tuple(f"{float(v):.6e}" for v in values)


def test_generator_matches_sp1065():
    """The integers SP 1065 prints after the seed, and the data's published standard deviation."""
    assert park_miller(4)[1:] == [395529916, 1209410747, 633705974]
    y = nist_1000()
    assert y.shape == (1000,)
    assert _digits([np.std(y, ddof=1)]) == ("2.884664e-01",)


@pytest.mark.parametrize("kind", ["adev", "oadev", "mdev"])
def test_published_deviations(kind):
    y = nist_1000()
    m = np.array(TAUS)
    if kind == "adev":
        got = adev_nonoverlapping(y, 1.0, m)
    elif kind == "oadev":
        got = np.asarray(oadev(y, 1.0, m)[0])
    else:
        got = mdev(y, 1.0, m)
    assert _digits(got) == PUBLISHED[kind]


def test_cli_taus_reproduce_published_oadev(tmp_path, capsys):
    """`diffgyro allan --taus 1,10,100 --json` on the data set as a gyro recording at 1 Hz."""
    import pandas as pd

    from diffgyro.cli import main

    y = nist_1000()
    path = tmp_path / "nist1000.csv"
    pd.DataFrame({"t": np.arange(1000.0), "gx": y, "gy": -y, "gz": 2.0 * y}).to_csv(path, index=False)
    assert main(["allan", str(path), "--taus", "1,10,100", "--json"]) == 0
    axes = json.loads(capsys.readouterr().out)["devices"][0]["axes"]
    assert axes["gx"]["tau"] == [1.0, 10.0, 100.0]
    assert _digits(axes["gx"]["adev"]) == PUBLISHED["oadev"]
    assert _digits(axes["gy"]["adev"]) == PUBLISHED["oadev"]  # sign does not matter
    assert _digits(np.array(axes["gz"]["adev"]) / 2.0) == PUBLISHED["oadev"]


def test_cli_taus_refused_when_not_a_multiple_of_dt(tmp_path, capsys):
    import pandas as pd

    from diffgyro.cli import main

    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": np.arange(200.0) * 0.5, "gx": nist_1000()[:200], "gy": 0.0,
                  "gz": 0.0}).to_csv(path, index=False)
    # the NIST series is not a gyro's: its unit is stated so that no plausibility note is added
    assert main(["allan", str(path), "--taus", "1,1.25", "--json", "--gyro-unit", "rad/s"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "rec.csv" in err and "1.25" in err
    assert main(["allan", str(path), "--taus", "1,abc"]) == 2
    assert "--taus" in capsys.readouterr().err


def test_cluster_sizes():
    np.testing.assert_array_equal(cluster_sizes([0.01, 0.1, 1.0], 0.01), [1, 10, 100])
    with pytest.raises(ValueError, match="0.015"):
        cluster_sizes([0.015], 0.01)
    with pytest.raises(ValueError):
        cluster_sizes([0.004], 0.01)


def test_companions_equal_allantools_on_other_data():
    """Beyond the three published τ: every cluster size of a longer series with a bias, and a
    stack of series (leading axes), against allantools (a cross-check, not the reference)."""
    import allantools

    rng = np.random.default_rng(5)
    y = 0.3 + rng.standard_normal((2, 3001)) * 1e-3 + np.cumsum(rng.standard_normal((2, 3001)), axis=-1) * 1e-5
    m = np.array([1, 2, 3, 7, 50, 333, 1000, 1001])
    dt = 0.01
    adev, md = adev_nonoverlapping(y, dt, m), mdev(y, dt, m)
    assert np.isnan(md[:, -1]).all()  # 3m > N (3002 phase points): no term
    for i in range(2):
        ref_a = allantools.adev(y[i], rate=1 / dt, data_type="freq", taus=m[:-1] * dt)[1]
        ref_m = allantools.mdev(y[i], rate=1 / dt, data_type="freq", taus=m[:-1] * dt)[1]
        np.testing.assert_allclose(adev[i, :-1], ref_a, rtol=1e-10)
        np.testing.assert_allclose(md[i, :-1], ref_m, rtol=1e-10)
