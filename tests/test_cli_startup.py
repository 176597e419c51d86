"""The command line answers ``--help``, usage errors and a missing file without JAX:
the engine is imported inside the command bodies, and float64 and the compilation
cache are set only once a command's options have parsed, for when JAX starts (a
command whose code never imports JAX never starts it); ``export`` and ``effects`` load
no pandas (benchmarks/cli_help.py and cli_latency.py time these)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

PROBE = """
import json, sys
from diffgyro.cli import main
sys.argv = ["diffgyro"]
code = {argv!r} and main({argv!r})
print(json.dumps({{"code": code, "jax": "jax" in sys.modules,
                   "equinox": "equinox" in sys.modules}}), file=sys.stderr)
"""


def _probe(argv: list[str], tmp_path) -> tuple[dict, str, str]:
    run = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv)], capture_output=True,
                         text=True, cwd=tmp_path, timeout=60, check=False)
    *err, last = run.stderr.strip().splitlines()
    return json.loads(last), run.stdout, "\n".join(err)


def test_import_cli_and_its_commands_does_not_import_jax(tmp_path):
    code = ("import sys, diffgyro, diffgyro.cli as cli; cli.load_commands(); "
            "print(sorted(m for m in ('jax', 'equinox', 'jaxlib', 'optimistix') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, timeout=60, check=True)
    assert run.stdout.strip() == "[]", run.stdout


@pytest.mark.parametrize("argv", [["--help"], ["fit", "--help"], ["export", "--help"]])
def test_help_answers_without_jax(argv, tmp_path):
    seen, out, _ = _probe(argv, tmp_path)
    assert seen == {"code": 0, "jax": False, "equinox": False}
    assert "Usage" in out


def test_missing_file_and_bad_option_answer_without_jax(tmp_path):
    seen, _, err = _probe(["fit", "missing.csv", "--model", "bias_poly(1)"], tmp_path)
    assert seen["code"] == 2 and not seen["jax"]
    assert err == "diffgyro: error: file missing.csv: file not found"
    seen, _, err = _probe(["compensate", "data.csv", "--cal", "nope.json", "--out", "o.csv"],
                          tmp_path)
    assert seen["code"] == 2 and not seen["jax"] and "file data.csv: file not found" in err
    seen, _, err = _probe(["fit", "--no-such-option"], tmp_path)
    assert seen["code"] == 2 and not seen["jax"] and "--no-such-option" in err
    seen, _, err = _probe(["fit", "x.csv", "--modle", "bias_poly(1)"], tmp_path)  # did you mean
    assert seen["code"] == 2 and not seen["jax"] and "--modle" in err and "--model" in err


def test_a_bad_csv_answers_without_jax(tmp_path):
    """A CSV without a required column is refused by the reader, before anything imports
    JAX: ``fit`` checks its spec without JAX (``diffgyro._term_info``) and loads first;
    the data containers are JAX-free (they become pytrees when JAX starts)."""
    (tmp_path / "nocol.csv").write_text("device,t,gx,gy,temp\nimu0,0,0.1,0.2,25\nimu0,1,0.1,0.2,25\n")
    want = ("diffgyro: error: file nocol.csv, column gz: missing required column (columns in the "
            "file: device, t, gx, gy, temp; map others with --columns std=name)")
    for argv in (["fit", "nocol.csv", "--model", "bias_poly(1)+gradient"],
                 ["diagnose", "nocol.csv", "--model", "bias_poly(1)"],
                 ["compensate", "nocol.csv", "--cal", "cal.json", "--out", "o.csv"]):
        if argv[0] == "compensate":
            (tmp_path / "cal.json").write_text(json.dumps(CAL))
        seen, _, err = _probe(argv, tmp_path)
        assert seen == {"code": 2, "jax": False, "equinox": False}, argv
        assert err == want
    seen, _, err = _probe(["fit", "nocol.csv", "--model", "bias_poly(1)+gradien"], tmp_path)
    assert seen["code"] == 2 and "did you mean 'gradient'" in err  # the spec is read first


def test_compensate_answers_without_jax(tmp_path):
    """``compensate`` reads the file, applies the calibration in numpy
    (:func:`diffgyro.apply.compensate`) and writes the corrected file: no JAX; the corrected
    rate is the measured one less the calibration's bias polynomial."""
    (tmp_path / "cal.json").write_text(json.dumps(CAL))
    (tmp_path / "x.csv").write_text("device,t,gx,gy,gz,temp\n" + "".join(
        f"imu0,{k},0.01,0.02,0.03,{20 + k}\n" for k in range(5)))
    seen, out, _ = _probe(["compensate", "x.csv", "--cal", "cal.json", "--out", "c.csv"],
                          tmp_path)
    assert seen == {"code": 0, "jax": False, "equinox": False}
    assert out.startswith("wrote c.csv: 1 device(s), 5 samples corrected by bias_poly(1)")
    rows = [ln.split(",") for ln in (tmp_path / "c.csv").read_text().splitlines()[1:]]
    for k, row in enumerate(rows):
        ts = (20 + k - 25.0) / 10.0
        want = [0.01 - 1e-3 - 2e-4 * ts, 0.02 + 1e-3, 0.03 - 5e-5 * ts]
        assert [float(x) for x in row[2:5]] == pytest.approx(want, abs=1e-15)


