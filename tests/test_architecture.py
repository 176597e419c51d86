"""The module graph of src/diffgyro: no import cycle, no private names across modules,
every module importable first, imports at the module top (but for a named list), no
import by a string (every edge is one the graph reads), the public API listed in one
place (``diffgyro.PUBLIC_MODULES`` and each module's ``__all__``), the fit's front door
apart from its engines, and the signal catalogue present in every place that derives
signals.

The graph is read statically (``ast``) from every ``import`` and ``from ... import``
in a module, at module level, inside a function or under ``TYPE_CHECKING``: an import
inside a function only delays a cycle to the first call, so it counts. ``from P import name`` is an edge to
``P.name`` when that is a module, else to ``P``. The implicit import of a module's
parent packages is not an edge (a package's ``__init__`` re-exports its children by
design).

A private name is one with a leading underscore (not a dunder). A module may import
the private module of its own package (``effects._common`` from ``effects._bias_poly``)
but no private name of another module.
"""

from __future__ import annotations

import ast
import functools
import json
import os
import random
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "diffgyro"


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


@functools.cache
def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package) of every module under src/diffgyro (read once
    per session, as are the trees below: a dozen checks walk the same files)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The parsed source of ``path`` (the checks only read it)."""
    return ast.parse(path.read_text(), str(path))


@functools.cache
def _nodes(path: Path) -> tuple[ast.AST, ...]:
    """Every node of :func:`_tree` in ``ast.walk`` order."""
    return tuple(ast.walk(_tree(path)))


def _imports(modules) -> list[tuple[str, str, str | None]]:
    """Every (importer, imported module, imported name or None) inside diffgyro."""
    edges = []
    for mod, (path, is_pkg) in modules.items():
        for node in _nodes(path):
            if isinstance(node, ast.Import):
                edges += [(mod, a.name, None) for a in node.names if a.name.startswith("diffgyro")]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "diffgyro":
                    continue
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    edges.append((mod, sub, None) if sub in modules else (mod, target, a.name))
    return edges


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_graph_reads_known_edges():
    """The reader sees relative, absolute, function-level and submodule imports."""
    modules = _modules()
    edges = {(a, b) for a, b, _ in _imports(modules)}
    assert ("diffgyro.fit", "diffgyro.status") in edges  # from .status import (...)
    assert ("diffgyro.kalman", "diffgyro._signal_builder") in edges
    assert ("diffgyro._noise", "diffgyro._noise_passes") in edges  # inside a function
    assert ("diffgyro.effects._bias_poly", "diffgyro.effects._common") in edges
    assert ("diffgyro", "diffgyro.errors") in edges  # from .errors import DataError, SpecError
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle():
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for a, b, _ in _imports(modules):
        if a != b and b in modules:
            graph.setdefault(a, set()).add(b)
    assert _cycles(graph) == [], "import cycles (module-level or inside functions)"


#: The one module that gathers private helpers for the tests (docs/architecture.md), and so
#: may import any package's private modules and names.
INTERNAL = "diffgyro.internal"


def test_no_private_cross_imports():
    modules = _modules()
    found = set()
    for importer, target, name in _imports(modules):
        if importer == INTERNAL:
            continue
        parent = target.rsplit(".", 1)[0]
        private_module = _is_private(target.rsplit(".", 1)[-1])
        if private_module and not (importer == parent or importer.startswith(parent + ".")):
            found.add((importer, target, name))  # another package's private module
        if name is not None and _is_private(name) and importer != target:
            found.add((importer, target, name))
    assert sorted(found) == []


def test_every_module_imports_first():
    """Each module imports in a fresh state, in random orders (one subprocess: the
    diffgyro modules are dropped from ``sys.modules`` before each round; JAX stays)."""
    names = sorted(m for m in _modules() if not m.endswith("__main__"))  # __main__ runs the CLI
    orders = [random.sample(names, len(names)) for _ in range(3)]
    script = (
        "import importlib, json, sys\n"
        "for order in json.loads(sys.argv[1]):\n"
        "    for k in [k for k in sys.modules if k.split('.')[0] == 'diffgyro']:\n"
        "        del sys.modules[k]\n"
        "    for m in order:\n"
        "        try:\n"
        "            importlib.import_module(m)\n"
        "        except Exception as err:\n"
        "            sys.exit(f'{m} after {order[:order.index(m)]}: {err!r}')\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(SRC)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    proc = subprocess.run([sys.executable, "-c", script, json.dumps(orders)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_cli_commands_load_through_one_helper():
    """A command module never imports another command (loading is ``cli/_load``, shared
    options ``cli/_options``); only ``demo`` prints through ``diagnose``'s tables."""
    modules = _modules()
    commands = {m for m in modules if m.startswith("diffgyro.cli.")
                and not _is_private(m.rsplit(".", 1)[-1])}
    edges = {(a, b) for a, b, _ in _imports(modules) if a in commands and b in commands and a != b}
    assert edges == {("diffgyro.cli.demo", "diffgyro.cli.diagnose")}


