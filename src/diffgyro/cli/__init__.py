"""The ``diffgyro`` command line (its options and ``--json`` objects are a contract).

Each command lives in its own module of this package and registers itself on
``app`` when imported; every module here is imported by :func:`main`.
Bad input raises :class:`~diffgyro.errors.DataError`: its one-line message
goes to stderr and the exit code is 2, never a traceback; under ``--json`` the same
error is also a JSON object on stdout (:meth:`~diffgyro.errors.DataError.to_json`).
"""

from __future__ import annotations

import atexit
import functools
import gc
import importlib
import inspect
import logging
import os
import pkgutil
import sys
import threading
from pathlib import Path
from typing import Annotated

import typer

import diffgyro
from diffgyro import _jax_setup
from diffgyro.errors import DataError

from . import _progress

app = typer.Typer(
    name="diffgyro",
    help="Gyroscope calibration with differentiable error models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

_loaded = False


def _print_version(value: bool) -> None:
    """``--version``: the installed package's version (``importlib.metadata``, read when
    ``diffgyro`` is imported; JAX is not loaded), then exit 0."""
    if value:
        print(f"diffgyro {diffgyro.__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option("--version", is_eager=True, callback=_print_version,
                                          help="Print the version and exit.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q",
                                        help="No progress display on stderr (it is shown only "
                                             "when stderr is a terminal).")] = False,
) -> None:
    """Gyroscope calibration with differentiable error models (rates in rad/s)."""
    _progress.set_quiet(quiet)


def load_commands() -> typer.Typer:
    """Import every command module so that each registers on ``app``."""
    global _loaded
    if not _loaded:
        for name in command_modules():
            importlib.import_module(f"{__name__}.{name}")
        _loaded = True
    return app


def command_modules() -> list[str]:
    """The command modules, by name (each registers the command of its name), sorted."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def _load_for(argv: list[str]) -> None:
    """Register what ``argv`` runs: only its command's module where it names one first
    (a process that runs one command builds no other: 0.04-0.07 s of every command's
    start), else every command (help, a root option, a misspelt command)."""
    if argv and argv[0] in command_modules():
        importlib.import_module(f"{__name__}.{argv[0]}")
    else:
        load_commands()


#: Options that name a file the command reads (besides its positional arguments).
INPUT_OPTIONS = ("cal", "limits", "sections")


def _check_inputs(command, values: dict) -> None:
    """A missing input file is one line before the engine starts (the same line as
    :func:`diffgyro.io.load` gives)."""


    for param in command.params:
        if param.param_type_name != "argument" and param.name not in INPUT_OPTIONS:
            continue
        given = values.get(param.name)
        for path in given if isinstance(given, (list, tuple)) else [given]:
            if isinstance(path, Path) and not path.exists():
                raise DataError("file not found", file=str(path))


def json_param(command) -> str | None:
    """The name of ``command``'s ``--json`` flag (``as_json``, ``json_out``), or None."""
    return next((p.name for p in command.params if "--json" in getattr(p, "opts", ())), None)


def error_json(err: Exception) -> dict:
    """The ``--json`` error object of ``err``: a DataError's fields, or (a usage error
    raised once the options were read) its message with the fields null."""
    if isinstance(err, DataError):
        return err.to_json()
    text = err.format_message() if hasattr(err, "format_message") else str(err)
    return DataError(text).to_json()


