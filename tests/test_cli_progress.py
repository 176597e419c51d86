"""Long commands show a progress display on stderr when it is a terminal (a pseudo-terminal
here, around the command in its own process), none under --quiet (checked in this process,
stderr answering that it is a terminal) or when stderr is not a terminal; stdout stays the
command's. ``demo``'s display is checked on the run test_demo.py makes."""

from __future__ import annotations

import json
import os
import pty
import re
import subprocess
import sys
import threading

import pytest

from diffgyro.cli import _progress, main

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _on_terminal(argv: list[str], cwd, python: tuple[str, ...] = ("-m", "diffgyro")
                 ) -> tuple[int, str, str]:
    """Run ``python -m diffgyro ARGV`` (or ``python PYTHON... ARGV``) with stderr on a
    pseudo-terminal; (code, stdout, stderr as drawn: control codes removed, redraws
    ``\\r`` kept)."""
    master, slave = pty.openpty()
    env = {**os.environ, "TERM": "xterm", "COLUMNS": "120"}
    for name in ("NO_COLOR", "FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE"):
        env.pop(name, None)
    proc = subprocess.Popen([sys.executable, *python, *argv], cwd=cwd, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=slave)
    os.close(slave)
    drawn: list[bytes] = []

    def read():
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                return
            if not chunk:
                return
            drawn.append(chunk)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    out, _ = proc.communicate(timeout=300)
    reader.join(timeout=10)
    os.close(master)
    err = ANSI.sub("", b"".join(drawn).decode("utf-8", "replace"))
    return proc.returncode, out.decode(), err


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("progress")
    subprocess.run([sys.executable, "-m", "diffgyro", "simulate", "--plan", "thermal",
                    "--devices", "2", "--duration", "600", "--rate", "1", "--out", "x.csv"],
                   cwd=folder, check=True, capture_output=True, timeout=120)
    return folder


def test_diagnose_shows_its_stages_on_a_terminal_and_json_stays_pure(recording):
    code, out, err = _on_terminal(["diagnose", "x.csv", "--model", "bias_poly(1)", "--json"],
                                  recording)
    assert code == 0, err
    assert json.loads(out)["model"] == "bias_poly(1)"  # stdout: the object alone
    assert "\r" in err  # the display redraws in place
    assert "fitting bias_poly(1) on 2 device(s)" in err, err
    assert re.search(r"scoring \d+ candidate\(s\) on devices 1-2 of 2", err), err


def test_allan_and_simulate_show_their_stages_on_a_terminal(recording):
    code, out, err = _on_terminal(["allan", "x.csv", "--json"], recording)
    assert code == 0, err
    assert len(json.loads(out)["devices"]) == 2  # stdout: the object alone
    assert "Allan deviation and its read-outs" in err, err
    code, _, err = _on_terminal(["simulate", "--plan", "static", "--devices", "1", "--duration",
                                 "60", "--out", "s.csv"], recording)
    assert code == 0, err
    assert "simulating 1 device(s), plan static" in err and "wrote s.csv" in err, err


def test_quiet_draws_nothing(recording, capsys, monkeypatch):
    """In this process, stderr made to answer that it is a terminal (without --quiet the
    same call draws the display into it, control codes, redraws and all)."""
    monkeypatch.setitem(_progress._state, "quiet", False)   # --quiet sets it; put back after
    monkeypatch.setitem(_progress._state, "said_compiling", False)
    monkeypatch.chdir(recording)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    capsys.readouterr()
    code = main(["--quiet", "diagnose", "x.csv", "--model", "bias_poly(1)", "--json"])
    captured = capsys.readouterr()
    out, err = captured.out, ANSI.sub("", captured.err)
    assert code == 0, err
    assert json.loads(out)["model"] == "bias_poly(1)"
    assert "fitting" not in err and "\r" not in err and _progress.COMPILING not in err, err


def test_nothing_is_drawn_when_stderr_is_not_a_terminal(capsys, monkeypatch):
    monkeypatch.setitem(_progress._state, "quiet", False)
    monkeypatch.setitem(_progress._state, "said_compiling", False)
    with _progress.steps("working", total=3) as step:
        step.advance()
        step("next stage")
        _progress.compiling()
    assert capsys.readouterr().err == ""


def test_compile_notice_once_on_a_terminal(capsys, monkeypatch):
    monkeypatch.setitem(_progress._state, "quiet", False)
    monkeypatch.setitem(_progress._state, "said_compiling", False)
    monkeypatch.setattr(_progress, "shown", lambda: True)
    _progress.compiling()
    _progress.compiling()
    assert capsys.readouterr().err == _progress.COMPILING + "\n"


def test_root_quiet_option_is_listed(capsys):
    from diffgyro.cli import main

    assert main(["--help"]) == 0
    assert "--quiet" in capsys.readouterr().out