#: A function longer than this many lines (its docstring left out) says why in a comment
#: starting "Over 80 lines".
MAX_FUNCTION_LINES = 80


def test_no_long_function_without_a_reason():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        lines = text.splitlines()
        for node in _nodes(path):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            length = node.end_lineno - node.lineno + 1
            doc = node.body[0] if node.body else None
            if isinstance(doc, ast.Expr) and isinstance(getattr(doc, "value", None), ast.Constant) \
                    and isinstance(doc.value.value, str):
                length -= doc.end_lineno - doc.lineno + 1
            body = "\n".join(lines[node.lineno - 1:node.end_lineno])
            if length > MAX_FUNCTION_LINES and "# Over 80 lines" not in body:
                long.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name} ({length} lines)")
    assert long == []


#: The imports a function may make late instead of at its module's top, each for a named
#: reason: an optional dependency (the extras ``logs`` and ``dask``, a POSIX-only module),
#: a library only figures need (matplotlib), numba's compile on first use,
#: ``import diffgyro`` staying free of JAX, and the state-space path, which the front door
#: registers as the random walk's fit and loads when a model has one, and the calibration
#: file read without JAX (the full model and compensation load on use). The command line's deferred loading of the
#: engine is checked apart (:func:`test_cli_defers_only_the_engine`).
DEFERRED = {
    "diffgyro": {"jax", "diffgyro._jit"},  # import diffgyro without JAX
    "diffgyro.data": {"pandas"},  # a DataFrame only (export and effects load data, not pandas)
    "diffgyro._jax_setup": {"jax"},  # sets JAX's options once it runs, never starts it
    "diffgyro.allan._plot": {"matplotlib", "matplotlib.pyplot"},  # figures only
    "diffgyro.report": {"matplotlib", "matplotlib.pyplot"},
    "diffgyro.sensitivity": {"matplotlib", "matplotlib.pyplot"},
    "diffgyro._noise": {"diffgyro._noise_passes"},  # numba
    "diffgyro._window_stats": {"diffgyro._window_pass"},  # numba, for a large batch
    "diffgyro._window_explain": {"diffgyro._window_pass"},  # numba, once the pass is loaded
    "diffgyro._motion_windows": {"diffgyro._judgement_pass"},  # numba, once the pass is loaded
    "diffgyro.stochastic._block_likelihood": {"diffgyro.stochastic._toeplitz"},  # numba
    "diffgyro.fit": {"diffgyro.kalman"},  # the stochastic model: 0.15 s of import
    # the solvers' libraries load when a solve is traced, not in a process whose programs
    # are stored (a warm command: 0.1-0.25 s of its start)
    "diffgyro._direct": {"optimistix"},
    "diffgyro._linalg": {"lineax"},
    "diffgyro.diagnose._synthesis": {"scipy.signal"},  # a lagged product only: 0.45 s of import
    # pandas and pyarrow (0.2-0.35 s of import) for what a plain CSV (io._plain_csv) is not
    "diffgyro.io._source": {"pandas", "pyarrow", "pyarrow.parquet"},
    "diffgyro.io._convert": {"pandas"},
    "diffgyro.logs._table": {"pandas"},
    "diffgyro.io._save": {"pyarrow", "pyarrow.csv", "pyarrow.parquet"},  # a large file
    # the calibration file read, checked, exported and applied without JAX: the full model
    # (a spec beyond the built-in terms' table), its compensation (a user's term) and the
    # extra columns' checks (an aux term) load on use
    "diffgyro._term_info": {"diffgyro.model"},
    "diffgyro.calibration": {"diffgyro.model", "diffgyro._compensate", "diffgyro._aux"},
    "diffgyro.logs": {"diffgyro.logs._ulog", "diffgyro.logs._rosbag",  # extra 'logs'
                      "diffgyro.logs._dataflash"},
    "diffgyro.pipeline._cluster": {"distributed"},  # extra 'dask'
    "diffgyro.pipeline._run": {"diffgyro.pipeline._cluster"},  # --dask only: 0.4 s of import
    "diffgyro.pipeline._workdir": {"fcntl"},  # POSIX only
}


