"""report.py: self-contained HTML pages with the diagnosis figures, written atomically."""

from __future__ import annotations

import base64
import os
import re

import hidden_effects as H
import numpy as np
import pytest

from diffgyro.data import Batch
from diffgyro.diagnose import diagnose, diagnose_auto
from diffgyro.effects import Gradient, registry
from diffgyro.report import (
    MAX_POINTS,
    named_term_residuals,
    outliers,
    residual_drop_figure,
    write_atomic,
    write_report,
)

#: The rate-table report's candidates: the hidden ``scale_asym`` and two that must lose to it.
#: Scoring every built-in candidate is test_diagnose's business; a report needs a named term
#: and a ladder, and each candidate scored here costs its programs' compile.
CANDIDATES = ["scale_asym", "g_sens", "bias_poly"]


@pytest.fixture(scope="module")
def rate_table():
    hs = [H.make_recording("rate_table", "scale_asym" if k < 3 else None, "bias_poly(1)+scale_poly(0)",
                           60 + k, size=2.0, noise=H.Noise(white=3e-4), hours=1.0, device=f"rt{k}")
          for k in range(4)]
    return Batch.from_recordings([h.recording for h in hs])


@pytest.fixture(scope="module")
def rate_ladder(rate_table):
    return diagnose_auto("bias_poly(1)+scale_poly(0)", rate_table, CANDIDATES, max_steps=2)


def _images(page: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page)]


def test_pages_are_self_contained(rate_table, rate_ladder, tmp_path):
    ladder = rate_ladder
    assert [s.added for s in ladder.steps] == [None, "scale_asym"]
    paths = write_report(ladder.first, rate_table, tmp_path / "r", ladder=ladder)
    names = sorted(p.name for p in paths)
    assert names == ["index.html", "rt0.html", "rt1.html", "rt2.html", "rt3.html"]
    page = (tmp_path / "r" / "rt0.html").read_text()
    imgs = _images(page)
    # time, rate/force, Allan, candidates, ladder (no temperature figure: no thermal span needed)
    assert len(imgs) >= 5 and all(i.startswith(b"\x89PNG") for i in imgs)
    assert not re.search(r"""(src|href)=['"]https?:""", page)  # nothing fetched from outside
    assert "scale_asym" in page and "missing_effect" in page
    index = (tmp_path / "r" / "index.html").read_text()
    assert "rt3.html" in index and "Model ladder" in index and "Outlier devices" in index
    assert "held-out RMS (rad/s)" in index and "value (rad/s" not in index  # units in the table
    assert "`" not in re.sub(r"data:image[^'\"]+", "", index + page)  # term names set as code
    assert not [p for p in (tmp_path / "r").iterdir() if p.name.startswith(".")]  # no temp files
    assert oct(os.stat(tmp_path / "r" / "index.html").st_mode & 0o444) == oct(0o444)


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "page.html"
    write_atomic(path, "old")

    with pytest.raises(TypeError):
        write_atomic(path, 12345)  # not text: the write fails
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["page.html"]


def test_outlier_device_is_listed(rate_table):
    import numpy as np

    # a bias far outside the others' spread makes one device an outlier
    recs = rate_table.recordings()
    recs[2] = H.replace_recording(recs[2], recs[2].gyro + np.array([0.5, 0.0, 0.0]))
    batch = Batch.from_recordings(recs)
    dg = diagnose("bias_poly(1)+scale_poly(0)+scale_asym", batch, CANDIDATES)  # the ladder's programs
    flagged = outliers(dg)
    assert any(dev == "rt2" and "bias_poly(1).c0" in why for dev, why in flagged), flagged


@pytest.fixture(scope="module")
def hidden_gradient():
    """A thermal run with a hidden dT/dt gradient beside a clean one, and the diagnosis."""
    noise = H.Noise(white=2e-4, flicker=0.1, drift=0.1)
    hs = [H.make_recording("thermal", "gradient", "bias_poly(2)", 21, size=2.0, noise=noise,
                           device="grad"),
          H.make_recording("thermal", None, "bias_poly(2)", 22, noise=noise, device="clean")]
    batch = Batch.from_recordings([h.recording for h in hs])
    return hs, batch, diagnose("bias_poly(2)", batch, ["gradient", "temp_diff", "bias_poly"])


def _drop_figure(dg, batch, e_new, spec):
    n = int(batch.n_valid[0])
    dtemp = np.asarray(dg.fit.signals(batch).dtemp[0, :n])
    return residual_drop_figure(dg.model, spec, batch.recording(0), np.asarray(dg.residuals[0, :n]),
                                e_new, dtemp)


def _labelled(ax) -> dict:
    """Drawn residual series of an axes by model spec (label "<spec>: RMS ...")."""
    return {ln.get_label().split(":")[0]: ln for ln in ax.get_lines() if not ln.get_label().startswith("_")}


