"""XLA compiler options of the programs that set their own (the sums path's, the motion check's,
the noise identification's and the Allan deviation's)."""

from __future__ import annotations

import os
import re


def _in_xla_flags(name: str) -> bool:
    """Whether ``XLA_FLAGS`` sets the option ``name``."""
    return any(f.lstrip("-").split("=")[0] == name for f in os.environ.get("XLA_FLAGS", "").split())


#: XLA options of the group program: its sums may be reassociated, which lets LLVM
#: vectorise the variadic reduction (XLA keeps every sum in source order otherwise, one
#: scalar accumulator per product). NaN, ±inf, division and library functions keep
#: their IEEE meaning. Sums agree with the ordered ones to rounding (about 5e-13
#: relative on the benchmark's bias_poly(3)) and run faster (bias_poly(3) by 7 %,
#: thermal_lag by about 15 %).
REASSOCIATE = dict(xla_cpu_enable_fast_math=True, xla_cpu_fast_math_honor_nans=True,
                   xla_cpu_fast_math_honor_infs=True, xla_cpu_fast_math_honor_division=True,
                   xla_cpu_fast_math_honor_functions=True)
#: XLA options of every group program but a fused linear model's: XLA's older loop
#: emitters instead of its MLIR fusion emitters. Such a program has many kernels (a
#: Newton loop, the lag recursions, per-axis columns, small factorisations) and XLA
#: spends most of its compile time emitting and optimising them one by one. The older
#: emitters compile such a program in about 60 % of the time and run it 9-14 % slower,
#: the right trade for the model-discovery loop, which compiles a program per spec and
#: fits each once. Fused linear models (every column shared by the axes: bias_poly and
#: the like) keep the fusion emitters: their one pass over the samples runs at memory
#: speed.
FAST_COMPILE = dict(xla_cpu_use_fusion_emitters=False)
#: XLA options of a large program whose run is small beside its compile (noise
#: identification of devices × axes, run once per batch): the loop emitters
#: (:data:`FAST_COMPILE`) and LLVM's lighter pipeline (level 1): identify's program
#: compiles in about three quarters of the time and runs about 10 % slower.
#: An optimisation level set in ``XLA_FLAGS`` (the test suite's 0) is kept: a program's
#: options would override it.
LIGHT_COMPILE = dict(FAST_COMPILE) if _in_xla_flags("xla_backend_optimization_level") \
    else dict(FAST_COMPILE, xla_backend_optimization_level=1)
#: XLA options that skip the HLO verifier, which XLA runs after every pass of its
#: pipeline to check the module's invariants: it reads the module and changes nothing (the
#: optimised HLO of every program of a ``diagnose`` is the same text without it), and it
#: took 8-9 % of the diagnosis's scoring program's compile time without optimisation.
#: Passes disabled in ``XLA_FLAGS`` are kept: a program's options would override them.
NO_VERIFIER = {} if _in_xla_flags("xla_disable_hlo_passes") \
    else dict(xla_disable_hlo_passes="hlo-verifier")
#: XLA options of a tiny program run once (LLVM without optimisation passes, no HLO
#: verifier: :data:`NO_VERIFIER`).
ONCE = dict(xla_backend_optimization_level=0, xla_cpu_use_fusion_emitters=False, **NO_VERIFIER)
#: XLA options of an unoptimised program compiled on a thread beside other work: LLVM
#: compiles its module as one part instead of splitting it over XLA's threads. The
#: diagnosis's scoring program of the walkthrough compiles in 15 % less CPU time so, with
#: the same bits on every simulated plan tried (thermal, warm-up, rate table, six faces);
#: with them the first ``noise`` call of the walkthrough takes 5 % less CPU time, its
#: chosen models unchanged and the rejected candidates' criteria within 1e-9 relative.
ONE_PART = dict(xla_cpu_parallel_codegen_split_count=1)
#: Samples (devices × samples, or series × samples) of a batch at most this large: its
#: fit, motion check, diagnosis and noise identification run programs compiled with
#: :data:`ONCE`. Such a batch (a command line walkthrough's file, a test's) is computed in
#: milliseconds either way, and the first call of a new model is what a person waits for:
#: unoptimised programs compile in a third to a seventh of the time and run 3-5× slower.
SMALL_WORK = 1 << 16

#: Options this process's XLA refused (a newer or older XLA drops or renames its flags:
#: jaxlib 0.11 knows no ``xla_cpu_use_fusion_emitters``); the programs compile without them.
REFUSED: set[str] = set()


def accepted(options: dict | None) -> dict | None:
    """``options`` without those this XLA refused (None where none is left)."""
    kept = {k: v for k, v in (options or {}).items() if k not in REFUSED}
    return kept or None


def refuse(error: Exception) -> bool:
    """Note the option that ``error`` (XLA's "No such compile option") names; whether it is
    one not refused before, so that compiling again without it can succeed."""
    found = re.search(r"No such compile option: '([^']+)'", str(error))
    if found is None or found.group(1) in REFUSED:
        return False
    REFUSED.add(found.group(1))
    return True