def _function_imports(modules) -> list[tuple[str, str, int]]:
    """(module, imported module, line) of every import inside a function."""
    out = []
    for mod, (path, is_pkg) in modules.items():
        for fn in _nodes(path):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import):
                    out += [(mod, a.name, node.lineno) for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    if node.level:
                        base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                        base = base[:len(base) - node.level + 1]
                        target = ".".join(base + ([node.module] if node.module else []))
                    else:
                        target = node.module
                    for a in node.names:
                        sub = f"{target}.{a.name}"
                        out.append((mod, sub if sub in modules else target, node.lineno))
    return out


def test_imports_at_module_top():
    """Outside the command line, a function imports only what :data:`DEFERRED` names."""
    found = [f"{m}:{line} imports {t}" for m, t, line in _function_imports(_modules())
             if not m.startswith("diffgyro.cli") and t not in DEFERRED.get(m, ())]
    assert found == []


def test_cli_defers_only_the_engine():
    """A command module imports late only what ``--help`` does not load (the engine:
    JAX, NumPy, the fit); what the command line has loaded anyway sits at its top."""
    code = ("import json, sys, diffgyro.cli as cli; cli.load_commands(); "
            "print(json.dumps(sorted(sys.modules)))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(SRC)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    loaded = set(json.loads(subprocess.run([sys.executable, "-c", code], env=env, check=True,
                                           capture_output=True, text=True).stdout))
    late = [(m, t, line) for m, t, line in _function_imports(_modules()) if m.startswith("diffgyro.cli")]
    assert late, "the command line defers the engine"
    assert [f"{m}:{line} imports {t}" for m, t, line in late if t in loaded] == []


def _public_on_disk() -> set[str]:
    return {m for m in _modules() if not any(_is_private(p) for p in m.split("."))
            and not m.startswith("diffgyro.cli") and m not in ("diffgyro.__main__", INTERNAL)}


def test_public_api_listed_in_one_place():
    """``diffgyro.PUBLIC_MODULES`` is every module without a private part (the command line
    aside: its commands are its API; and ``diffgyro.internal``, the tests' namespace); each
    lists its names in ``__all__``, and each name
    there exists and, if a class or function, says what it is."""
    import importlib

    import diffgyro

    assert set(diffgyro.PUBLIC_MODULES) == _public_on_disk()
    missing = []
    for name in diffgyro.PUBLIC_MODULES:
        module = importlib.import_module(name)
        assert module.__doc__, name
        assert isinstance(getattr(module, "__all__", None), list), f"{name} has no __all__"
        assert len(set(module.__all__)) == len(module.__all__), name
        for attr in module.__all__:
            value = getattr(module, attr, missing)
            assert value is not missing, f"{name}.{attr} is in __all__ but not defined"
            if callable(value) and getattr(value, "__module__", "").startswith("diffgyro"):
                assert (value.__doc__ or "").strip(), f"{name}.{attr} has no docstring"


