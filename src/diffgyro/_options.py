"""The solver settings every fit path reads (:class:`FitOptions`).

The direct path (:mod:`diffgyro.fit`), the sums path (:mod:`diffgyro._fit_sums`) and
the random-walk fit (:mod:`diffgyro.kalman`) take the same options, so a setting
means the same thing whichever path runs.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

__all__ = ["FitOptions"]


class FitOptions(eqx.Module):
    """Solver settings. Integers are static; tolerances are arrays so changing them
    does not compile again."""

    n_blocks: int = eqx.field(static=True, default=100)
    n_folds: int = eqx.field(static=True, default=5)
    max_steps: int = eqx.field(static=True, default=100)
    chunk: int = eqx.field(static=True, default=64)
    rtol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-10)))
    atol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-14)))
    rank_tol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-10)))
    dtemp_window: float = eqx.field(static=True, default=60.0)
    #: "closed": closed form (linear part) + variable projection (time constants);
    #: "lm": one Levenberg–Marquardt solve over all parameters (the reference path).
    solver: str = eqx.field(static=True, default="closed")
    #: "sums" reads the samples once per trial of the time constants and never forms the
    #: design (the fit_sums package; Newton on the projected cost for time constants); "direct"
    #: forms it (optimistix LM for time constants); "auto": "sums" with the closed-form
    #: solver (linear models and time constants alike), "direct" with ``solver="lm"``.
    path: str = eqx.field(static=True, default="auto")
    #: The model-free noise floor per device and axis (on the host's threads beside
    #: the compiled fit, :mod:`diffgyro._noise`); False skips it (NaN) when only
    #: coefficients matter.
    noise_floor: bool = eqx.field(static=True, default=True)

    def replace(self, **kw) -> FitOptions:
        """These options with some fields changed (unknown names raise TypeError)."""
        fields = {f: getattr(self, f) for f in self.__dataclass_fields__}
        for k, v in kw.items():
            if k not in fields:
                raise TypeError(f"unknown fit option {k!r}; options: {', '.join(fields)}")
            fields[k] = jax.device_put(np.asarray(v)) if k in ("rtol", "atol", "rank_tol") else v
        return FitOptions(**fields)
