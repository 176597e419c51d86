"""Under ``CI=true`` a skipped test or test module fails the run, unless it is a documented
platform skip.

The external references (allantools, imucal, the notebooks, Dask, pymavlink, PyYAML, a C
compiler for the exported header) are reached through ``importorskip`` or a skip when they
are missing: convenient on a developer's machine, but on CI a missing dev dependency would
silently drop the only independent checks. So on CI every skip is turned into a failure
naming its reason, except the skips listed in :data:`PLATFORM_SKIPS`: tests that need a
facility of the operating system (Linux's ``/proc``) rather than something the project
installs. An expected failure (``xfail``) is not a skip and is left alone.

Registered from ``tests/conftest.py`` (``pytest_plugins``).
"""

from __future__ import annotations

import os

import pytest

#: Skip reasons (as the test gives them) that may stand on CI, and why each is a platform skip.
PLATFORM_SKIPS = {
    "no /proc/self/maps or vm.max_map_count here": "memory-mapping count from Linux's /proc",
    "cannot reset the peak RSS here (/proc/self/clear_refs)": "peak RSS reset through Linux's /proc",
    "peak RSS from /proc (Linux)": "peak RSS read from Linux's /proc",
}


def on_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() == "true"


def skip_reason(report) -> str:
    """The reason a skipped report gives (pytest stores it as (file, line, "Skipped: why"))."""
    longrepr = report.longrepr
    reason = longrepr[2] if isinstance(longrepr, tuple) and len(longrepr) == 3 else str(longrepr)
    return reason.removeprefix("Skipped: ")


def forbidden(report) -> str | None:
    """The failure text for a skip that may not stand on CI, or None."""
    if not report.skipped or hasattr(report, "wasxfail"):
        return None
    reason = skip_reason(report)
    if reason in PLATFORM_SKIPS:
        return None
    return (f"skipped under CI=true: {reason!r} is not a documented platform skip "
            f"(tests/_no_skips.py); install what the test needs (pyproject's dev extra)")


def _fail(report, text: str) -> None:
    report.outcome = "failed"
    report.longrepr = text


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    text = forbidden(report) if on_ci() else None
    if text is not None:
        _fail(report, text)


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    report = outcome.get_result()
    text = forbidden(report) if on_ci() else None
    if text is not None:  # a module-level importorskip
        _fail(report, text)
