"""tests/_no_skips.py: under CI=true an undocumented skip fails the run; a platform skip,
an expected failure and everything off CI stand as they are."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).parent

CASES = '''
import pytest

def test_missing_dependency():
    pytest.importorskip("no_such_module_for_the_no_skips_test")

def test_platform():
    pytest.skip("no /proc/self/maps or vm.max_map_count here")

@pytest.mark.xfail(reason="known")
def test_expected_failure():
    assert False

def test_passes():
    pass
'''


def _run(tmp_path: Path, ci: str | None, module_skip: bool = False):
    (tmp_path / "test_cases.py").write_text(CASES)
    if module_skip:
        (tmp_path / "test_module.py").write_text(
            'import pytest\npytest.importorskip("no_such_module_for_the_no_skips_test")\n'
            "def test_never():\n    pass\n")
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "PYTEST_ADDOPTS")}
    if ci is not None:
        env["CI"] = ci
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "_no_skips", "-p", "no:cacheprovider",
                           "-p", "no:xdist", "-q", "-rA", str(tmp_path)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)


def test_off_ci_skips_stand(tmp_path):
    res = _run(tmp_path, None)
    assert res.returncode == 0, res.stdout
    assert "1 passed, 2 skipped, 1 xfailed" in res.stdout


@pytest.mark.parametrize("ci", ["true", "TRUE"])
def test_on_ci_an_undocumented_skip_fails(tmp_path, ci):
    res = _run(tmp_path, ci)
    assert res.returncode == 1, res.stdout
    assert "FAILED test_cases.py::test_missing_dependency" in res.stdout
    assert "is not a documented platform skip" in res.stdout
    assert "1 failed, 1 passed, 1 skipped, 1 xfailed" in res.stdout  # the platform skip stands


def test_on_ci_a_module_level_importorskip_fails(tmp_path):
    res = _run(tmp_path, "true", module_skip=True)
    assert res.returncode != 0, res.stdout
    assert "ERROR test_module.py" in res.stdout and "is not a documented platform skip" in res.stdout


def test_ci_false_is_off(tmp_path):
    assert _run(tmp_path, "false").returncode == 0