def test_each_public_name_exported_once():
    """A class or function is public under one module only (``diffgyro`` itself re-exports
    a few names for convenience); the modules users import re-export what private
    modules define, never another public module's names."""
    import importlib

    import diffgyro

    homes: dict[int, list[str]] = {}
    for name in diffgyro.PUBLIC_MODULES:
        if name == "diffgyro":
            continue
        module = importlib.import_module(name)
        for attr in module.__all__:
            value = getattr(module, attr)
            if isinstance(value, type) or callable(value):
                homes.setdefault(id(value), []).append(f"{name}.{attr}")
    twice = sorted(v for v in homes.values() if len(v) > 1)
    assert twice == []
    for attr in diffgyro.__all__:
        value = getattr(diffgyro, attr)
        if not attr.startswith("__") and (isinstance(value, type) or callable(value)) \
                and getattr(value, "__module__", "") != "diffgyro":
            private_home = any(_is_private(p) for p in value.__module__.split("."))
            assert id(value) in homes or private_home, f"diffgyro.{attr}: where is it public?"


#: The rows of docs/architecture.md, bottom up: a top-level module or package imports
#: only from its own row and the rows below.
LAYERS = (
    ("errors", "data", "channel", "_jit", "_xla_options", "_program_cache", "_jsonio",
     "_jax_setup", "_vocabulary"),
    ("signals", "effects", "model", "_signal_catalogue", "_signal_builder", "_aux", "_term_info"),
    ("status", "motion", "_options", "_folds", "_temperature", "_linalg", "_noise",
     "_noise_passes", "_select", "_noise_jax", "_motion_judge", "_fit_result", "_window_pass",
     "_window_stats", "_window_explain", "_motion_constants", "_motion_windows", "_motion_host",
     "_judgement_pass", "_rest_stretches", "_motion_result"),
    ("fit", "kalman", "_fit_sums", "_direct"),
    ("diagnose", "sensitivity", "plan_design", "allan", "stochastic", "detect", "_reference"),
    ("io", "logs", "calibration", "carry", "apply", "export", "report", "limits", "_compensate"),
    ("simulate", "recipes", "pipeline", "cli", "_demo", "__main__", "internal"),
)
#: Imports up a row, each for a reason: the random-walk fit runs the stochastic model's
#: bias filter (a random walk alone is that filter).
UPWARD = {("kalman", "stochastic")}


def test_layers_of_the_architecture_page():
    row = {name: i for i, names in enumerate(LAYERS) for name in names}
    tops = {m.split(".")[1] for m in _modules() if m != "diffgyro"}
    assert tops == set(row), "every top-level module sits in one row"
    up = set()
    for a, b, _ in _imports(_modules()):
        if a == "diffgyro" or b == "diffgyro":
            continue
        pa, pb = a.split(".")[1], b.split(".")[1]
        if pa != pb and row[pb] > row[pa]:
            up.add((pa, pb))
    assert up == UPWARD


#: The names a user calls (and the result type fit() returns) from the front door of the
#: fit; its engines (the direct solver, the noise floor, the signal builder, the motion
#: judgement) live in private modules.
FIT_API = ["fit", "FitResult", "AbstractFitResult", "FitOptions", "solve_device"]


