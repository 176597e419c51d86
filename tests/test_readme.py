"""README.md runs as written: every ```sh block, in order, in one fresh directory.

``diffgyro`` is this interpreter's command line (``diffgyro.cli.main``, what ``python -m
diffgyro`` runs), called in the test's process. Two kinds of line are not
run: ``pip install ...`` (CI installed the package before the tests; the ``diffgyro
demo`` chained after the install is run by tests/test_demo.py) and the line that runs
the test suite itself (``python -m pytest``: this test is part of it). ```text blocks
are synopses and templates with the reader's own file names; they are not run.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

from diffgyro.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"
NOT_RUN = (re.compile(r"^pip install\b"), re.compile(r"\bpython -m pytest\b"))


def shell_blocks(text: str) -> list[str]:
    """The body of every ```sh (or ```bash / ```console) fenced block, in order."""
    return re.findall(r"^```(?:sh|bash|shell|console)\n(.*?)^```", text, re.S | re.M)


def runnable_lines(blocks: list[str]) -> list[str]:
    lines = []
    for block in blocks:
        for line in block.splitlines():
            if line.strip() and not line.lstrip().startswith("#") and \
                    not any(p.search(line) for p in NOT_RUN):
                lines.append(line)
    return lines


def written_files(lines: list[str]) -> list[str]:
    """What the commands write (``--out FILE``, ``-o FILE``, ``> FILE``)."""
    out = []
    for line in lines:
        words = shlex.split(line, comments=True)
        out += [b for a, b in zip(words, words[1:]) if a in ("--out", "-o", ">")]
    return out


def test_readme_commands_run_in_order(tmp_path, monkeypatch, capsys):
    """Each ``diffgyro ...`` line runs through the command line's entry point in this
    process (the worker's compiled programs serve every command, as they would a user's
    shell session of one long-lived interpreter); any other line runs in bash."""
    lines = runnable_lines(shell_blocks(README.read_text(encoding="utf-8")))
    formats = {w for line in lines if line.startswith("diffgyro export")
               for w in re.findall(r"--format (\S+)", line)}
    # the walkthrough reaches every export format
    assert formats >= {"px4", "ardupilot", "c-header", "kalibr", "px4-ekf", "ardupilot-ekf"}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("COLUMNS", "100")
    shell = f'set -euo pipefail\ndiffgyro() {{ {shlex.quote(sys.executable)} -m diffgyro "$@"; }}\n'
    for line in lines:
        words = shlex.split(line, comments=True)
        target = None
        if len(words) > 2 and words[-2] == ">":
            words, target = words[:-2], words[-1]
        if words[0] != "diffgyro" or any(w in ("|", "&&", ";", "<", ">", ">>") for w in words):
            run = subprocess.run(["bash", "-c", shell + line], cwd=tmp_path, capture_output=True,
                                 text=True, timeout=600, check=False)
            assert run.returncode == 0, (line, run.stdout[-3000:], run.stderr[-3000:])
            continue
        code = main(words[1:])
        out = capsys.readouterr()
        assert code == 0, (line, out.out[-3000:], out.err[-3000:])
        assert "Traceback" not in out.err, line
        if target is not None:
            (tmp_path / target).write_text(out.out, encoding="utf-8")
    for name in written_files(lines):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
