"""What a long command is doing, on stderr: a rich progress display while it works.

Shown only when stderr is a terminal and ``--quiet`` was not given; otherwise every
call here does nothing (logs, pipes, CI and ``--json`` consumers see no control
codes; stdout is never written). Use in a command::

    from . import _progress

    with _progress.steps("loading the recordings") as step:
        batch = load(...)
        step("fitting bias_poly(1)")           # a new stage (indeterminate)
        step("scoring candidates", total=8)    # a stage with a count
        step.advance()                         # one more of the count done
        result = engine(..., progress=step)    # engines take a plain callable

The first program this process compiles for a model (none stored on disk yet, see
:mod:`diffgyro._program_cache`) prints one line, :data:`COMPILING`.
This module starts with ``_`` so it is not imported as a command; it loads rich's
progress display only when it is shown (``--help`` does not load it).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from rich.console import Console

#: The line a first run prints once, when it compiles a model's programs.
COMPILING = "compiling programs for this model: once per machine"

_state = {"quiet": False, "said_compiling": False, "step": None}


def set_quiet(quiet: bool) -> None:
    """``diffgyro --quiet``: no progress display, no compile notice."""
    _state["quiet"] = bool(quiet)


def quiet() -> bool:
    """Whether ``--quiet`` was given (the streamed runs' log lines are left out too)."""
    return _state["quiet"]


def shown() -> bool:
    """Whether progress is displayed: stderr is a terminal and ``--quiet`` was not given."""
    try:
        return not _state["quiet"] and sys.stderr.isatty()
    except (AttributeError, ValueError):  # stderr closed or replaced
        return False


class Step:
    """The running display's one task; every method does nothing when nothing is shown.

    Calling it (``step(text, total=None)``) starts a stage: its description, and a count
    of ``total`` things when given (``advance`` counts them).
    """

    def __init__(self, bar=None, text: str = "", total: int | None = None):
        self._bar = bar
        self._done, self._total = 0, total
        self._task = None if bar is None else bar.add_task(text, total=total,
                                                           count=_count(0, total))

    def __call__(self, text: str, total: int | None = None, done: int = 0) -> None:
        self._done, self._total = done, total
        if self._bar is not None:
            self._bar.update(self._task, description=text, total=total, completed=done,
                             count=_count(done, total))
            self._bar.refresh()  # drawn now: a stage shorter than a redraw is still shown

    def advance(self, n: int = 1) -> None:
        self.count(self._done + n, self._total)

    def count(self, done: int, total: int | None) -> None:
        """``done`` of ``total`` (devices, chunks, candidates) of the current stage."""
        self._done, self._total = done, total
        if self._bar is not None:
            self._bar.update(self._task, completed=done, total=total, count=_count(done, total))


def _count(done: int, total) -> str:
    return "" if total is None else f"{int(done)}/{int(total)}"


@contextmanager
def steps(text: str, total: int | None = None) -> Iterator[Step]:
    """A progress display on stderr for the ``with`` block (gone when it ends), starting
    at stage ``text``; yields its :class:`Step`. Does nothing unless :func:`shown`; inside
    another ``steps`` block it yields that block's step, at stage ``text``."""
    outer = _state["step"]
    if outer is not None:
        outer(text, total)
        yield outer
        return
    if not shown():
        yield Step(None)
        return
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    bar = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                   TextColumn("{task.fields[count]}"), TimeElapsedColumn(),
                   console=Console(stderr=True), transient=True,
                   redirect_stdout=False)  # stdout stays the command's (--json)
    try:
        step = _state["step"] = Step(bar, text, total)
        with bar:
            yield step
    finally:
        _state["step"] = None


def compiling() -> None:
    """Say :data:`COMPILING` once per process (above the display when one runs), on a
    terminal without ``--quiet``."""
    if _state["said_compiling"] or not shown():
        return
    _state["said_compiling"] = True
    step = _state["step"]
    if step is not None and step._bar is not None:
        step._bar.console.print(COMPILING, markup=False, highlight=False)
    else:
        print(COMPILING, file=sys.stderr, flush=True)