def test_fit_is_the_front_door_only():
    """``diffgyro.fit`` exports what a user calls and defines only the front door (its
    functions and the result); the engines it runs live in their own modules, which the
    other paths import directly: no module takes anything but :data:`FIT_API` from
    ``fit``, and ``kalman`` does not import it at all."""
    import diffgyro.fit as front

    assert front.__all__ == FIT_API
    path, _ = _modules()["diffgyro.fit"]
    defined = {n.name for n in _tree(path).body
               if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    assert defined <= {"fit", "FitResult", "_fit", "_fit_sums", "_result", "_aux_fields", "_residual_batch",
                       "_fit_random_walk"}, defined
    imports = _imports(_modules())
    taken = {(a, name) for a, b, name in imports if b == "diffgyro.fit" and name not in FIT_API}
    assert taken == set()
    assert ("diffgyro.kalman", "diffgyro.fit") not in {(a, b) for a, b, _ in imports}


#: The modules that import by name at run time, each for a reason: ``diffgyro``'s public
#: names loaded on first use (``_LAZY``: the package itself, whose edges the layers leave
#: out), the command line's commands found on disk (each registers itself), and the
#: optional libraries of the log readers (the extra ``logs``).
NAMED_IMPORTS = {"diffgyro", "diffgyro.cli", "diffgyro.logs._table"}


def test_no_string_imports():
    """Every edge between the package's modules is an ``import`` statement the graph reads:
    no other module calls ``importlib.import_module`` or ``__import__``, and no string in
    the code (docstrings aside) names one of the package's modules but the list of public
    modules."""
    modules = _modules()
    calls, names = [], []
    for mod, (path, _) in modules.items():
        docs = {id(n.body[0].value) for n in _nodes(path)
                if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef)) and n.body
                and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        for node in _nodes(path):
            if isinstance(node, ast.Call):
                fn = node.func
                called = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
                if called in ("import_module", "__import__") and mod not in NAMED_IMPORTS:
                    calls.append(f"{mod}:{node.lineno}")
            elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
                  and id(node) not in docs and node.value in modules and node.value != "diffgyro"
                  and mod != "diffgyro"):
                names.append(f"{mod}:{node.lineno} {node.value!r}")
    assert calls == []
    assert names == []


def test_every_catalogue_signal_in_each_place_that_derives_signals():
    """The signal catalogue is the one table of signals: every catalogue signal is present
    in the signals each place makes (``make_signals``, plan design's steady state, the sums
    path's probe), the simulator's error model and the report's overlays read it, and the
    numpy-only ``apply`` derives every built-in one (in ``SIGNALS`` and its docstring).
    A signal added to the catalogue that one of them lacks fails here."""
    import re

    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    import diffgyro
    from diffgyro import apply
    from diffgyro._fit_sums.layout import INPUTS, _random_signals
    from diffgyro.data import Recording
    from diffgyro.effects import STANDARD as CATALOGUE
    from diffgyro.effects import product_of
    from diffgyro.internal import BUILT_IN, present
    from diffgyro.model import ErrorModel, Params
    from diffgyro.plan_design import operating_signals
    from diffgyro.signals import TempNorm, make_signals
    from diffgyro.simulate import model_error

    diffgyro.enable_x64()
    n = 64
    t = np.arange(n, dtype=float)
    temp = 20.0 + 0.5 * t
    rate = np.stack([np.sin(t / 5), np.cos(t / 7), np.sin(t / 3)], 1)
    accel = np.tile([0.0, 0.0, 9.81], (n, 1))
    # (each compiled as one program: run op by op, they compiled a hundred small ones)
    made = {
        "signals.make_signals": eqx.filter_jit(make_signals)(
            jnp.asarray(t), jnp.zeros((n, 3)), jnp.ones(n, bool), rate=jnp.asarray(rate),
            temp=jnp.asarray(temp), temp_ext=jnp.asarray(temp - 2), accel=jnp.asarray(accel)),
        "plan_design.operating_signals": eqx.filter_jit(operating_signals)(
            [20.0, 30.0], [0.1, 0.2, 0.3], TempNorm(centre=25.0, scale=10.0)),
        "_fit_sums.layout._random_signals": eqx.filter_jit(_random_signals)(
            frozenset(INPUTS), n, 0),
    }
    for place, sig in made.items():
        assert [s for s in CATALOGUE if not present(sig, s)] == [], place

    every = ErrorModel.from_spec("+".join(f"term({s})" for s in CATALOGUE))
    params = Params(beta=jnp.ones((1, 3, every.n_params)), theta=jnp.zeros((1, every.n_nonlinear)))
    err = model_error(every, params, TempNorm(centre=25.0, scale=10.0), t, rate[None],
                      temp[None], np.full((1, n), 0.5), temp[None] - 2, accel[None])
    assert np.all(np.isfinite(err)) and np.any(err != 0), "simulate.model_error"

    rec = Recording(t=t, gyro=np.zeros((n, 3)), rate=rate, temp=temp, temp_ext=temp - 2,
                    accel=accel)
    missing = [s for s in CATALOGUE if product_of(s, rec, np.full(n, 0.5 / 60)) is None]
    assert missing == [], "effects.product_of (the report's overlays)"

    assert set(apply.SIGNALS) >= set(BUILT_IN), "apply.SIGNALS"
    words = set(re.findall(r"[a-z_]+", apply.__doc__))
    assert [s for s in BUILT_IN if s not in words] == [], "apply's docstring"