def test_public_names_still_load_on_use(tmp_path):
    code = ("import sys, diffgyro; assert 'jax' not in sys.modules; "
            "from diffgyro import Batch, ErrorModel; import diffgyro.effects as effects; "
            "from diffgyro.effects import RandomWalk; import diffgyro.fit; "
            "assert 'diffgyro.kalman' not in sys.modules; "
            "print(diffgyro.Params.__name__, callable(effects.noise_fit(ErrorModel.from_spec("
            "'bias_poly(0)+random_walk').noise)))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["Params", "True"]


def test_help_reads_cleanly_at_80_columns(tmp_path):
    import os

    env = {**os.environ, "COLUMNS": "80"}
    outs = {}
    for argv in (["--help"], ["fit", "--help"], ["compensate", "--help"], ["recipe", "--help"]):
        out = subprocess.run([sys.executable, "-m", "diffgyro", *argv], capture_output=True,
                             text=True, cwd=tmp_path, env=env, timeout=60, check=True).stdout
        assert "<bool>" not in out and "…" not in out, out  # no type on a flag, nothing cut
        assert max(map(len, out.splitlines())) <= 80, out
        outs[argv[0]] = out
    assert "..." not in outs["--help"].split("Commands:")[1]  # each command's first sentence is whole
    # a docstring's paragraph wraps to the terminal, its source line breaks gone
    assert "Write DATA with gyro rates corrected by CAL (rad/s). Temperatures outside\n" \
        "  the calibrated range" in outs["compensate"]


def test_version_answers_without_jax(tmp_path):
    """``diffgyro --version``: the installed package's version, exit 0, no JAX."""
    from importlib.metadata import version

    seen, out, _ = _probe(["--version"], tmp_path)
    assert seen == {"code": 0, "jax": False, "equinox": False}
    assert out.strip() == f"diffgyro {version('diffgyro')}"


#: A command added for the test: it starts JAX only when asked, and says how JAX runs.
COMMAND_PROBE = """
import json, os, sys
from diffgyro.cli import app, main

@app.command("probe")
def probe(start: bool = False):
    if start:
        import jax
        print(json.dumps({"x64": bool(jax.config.jax_enable_x64),
                          "cache": jax.config.jax_compilation_cache_dir}))

code = main(["probe", *sys.argv[1:]])
print(json.dumps({"code": code, "jax": "jax" in sys.modules,
                  "env": sorted(k for k in os.environ if k.startswith("JAX_"))}))
"""


def test_a_command_starts_jax_only_when_its_code_does(tmp_path):
    """The command line's wrapper starts no JAX itself; where a command's code imports
    JAX it runs in float64 with the persistent cache in ``$DIFFGYRO_CACHE_DIR``, and
    JAX's variables leave the environment with the command."""
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    env["DIFFGYRO_CACHE_DIR"] = str(tmp_path / "cache")

    def run(*argv):
        out = subprocess.run([sys.executable, "-c", COMMAND_PROBE, *argv], capture_output=True,
                             text=True, cwd=tmp_path, env=env, timeout=120, check=True).stdout
        return [json.loads(line) for line in out.splitlines()]

    assert run() == [{"code": 0, "jax": False, "env": []}]
    started, after = run("--start")
    assert started == {"x64": True, "cache": str(tmp_path / "cache")}
    assert after == {"code": 0, "jax": True, "env": []}


#: A calibration file of one device, bias_poly(1).
CAL = {"format": "diffgyro-calibration", "format_version": 1, "model": "bias_poly(1)",
       "dtemp_window": 60.0, "devices": [{
           "device": "imu0", "status": "ok", "beta": [[1e-3, 2e-4], [-1e-3, 0.0], [0.0, 5e-5]],
           "theta": [], "temp_centre": 25.0, "temp_scale": 10.0, "temp_range": [15.0, 35.0],
           "quality": {"heldout_rms": 3e-4, "noise_floor": 3e-4}}]}


def test_export_and_effects_load_no_pandas(tmp_path):
    """``export`` reads a calibration file and ``effects`` lists the terms: no DataFrame,
    so no pandas (nor numba, matplotlib), and no compiled program, so no JAX (the terms'
    table, ``diffgyro._term_info``); the file export writes holds the device's
    parameters."""
    (tmp_path / "cal.json").write_text(json.dumps(CAL))
    code = ("import json, sys; from diffgyro.cli import main; code = main({argv!r}); "
            "print(json.dumps([code, sorted(m for m in ('pandas', 'numba', 'matplotlib', 'jax', "
            "'equinox') if m in sys.modules)]))")

    def run(argv):
        return subprocess.run([sys.executable, "-c", code.format(argv=argv)], capture_output=True,
                              text=True, cwd=tmp_path, timeout=120, check=True).stdout

    out = run(["export", "cal.json", "--format", "px4", "--device-id", "7", "--out", "px4.params"])
    assert json.loads(out.splitlines()[-1]) == [0, []]
    written = (tmp_path / "px4.params").read_text()
    assert "TC_G0_ID\t7\t6" in written and "TC_G0_TREF\t25\t9" in written
    out = run(["effects"])
    assert "bias_poly" in out and json.loads(out.splitlines()[-1]) == [0, []]


def test_the_program_ends_at_once_with_its_output_and_exit_code(tmp_path):
    """``python -m diffgyro`` skips the interpreter's teardown (``cli._exit_now``): what it
    printed still arrives whole, on both streams, with the command's exit code."""
    run = subprocess.run([sys.executable, "-m", "diffgyro", "fit", "missing.csv", "--model",
                          "bias_poly(1)", "--json"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=60, check=False)
    assert run.returncode == 2
    assert json.loads(run.stdout)["file"] == "missing.csv"
    assert run.stderr.strip() == "diffgyro: error: file missing.csv: file not found"
    run = subprocess.run([sys.executable, "-m", "diffgyro", "effects"], capture_output=True,
                         text=True, cwd=tmp_path, timeout=60, check=False)
    assert run.returncode == 0 and "bias_poly" in run.stdout and run.stdout.endswith("\n")


def test_a_command_that_fitted_ends(tmp_path):
    """A fit starts the host's kept worker pools (``_jit.host_pool``), whose idle threads
    never end by themselves: the program still ends once its output is out."""
    for args in (["simulate", "--plan", "thermal", "--devices", "1", "--duration", "1200",
                  "--rate", "1", "--out", "x.csv"],
                 ["fit", "x.csv", "--model", "bias_poly(1)", "--out", "cal.json"]):
        run = subprocess.run([sys.executable, "-m", "diffgyro", *args], capture_output=True,
                             text=True, cwd=tmp_path, timeout=120, check=False)
        assert run.returncode == 0, run.stderr
    assert json.loads((tmp_path / "cal.json").read_text())


LAPACK_PROBE = """
import json, sys
import numpy as np
from diffgyro import _jax_setup
_jax_setup.when_jax_imported(_jax_setup.lapack_tables_only)
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
a = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
chol = np.asarray(jnp.linalg.cholesky(jnp.asarray(a)))
eig = np.asarray(jnp.linalg.eigh(jnp.asarray(a))[0])
package = "scipy.linalg" in sys.modules
import scipy.linalg, scipy.signal
from scipy.linalg import cython_blas
print(json.dumps({"package_before": package, "tables": [m in sys.modules for m in
                  _jax_setup.LAPACK_TABLES],
                  "chol": float(np.max(np.abs(chol @ chol.T - a))),
                  "eig": float(np.max(np.abs(eig - np.linalg.eigvalsh(a)))),
                  "scipy": float(np.max(np.abs(scipy.linalg.cholesky(a, lower=True) - chol))),
                  "lfilter": scipy.signal.lfilter([1.0], [1.0, -0.5], [1.0, 0.0]).tolist(),
                  "same": cython_blas is sys.modules["scipy.linalg.cython_blas"]}))
"""


def test_lapack_starts_without_scipy_linalg():
    """A command's first factorisation loads scipy's two BLAS and LAPACK tables, not the
    package ``scipy.linalg`` (0.14 s of its start); JAX's factorisations are right, and a
    later ``import scipy.linalg`` (and scipy.signal, which uses it) works as usual, with
    the same table modules."""
    out = subprocess.run([sys.executable, "-c", LAPACK_PROBE], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    seen = json.loads(out.splitlines()[-1])
    assert seen["package_before"] is False and seen["tables"] == [True, True]
    assert seen["chol"] < 1e-14 and seen["eig"] < 1e-13 and seen["scipy"] < 1e-15
    assert seen["lfilter"] == [1.0, 0.5] and seen["same"] is True


ONE_COMMAND_PROBE = """
import json, sys
from diffgyro import cli
code = cli.main({argv!r}, one_command=True)
print(json.dumps([code, sorted(m.rsplit(".", 1)[1] for m in sys.modules
                               if m.startswith("diffgyro.cli.") and "._" not in m)]),
      file=sys.stderr)
"""


def test_a_process_registers_only_the_command_it_runs(tmp_path):
    """``python -m diffgyro COMMAND`` imports that command's module alone (building the
    others took 0.04-0.07 s of every start); help, a root option first or a misspelt
    command load them all, and a command's help reads the same either way."""

    def run(argv):
        done = subprocess.run([sys.executable, "-c", ONE_COMMAND_PROBE.format(argv=argv)],
                              capture_output=True, text=True, cwd=tmp_path, timeout=60)
        return json.loads(done.stderr.strip().splitlines()[-1]), done.stdout

    every = sorted(["allan", "compensate", "demo", "diagnose", "effects", "export", "fit",
                    "noise", "recipe", "simulate"])
    assert run(["effects"])[0] == [0, ["effects"]]
    assert run(["demo", "--help"])[0] == [0, ["demo", "diagnose"]]  # demo prints diagnose's tables
    (code, loaded), out = run(["--help"])
    assert code == 0 and loaded == every and all(f"  {c}" in out for c in every)
    assert run(["-q", "effects"])[0] == [0, every]
    assert run(["fitt", "x.csv"])[0] == [2, every]
    alone = run(["fit", "--help"])[1]
    everything = subprocess.run([sys.executable, "-c", "from diffgyro.cli import main; "
                                 "main(['fit', '--help'])"], capture_output=True, text=True,
                                cwd=tmp_path, timeout=60).stdout
    assert alone == everything and "--model" in alone