@pytest.fixture(scope="module")
def gradient_report(hidden_gradient, tmp_path_factory):
    """The hidden-gradient diagnosis' report, written once, and the figures drawn for it."""
    from diffgyro import report

    hs, batch, dg = hidden_gradient
    out = tmp_path_factory.mktemp("gradient-report")
    figures = []
    encode = report.figure_png
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(report, "figure_png", lambda fig: figures.append(fig) or encode(fig))
        write_report(dg, batch, out)
    return out, figures


def test_thermal_page_has_heating_and_cooling(hidden_gradient, gradient_report):
    """The thermal figure is on the page and draws the heating samples red and the cooling ones
    blue: each coloured cloud is checked against the recorded temperature's own slope (a
    one-minute moving mean, on the ramps only), so swapped states or colours fail."""
    import matplotlib.colors as mcolors

    hs, batch, dg = hidden_gradient
    out, figures = gradient_report
    page = (out / "grad.html").read_text()
    assert "<h2>Residual against temperature and dT/dt</h2>" in page
    assert "gradient" in page
    thermal = [f for f in figures if "heating red, cooling blue" in f.axes[0].get_title()]
    assert len(thermal) == 2  # one per device, grad's first
    lines = {ln.get_label(): ln for ln in thermal[0].axes[0].get_lines()}
    assert mcolors.same_color(lines["heating"].get_color(), "tab:red")
    assert mcolors.same_color(lines["cooling"].get_color(), "tab:blue")
    rec = batch.recording(0)
    e = np.asarray(dg.residuals[0, : rec.n])
    kernel = np.ones(121) / 121  # one minute at 2 Hz
    smooth = np.convolve(rec.temp, kernel, mode="same")
    slope = np.gradient(smooth, rec.t) * 60.0  # °C/min
    edge = slice(60, rec.n - 60)  # the moving mean is cut short at the ends
    index = {(float(x), float(y)): i for i, (x, y) in enumerate(zip(rec.temp, e.mean(1)))}
    for label, sign in (("heating", 1.0), ("cooling", -1.0)):
        pts = [index[(float(x), float(y))] for x, y in zip(*lines[label].get_data())]
        on_ramp = [i for i in pts if edge.start <= i < edge.stop and abs(slope[i]) > 0.3]
        assert len(on_ramp) > 100, label
        agree = np.mean(np.sign(slope[on_ramp]) == sign)
        assert agree > 0.95, (label, agree)