TESTS = Path(__file__).resolve().parent
#: Test files that test one private module itself and import it (or its private names)
#: directly; every other test reaches the package through public names and
#: ``diffgyro.internal``. The second group are files other work had open when the rule
#: came, to be moved onto ``diffgyro.internal``.
PRIVATE_UNDER_TEST = {
    "test_architecture.py": {"diffgyro._fit_sums"},  # the sums path's signal probe
    "test_jit.py": {"diffgyro._jit"},
    "test_xla_options.py": {"diffgyro._xla_options"},
    "test_compile.py": {"diffgyro._jit"},
    "test_program_cache.py": {"diffgyro._program_cache", "diffgyro._jit"},
    "test_plain_csv.py": {"diffgyro.io._plain_csv"},
    "test_float_text.py": {"diffgyro.io._float_text", "diffgyro.io._save"},
    "test_jsonio.py": {"diffgyro._jsonio"},
    "test_demo.py": {"diffgyro._demo"},
    "test_cli_progress.py": {"diffgyro.cli._progress"},
    # the noise command's text table; the identification's program loaded ahead
    "test_stochastic.py": {"diffgyro.cli.noise", "diffgyro.stochastic._identify",
                           "diffgyro.stochastic._wavelet_variance"},
    "test_report.py": {"diffgyro.report"},  # the report's private text helpers
    "test_diagnose_scoring.py": {"diffgyro.diagnose._scoring"},
    # the setting predicted before the fit, and how the programs prepared ahead served
    "test_diagnose_ahead.py": {"diffgyro.diagnose._ahead", "diffgyro.diagnose._plan"},
    "test_fit_sums.py": {"diffgyro._fit_sums"},
    "test_fit_paths.py": {"diffgyro._fit_sums"},
    "test_window_stats.py": {"diffgyro._window_pass", "diffgyro._window_stats",
                            "diffgyro._window_explain"},
    "test_window_explain.py": {"diffgyro._window_explain", "diffgyro._window_stats",
                               "diffgyro._motion_judge"},
    "test_cli_conventions.py": {"diffgyro.cli._tables"},  # the tables' width rule
    "test_term_info.py": {"diffgyro._term_info"},
    "test_allan.py": {"diffgyro.allan._oadev"},  # the Allan sums' block and chunk sizes
    "test_synthesis.py": {"diffgyro.diagnose._synthesis"},  # its claims table
    "test_diagnose_greedy.py": {"diffgyro.diagnose._run"},  # the base fits a pair's runs
    "test_noise.py": {"diffgyro._noise", "diffgyro._noise_jax", "diffgyro._noise_passes"},
    "test_block_likelihood.py": {"diffgyro.stochastic._toeplitz"},  # the O(M²) deviance
    "test_slow_bootstrap.py": {"diffgyro.stochastic._slow_bootstrap"},  # the drawn law
    # open elsewhere when diffgyro.internal came
    "test_diagnose.py": {"diffgyro._temperature", "diffgyro.effects._common"},
    "test_sharding.py": {"diffgyro.pipeline._chunkfit", "diffgyro._fit_sums"},
    "test_imu_orientations.py": {"diffgyro.recipes._six_position", "diffgyro.simulate._motion"},
}


