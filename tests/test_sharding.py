"""The device axis of each chunk sharded over several JAX devices (CPU devices forced with
XLA_FLAGS in one subprocess for all the checks): same results as one device, no
collectives, no hang."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from pipeline_data import CHUNK, MODEL, load_outputs, make_dataset

from diffgyro.pipeline import fit_dataset

TESTS = Path(__file__).parent
PRELUDE = f"""
import json, re, sys
sys.path.insert(0, {str(TESTS)!r})
import diffgyro
diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
import jax
import numpy as np
assert jax.local_device_count() == 2, jax.devices()
"""


def run_forced(sections: dict[str, str], timeout: float) -> dict:
    """Run every script of ``sections`` in one process with two forced host devices (one
    JAX import, one set of compiles); each section prints nothing and returns its result
    as ``out``. Returns section name → result, or → {"error": traceback} for a section that
    raised. A hang fails every test that reads the run at ``timeout``."""
    body = ["import traceback", "results = {}"]
    for name, script in sections.items():
        body += [f"def _section_{name}():",
                 textwrap.indent(textwrap.dedent(script).strip(), "    "),
                 "    return out",
                 "try:",
                 f"    results[{name!r}] = _section_{name}()",
                 "except Exception:",
                 f"    results[{name!r}] = {{'error': traceback.format_exc()[-3000:]}}"]
    body.append("print(json.dumps(results))")
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    env["JAX_PLATFORMS"] = "cpu"
    try:
        proc = subprocess.run([sys.executable, "-c", PRELUDE + "\n".join(body)], env=env,
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"sharded run did not finish in {timeout} s (hang?)")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_close(a, b, rel=1e-12, path="") -> None:
    """Same structure and text; numbers equal to ``rel`` (summation order may differ)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), path
        for k in a:
            assert_close(a[k], b[k], rel, f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_close(x, y, rel, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert math.isclose(a, b, rel_tol=rel, abs_tol=1e-300), (path, a, b)
    else:
        assert a == b, (path, a, b)


STREAM = """
from diffgyro.pipeline import fit_dataset
from diffgyro.pipeline import _chunkfit as chunkfit
fit_dataset([DATA], MODEL, out=ROOT + "/sharded/cal.json", chunk_devices=CHUNK,
            progress=False, shard=True)
# the sharded direct path (linear models the sums path cannot take): split over both
# devices, and no collective operation in the compiled program
fitter = chunkfit.ChunkFitter(MODEL, CHUNK, shard=True)
from diffgyro.io import load
from diffgyro.data import Batch
batch = Batch.from_recordings(load(DATA + "/part-00.parquet")[:CHUNK])
full = batch.select(np.minimum(np.arange(fitter.padded), batch.n_devices - 1))
f = lambda x: None if x is None else jax.numpy.asarray(x)
from diffgyro.data import sampling_intervals
from diffgyro._signal_builder import stacked_signals
sig = stacked_signals(f(full.t), f(full.gyro), f(full.mask), f(full.rate), f(full.temp),
                      f(full.temp_ext), f(full.accel), None, f(sampling_intervals(full)), {},
                      fitter.opts.dtemp_window)
sig = jax.device_put(sig, jax.sharding.NamedSharding(fitter.mesh,
                                                     jax.sharding.PartitionSpec("devices")))
compiled = chunkfit._solve.lower(fitter.model, sig, fitter.opts, fitter.block,
                                 fitter.mesh).compile()
hlo = compiled.compiled.as_text()
r = chunkfit._solve(fitter.model, sig, fitter.opts, fitter.block, fitter.mesh)
out = {"n_shards": fitter.n_shards, "padded": fitter.padded,
       "collectives": len(re.findall(r"(all-reduce|all-gather|all-to-all|"
                                     r"collective-permute|reduce-scatter)", hlo)),
       "out_devices": len(r["rms"].sharding.device_set)}
"""

VARPRO = """
from diffgyro.simulate import simulate
from diffgyro.pipeline._chunkfit import ChunkFitter
batch, truth = simulate("warmup", 5, effects="bias_poly(0)+warmup", seed=3,
                        sample_rate=0.5, duration=1800.0)
out = {}
for name, shard in (("sharded", True), ("single", False)):
    fitter = ChunkFitter("bias_poly(0)+warmup", 5, {"n_folds": 2}, shard=shard)
    r = fitter.fit_direct(batch)
    out[name] = {"n_shards": fitter.n_shards, "beta": r.params.beta.tolist(),
                 "theta": r.params.theta.tolist(), "rms": r.rms.tolist(),
                 "heldout_rms": r.heldout_rms.tolist(), "status": r.status.tolist(),
                 "steps": r.steps.tolist()}
"""

# fit()'s sums path for both specs of test_two_cpu_devices_fit_on_the_first
FIRST = """
import diffgyro._fit_sums.groups as fs
from diffgyro.fit import fit
from diffgyro.simulate import simulate
old = fs.MAX_GROUP_DEVICES
fs.MAX_GROUP_DEVICES = 4   # 11 devices: 3 groups, the last one partial
batch, _ = simulate("thermal", 11, effects="bias_poly(2)+thermal_lag", seed=4,
                    duration=1800.0)
out = {}
put = jax.device_put
try:
    for spec in SPECS:
        seen = []
        jax.device_put = lambda x, d=None, **k: (seen.append(getattr(d, "id", None)),
                                                 put(x, d, **k))[1]
        r = fit(spec, batch, path="sums")
        jax.device_put = put
        out[spec] = {"beta": r.params.beta.tolist(), "theta": r.params.theta.tolist(),
                     "heldout_rms": r.heldout_rms.tolist(), "status": r.status.tolist(),
                     "devices": sorted(set(i for i in seen if i is not None))}
finally:
    jax.device_put = put
    fs.MAX_GROUP_DEVICES = old
"""

LARGEST = """
import diffgyro._fit_sums.groups as fs
from diffgyro import Batch
from diffgyro.fit import fit
d, n = 3 * fs.MAX_GROUP_DEVICES, 640
rng = np.random.default_rng(0)
temp = 20 + 10 * np.sin(np.linspace(0, 3, n))[None, :] + rng.normal(size=(d, 1))
gyro = 1e-3 * (temp[..., None] - 20) * 0.01 + 1e-5 * rng.normal(size=(d, n, 3))
batch = Batch(t=np.broadcast_to(np.arange(n, dtype=float), (d, n)).copy(), gyro=gyro,
              mask=np.ones((d, n), bool), n_valid=np.full(d, n), temp=temp,
              devices=tuple(f"u{i}" for i in range(d)))
assert fs.group_size(d, n, fs.GROUP_SAMPLES * fs.FUSED_GROUP_FACTOR) == fs.MAX_GROUP_DEVICES
r = fit("bias_poly(3)", batch, path="sums")
out = {"ok": int(np.sum(np.asarray(r.status) == 0)), "d": d}
"""

DEFAULT = """
from diffgyro.pipeline._chunkfit import ChunkFitter, local_mesh
out = {"default": local_mesh() is None,
       "fitter": ChunkFitter("bias_poly(1)", 4).n_shards,
       "forced": ChunkFitter("bias_poly(1)", 4, shard=True).n_shards}
"""

S2 = """
from diffgyro import Batch
from diffgyro.fit import fit
d, n = 256, 2000
rng = np.random.default_rng(5)
t = np.broadcast_to(np.arange(n, dtype=float), (d, n)).copy()
temp = 20 + 15 * np.sin(t / 700.0) + rng.normal(size=(d, 1))
temp_ext = 0.7 * temp + 5 + 0.5 * rng.normal(size=temp.shape)
rate = np.repeat(rng.choice([-1.0, 0.0, 1.0], size=(d, n // 200 + 1, 3)), 200,
                 axis=1)[:, :n]
gyro = rate * 1.001 + 1e-3 * (temp - 20)[..., None] + 1e-4 * rng.normal(size=rate.shape)
batch = Batch(t=t, gyro=gyro, mask=np.ones((d, n), bool), n_valid=np.full(d, n),
              temp=temp, temp_ext=temp_ext, rate=rate,
              devices=tuple(f"u{i}" for i in range(d)))
for _ in range(2):
    r = fit("bias_poly(2)+scale_poly(2)+gradient+temp_diff", batch, noise_floor=False)
out = {"ok": int(np.sum(np.asarray(r.status) == 0)), "d": d}
"""

FIRST_SPECS = ["bias_poly(2)", "bias_poly(1)+thermal_lag"]


@pytest.fixture(scope="module")
def forced(tmp_path_factory):
    """Every two-device check run in one subprocess (the sections above, in this order;
    the dataset of the streaming check written first); returns (results, its folder)."""
    root = tmp_path_factory.mktemp("forced")
    data = root / "data"
    make_dataset(data, files=(4, 3), seed=11)
    consts = (f"DATA, ROOT, MODEL, CHUNK = {str(data)!r}, {str(root)!r}, {MODEL!r}, {CHUNK}\n"
              f"SPECS = {FIRST_SPECS!r}\n")
    sections = {"stream": consts + STREAM, "varpro": VARPRO, "first": consts + FIRST,
                "largest": LARGEST, "default": DEFAULT, "s2": S2}
    # the sum of the separate runs' limits: a hang in any section fails the tests
    return run_forced(sections, timeout=900), root


def section(forced, name: str) -> dict:
    out = forced[0][name]
    if isinstance(out, dict) and set(out) == {"error"}:
        pytest.fail(f"section {name} of the two-device run raised:\n{out['error']}")
    return out


def test_sharded_stream_equals_single_device(forced, tmp_path):
    info = section(forced, "stream")
    root = forced[1]
    # the single-device reference: this process has one JAX device
    fit_dataset([root / "data"], MODEL, out=tmp_path / "single" / "cal.json",
                chunk_devices=CHUNK, progress=False)
    assert info["n_shards"] == 2 and info["padded"] % 2 == 0
    assert info["out_devices"] == 2
    assert info["collectives"] == 0   # independent fits: nothing to wait on, nothing to hang
    sharded = load_outputs(root / "sharded" / "cal.json")
    single = load_outputs(tmp_path / "single" / "cal.json")
    # held-out RMS comes from Q − 2βᵀc + βᵀAβ (a difference of sums): its last digits
    # follow the summation order, which XLA's thread split of a reduction may change
    assert_close(sharded, single, rel=1e-10)
    assert [r["device"] for r in sharded[1]] == [f"f0-{i:03d}" for i in range(4)] + \
        [f"f1-{i:03d}" for i in range(3)]


@pytest.mark.slow
def test_sharded_variable_projection_does_not_hang(forced):
    """The nonlinear path (optimistix LM in a while loop: one all-reduce per step across
    the shards to agree on stopping) under sharding, against the same path on one device,
    on devices with a power-on warm-up transient."""
    out = section(forced, "varpro")
    assert out["sharded"].pop("n_shards") == 2 and out["single"].pop("n_shards") == 1
    assert out["single"]["status"].count(0) >= 3   # a well-posed problem: most converge
    assert_close(out["sharded"], out["single"], rel=1e-10)


def test_one_device_means_no_mesh():
    import jax

    from diffgyro.pipeline._chunkfit import local_mesh

    if jax.local_device_count() == 1:
        assert local_mesh() is None
    assert local_mesh(shard=False) is None


@pytest.mark.parametrize("spec", FIRST_SPECS)
def test_two_cpu_devices_fit_on_the_first(forced, spec):
    """fit()'s sums path with two CPU devices runs every group on the first (side by side
    on two they deadlocked); results equal to one device's, in order."""
    out = dict(section(forced, "first")[spec])
    assert out.pop("devices") == [0]
    import diffgyro._fit_sums.groups as fs
    from diffgyro.fit import fit
    from diffgyro.simulate import simulate

    old = fs.MAX_GROUP_DEVICES
    fs.MAX_GROUP_DEVICES = 4
    try:
        batch, _ = simulate("thermal", 11, effects="bias_poly(2)+thermal_lag", seed=4,
                            duration=1800.0)
        r = fit(spec, batch, path="sums")
    finally:
        fs.MAX_GROUP_DEVICES = old
    single = {"beta": r.params.beta.tolist(), "theta": r.params.theta.tolist(),
              "heldout_rms": r.heldout_rms.tolist(), "status": r.status.tolist()}
    assert_close(out, single, rel=1e-10)


def test_largest_groups_on_two_cpu_devices_finish(forced):
    """Groups at the cap (MAX_GROUP_DEVICES) of short recordings with two CPU devices
    present: two groups of 256 side by side never finished in XLA's CPU runtime."""
    out = section(forced, "largest")
    assert out["ok"] == out["d"]


def test_cpu_devices_are_not_sharded_by_default(forced):
    """Two CPU devices: the streaming path keeps each chunk on one (no mesh) unless
    asked; with shard=True it takes both."""
    assert section(forced, "default") == {"default": True, "fitter": 1, "forced": 2}


def test_s2_regression_with_two_cpu_devices_finishes(forced):
    """The case that deadlocked when groups ran side by side on two CPU devices (fog-one-run's
    regression, 256 devices × 2000 samples, groups of 64): it must finish."""
    out = section(forced, "s2")
    assert out["ok"] == out["d"]