def test_report_shows_the_error_fall_with_the_named_term(hidden_gradient, gradient_report):
    hs, batch, dg = hidden_gradient
    assert dg.devices[0].best.spec == "bias_poly(2)+gradient" and dg.devices[1].best is None
    named = named_term_residuals(dg, batch)
    assert set(named) == {0}, "only the device with a named term gets the overlay"
    spec, e_new = named[0]
    assert spec == "bias_poly(2)+gradient" and e_new.shape == (int(batch.n_valid[0]), 3)
    e_base = np.asarray(dg.residuals[0, : int(batch.n_valid[0])])
    # the two residuals differ by the hidden effect the simulator added
    k = int(np.argmax(np.mean(e_base**2, 0) - np.mean(e_new**2, 0)))
    assert np.corrcoef(e_base[:, k] - e_new[:, k], hs[0].hidden[:, k])[0, 1] > 0.95
    fig = _drop_figure(dg, batch, e_new, spec)
    time_ax, signal_ax = fig.axes
    assert time_ax.get_xlabel() == "time (min)" and signal_ax.get_xlabel() == "dT/dt (°C/min)"
    # the second panel is drawn against dT/dt: the simulator's true die dT/dt
    x = np.asarray(_labelled(signal_ax)["bias_poly(2)"].get_xdata())
    ddie = hs[0].env["ddie"]
    assert np.corrcoef(x, ddie[::max(1, len(ddie) // MAX_POINTS)])[0, 1] > 0.9
    for ax in fig.axes:
        lines = _labelled(ax)
        assert set(lines) == {"bias_poly(2)", "bias_poly(2)+gradient"}
        rms = {sp: float(np.sqrt(np.mean(np.asarray(ln.get_ydata(), float) ** 2))) for sp, ln in lines.items()}
        assert rms["bias_poly(2)+gradient"] < 0.5 * rms["bias_poly(2)"]
        # with the term, what is left is the noise the simulator added
        assert rms["bias_poly(2)+gradient"] == pytest.approx(hs[0].noise_rms, rel=0.15)
        # each label states the RMS of every sample of that model on the drawn axis
        for sp, e in (("bias_poly(2)", e_base), (spec, e_new)):
            assert f"RMS {np.sqrt(np.mean(e[:, k] ** 2)):.3g} rad/s" in lines[sp].get_label()
    import matplotlib.pyplot as plt

    plt.close(fig)
    out, _ = gradient_report
    grad, clean = (out / "grad.html").read_text(), (out / "clean.html").read_text()
    assert "The residual without and with gradient" in grad and "without and with" not in clean
    assert len(_images(grad)) == len(_images(clean)) + 1


def test_a_term_without_a_signal_is_drawn_against_the_one_it_follows(hidden_gradient, monkeypatch):
    """A user effect that names no signal: the figure picks the one its contribution follows."""
    hs, batch, dg = hidden_gradient
    n = int(batch.n_valid[0])
    e_new = np.asarray(dg.residuals[0, :n]) - hs[0].hidden  # the hidden dT/dt term taken out
    monkeypatch.setattr(Gradient, "follows", None)
    fig = _drop_figure(dg, batch, e_new, "bias_poly(2)+gradient")
    assert fig.axes[1].get_xlabel() == "dT/dt (°C/min)"


def test_every_builtin_effect_names_its_signal():
    for name, cls in registry().items():
        if cls.__module__.startswith("diffgyro."):
            assert isinstance(cls.follows, str), name


def test_an_aux_term_is_drawn_against_its_column():
    from diffgyro.fit import fit
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 1, effects="bias_poly(1)+aux(vdd)", seed=8, duration=3600.0,
                        sample_rate=1.0, noise={"arw": 2e-5, "rrw": 0.0, "bias_instability": 0.0})
    n = int(batch.n_valid[0])
    base = fit("bias_poly(1)", batch)
    e_base = np.asarray(base.residuals(batch))[0, :n]
    e_new = np.asarray(fit("bias_poly(1)+aux(vdd)", batch).residuals(batch))[0, :n]
    fig = residual_drop_figure(base.model, "bias_poly(1)+aux(vdd)", batch.recording(0), e_base, e_new)
    assert fig.axes[1].get_xlabel() == "vdd"
    # the base residual, drawn against the column, follows it: the term's signal
    x, y = (np.asarray(a, float) for a in _labelled(fig.axes[1])["bias_poly(1)"].get_data())
    assert abs(np.corrcoef(x, y)[0, 1]) > 0.8


@pytest.fixture(scope="module")
def batch_500_fit():
    """500 devices (bias_poly(1)+gradient fitted) with two x biases far from the others."""
    import dataclasses

    from diffgyro.fit import fit
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 500, effects="bias_poly(1)+gradient", seed=0, duration=1800.0,
                        sample_rate=0.5)
    recs = batch.recordings()
    for k, offset in ((7, 0.2), (321, -0.15)):
        recs[k] = dataclasses.replace(recs[k], gyro=recs[k].gyro + np.array([offset, 0.0, 0.0]))
    batch = Batch.from_recordings(recs)
    return batch, fit("bias_poly(1)+gradient", batch, noise_floor=False)


def test_a_500_device_summary_reads(batch_500_fit):
    """Histograms with units on the axes, the y axis in devices, the outliers named."""
    from diffgyro.report import coefficient_unit, coefficients_figure

    batch, result = batch_500_fit
    fig, named = coefficients_figure(result, list(batch.devices))
    axes = [ax for ax in fig.axes if ax.get_title()]
    assert len(axes) == 9  # 3 axes x (c0, c1, g)
    for ax in axes:
        assert ax.get_ylabel() == "devices"
        assert re.fullmatch(r"value \(rad/s( per (T_s|°C/s))?\)", ax.get_xlabel()), ax.get_xlabel()
        assert len(ax.patches) >= 10  # a histogram, not a strip of 500 dots
        assert all(t.get_fontsize() >= 7 for t in ax.get_xticklabels())
    c0 = next(ax for ax in axes if ax.get_title() == "x: bias_poly(1).c0")
    assert {t.get_text().split(" = ")[0] for t in c0.texts} >= {"dev007", "dev321"}
    assert set(named["x: bias_poly(1).c0"]) >= {"dev007", "dev321"}
    fig.canvas.draw()  # no y label runs into a neighbouring panel
    renderer = fig.canvas.get_renderer()
    for ax in axes:
        box = ax.yaxis.label.get_window_extent(renderer)
        assert not any(box.overlaps(other.get_window_extent(renderer)) for other in axes
                       if other is not ax)
    assert coefficient_unit(result.model, "gradient.g") == "rad/s per °C/s"
    assert coefficient_unit(result.model, "bias_poly(1).c0") == "rad/s"
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_summary_text_has_units_links_and_no_backticks():
    from diffgyro.model import ErrorModel
    from diffgyro.report import _text, coefficient_unit

    assert _text("add `gradient` & <x>") == "add <code>gradient</code> &amp; &lt;x&gt;"
    m = ErrorModel.from_spec("bias_poly(3)+thermal_lag")
    assert coefficient_unit(m, "bias_poly(3).c2") == "rad/s per T_s^2"
    assert coefficient_unit(m, "thermal_lag.tau") == "s"
