"""The front page's figure: one turn of the discovery loop on the README's walkthrough.

Two gyros are simulated through a thermal run whose bias follows temperature and its rate
of change (``bias_poly(2)+gradient``, the walkthrough's ``simulate`` line). ``fit`` with
``bias_poly(2)`` leaves a residual that follows dT/dt; ``diagnose`` names the missing
term; the refit with it leaves noise. The figure shows device 0's z-axis residual
before and after, with its temperature, and each fit's held-out RMS against the noise
floor. Run from the repository root::

    python docs/figures/discovery_loop.py      # writes docs/figures/discovery-loop.png
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import diffgyro  # noqa: E402

OUT = Path(__file__).with_name("discovery-loop.png")
DEG_H = 180.0 / np.pi * 3600.0  # rad/s -> deg/h


def main() -> None:
    diffgyro.enable_x64()
    from diffgyro.diagnose import diagnose
    from diffgyro.fit import fit
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 2, effects="bias_poly(2)+gradient", seed=0,
                        duration=3600.0, sample_rate=2.0)
    base = "bias_poly(2)"
    best = diagnose(base, batch).device(0).best  # the term the base model lacks, and its spec
    named = best.term
    fits = {spec: fit(spec, batch) for spec in (base, best.spec)}

    n = int(batch.n_valid[0])
    t = (batch.t[0, :n] - batch.t[0, 0]) / 60.0
    fig, (ax_t, ax_r) = plt.subplots(2, 1, figsize=(7.0, 3.6), sharex=True,
                                     gridspec_kw={"height_ratios": [1, 2.2]})
    ax_t.plot(t, batch.temp[0, :n], color="tab:red", lw=1.0)
    ax_t.set_ylabel("temp (°C)")
    for (spec, result), color in zip(fits.items(), ("tab:orange", "tab:blue")):
        rec = result.records()[0]
        ratio = rec["heldout_rms"] / rec["noise_floor"]
        res = np.asarray(result.residuals(batch))[0, :n, 2] * DEG_H
        ax_r.plot(t, res, color=color, lw=0.6, alpha=0.9,
                  label=f"{spec}: held-out RMS {ratio:.2f}× the noise floor")
    ax_r.set_ylabel("residual z (°/h)")
    ax_r.set_xlabel("time (min)")
    ax_r.legend(loc="lower left", fontsize=8, frameon=False)
    ax_t.set_title(f"diagnose {base} names {named}; the refit leaves noise", fontsize=10)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print(f"{OUT}: {OUT.stat().st_size / 1024:.0f} kB")


if __name__ == "__main__":
    main()