def _engine_first(command):
    """``command``'s callback with its input files checked, then float64 and the
    compilation cache set for when JAX starts: JAX starts only when a command's code
    needs it, after its options parsed (``--help``, usage errors and the commands that
    compile nothing answer without it). Under ``--json``
    an error is also its JSON object on stdout (the one line still goes to stderr)."""

    callback = command.callback
    flag = json_param(command)

    @functools.wraps(callback)
    def run_command(*args, **kwargs):
        try:
            _check_inputs(command, kwargs)
            if _progress.shown():  # a first run says once that it compiles
                _jax_setup.on_new_program = _progress.compiling
            _jax_setup.when_jax_imported(_jax_setup.lapack_tables_only)
            settings = _jax_setup.cache_settings()
            stored, _jax_setup.store_programs = _jax_setup.store_programs, bool(settings)
            frozen, _jax_setup.freeze_after_trace = _jax_setup.freeze_after_trace, True
            thawed = gc.get_freeze_count() == 0
            try:
                with _jax_setup.when_jax_starts({**_jax_setup.FLOAT64, **settings}):
                    return callback(*args, **kwargs)
            finally:
                _jax_setup.store_programs = stored
                _jax_setup.freeze_after_trace = frozen
                if not frozen and thawed:  # what the command's traces froze is collected again
                    gc.unfreeze()
        except Exception as err:
            usage = hasattr(err, "show") and getattr(err, "exit_code", None) == 2
            if flag is not None and kwargs.get(flag) and (isinstance(err, DataError) or usage):
                from diffgyro._jsonio import dumps  # the one sanitiser of JSON output

                sys.stdout.flush()
                print(dumps(error_json(err)), flush=True)
            raise

    return run_command


def _reflow(text: str) -> str:
    """Docstring paragraphs as single lines (the help panel wraps them to the terminal);
    an indented or bulleted paragraph keeps its lines."""

    paragraphs = inspect.cleandoc(text).split("\n\n")
    return "\n\n".join(
        p if any(line[:1].isspace() or line.lstrip()[:2] in ("- ", "* ") or line.startswith("\b")
                 for line in p.splitlines()) else " ".join(line.strip() for line in p.splitlines())
        for p in paragraphs)


def tidy_help(command) -> None:
    """Help as a reader wants it, for ``command`` and its subcommands: paragraphs not
    broken mid-sentence, arguments named as the text names them (``DATA``), and no
    type shown for a flag (``--json``, ``--help``)."""
    if command.help:
        command.help = _reflow(command.help)
        if command.short_help is None:  # the list of commands shows its first sentence whole
            command.short_help = command.help.split("\n\n")[0].split(". ")[0].rstrip(".") + "."
    ctx = command.context_class(command, info_name=command.name)
    for param in [*command.params, command.get_help_option(ctx)]:
        if param is not None and getattr(param, "is_flag", False) and param.metavar is None:
            param.metavar = ""
        elif getattr(param, "param_type_name", "") == "argument" and param.metavar is None:
            param.metavar = param.name.upper()  # DATA, as the help text names it
    for sub in getattr(command, "commands", {}).values():
        tidy_help(sub)


def main(argv: list[str] | None = None, *, one_command: bool = False) -> int:
    """Entry point: float64 and the compilation cache on, clean errors out.
    ``one_command``: register only the command ``argv`` runs (the process runs no other:
    :func:`run`)."""

    if one_command:
        _load_for(sys.argv[1:] if argv is None else argv)
    else:
        load_commands()
    root = typer.main.get_command(app)
    tidy_help(root)
    for cmd in getattr(root, "commands", {}).values():
        if cmd.callback is not None:
            cmd.callback = _engine_first(cmd)
    try:
        root.main(args=argv, prog_name="diffgyro", standalone_mode=False)
    except DataError as err:
        print(f"diffgyro: error: {err}", file=sys.stderr)
        return 2
    except typer.Exit as err:
        return err.exit_code
    except typer.Abort:
        print("diffgyro: aborted", file=sys.stderr)
        return 130
    except Exception as err:  # usage errors (click's, vendored by typer) carry their own message
        if hasattr(err, "show") and hasattr(err, "exit_code"):
            err.show()
            return err.exit_code
        raise
    return 0


def run() -> None:  # console script
    """``diffgyro`` as a program: :func:`main` (its command alone registered), then the
    process ends at once."""
    _exit_now(main(one_command=True))


def _exit_now(code: int) -> None:
    """End the process with ``code`` once its output is out, without the interpreter's
    teardown: freeing XLA's compiled programs and every module's objects took 0.6-0.9 s
    of a warm ``fit`` after its result was printed. Other threads that are not daemons
    are joined and the exit handlers run first (what a normal exit does before the
    teardown); a write that fails (a closed pipe) ends with the normal exit instead."""
    for end in _jax_setup.before_exit:  # e.g. the kept worker pools, whose threads idle
        end()
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    logging.shutdown()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        sys.exit(code)
    os._exit(code)