def _private_home(module: str, name: str | None, modules) -> str | None:
    """The private module an import reaches into (``from diffgyro._fit_sums import pack``:
    ``diffgyro._fit_sums``; ``from diffgyro.report import _text``: ``diffgyro.report``),
    or None for a public import."""
    parts = module.split(".")
    private = [i for i, p in enumerate(parts) if _is_private(p)]
    if private:
        return ".".join(parts[:private[0] + 1])
    if name and _is_private(name):
        return f"{module}.{name}" if f"{module}.{name}" in modules else module
    return None


def test_tests_reach_private_code_through_internal():
    """A test imports a private module or name only where it tests that module
    (:data:`PRIVATE_UNDER_TEST`); the helpers other tests need come from
    ``diffgyro.internal``."""
    found, modules = {}, _modules()
    for path in sorted(TESTS.rglob("*.py")):
        rel = path.relative_to(TESTS).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("diffgyro"):
                targets = [(node.module, a.name) for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [(a.name, None) for a in node.names if a.name.startswith("diffgyro")]
            else:
                continue
            for module, name in targets:
                home = _private_home(module, name, modules)
                if home is not None and home not in PRIVATE_UNDER_TEST.get(rel, ()):
                    found.setdefault(rel, set()).add(home)
    assert found == {}


#: Public modules whose functions do not all document each argument yet: the rule came
#: with issue 43, and a module leaves this set once its docstrings are written (none now).
ARGUMENTS_TO_WRITE: set[str] = set()


def _undocumented_arguments(fn) -> list[str]:
    """The parameters of ``fn`` its docstring's ``**Arguments:**`` section does not name
    (as ``name``, or ``*name`` / ``**name``); all of them when there is no such section."""
    import inspect

    doc = inspect.getdoc(fn) or ""
    params = [p for p in inspect.signature(fn).parameters.values()
              if p.name not in ("self", "cls")]
    if "**Arguments:**" not in doc:
        return [p.name for p in params] or []
    section = doc.split("**Arguments:**", 1)[1]
    return [p.name for p in params
            if not any(f"``{star}{p.name}``" in section for star in ("", "*", "**"))]


def test_public_functions_document_each_argument():
    """Every function of a public module's ``__all__`` documents each of its parameters in
    an ``**Arguments:**`` section (as optimistix does), modules still being written aside
    (:data:`ARGUMENTS_TO_WRITE`); a function without parameters needs none."""
    import importlib
    import inspect

    import diffgyro

    assert ARGUMENTS_TO_WRITE <= set(diffgyro.PUBLIC_MODULES)
    missing = {}
    for name in diffgyro.PUBLIC_MODULES:
        if name in ARGUMENTS_TO_WRITE:
            continue
        module = importlib.import_module(name)
        for attr in module.__all__:
            fn = inspect.unwrap(getattr(module, attr))
            if inspect.isfunction(fn) and fn.__module__.startswith("diffgyro"):
                if gaps := _undocumented_arguments(fn):
                    missing[f"{name}.{attr}"] = gaps
    assert missing == {}


def test_the_arguments_check_finds_a_missing_argument():
    def documented(a, b=1, **extra):
        """Add.

        **Arguments:**

        - ``a``: one.
        - ``b``: another.
        - ``**extra``: the rest.
        """

    def one_missing(a, b):
        """Add.

        **Arguments:**

        - ``a``: one.
        """

    def none(a):
        """Add ``a``."""

    assert _undocumented_arguments(documented) == []
    assert _undocumented_arguments(one_missing) == ["b"]
    assert _undocumented_arguments(none) == ["a"]
