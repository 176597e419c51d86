"""README.md runs as written: every ```sh block, in order, in one fresh directory.

``diffgyro`` is this interpreter's ``python -m diffgyro``. Two kinds of line are not
run: ``pip install ...`` (CI installed the package before the tests; the ``diffgyro
demo`` chained after the install is run by tests/test_demo.py) and the line that runs
the test suite itself (``python -m pytest``: this test is part of it). ```text blocks
are synopses and templates with the reader's own file names; they are not run.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

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


def test_readme_commands_run_in_order(tmp_path):
    lines = runnable_lines(shell_blocks(README.read_text(encoding="utf-8")))
    formats = {w for line in lines if line.startswith("diffgyro export")
               for w in re.findall(r"--format (\S+)", line)}
    # the walkthrough reaches every export format
    assert formats >= {"px4", "ardupilot", "c-header", "kalibr", "px4-ekf", "ardupilot-ekf"}
    script = "\n".join(["set -euo pipefail",
                        f'diffgyro() {{ {shlex.quote(sys.executable)} -m diffgyro "$@"; }}',
                        *(f"echo '$ {line.replace(chr(39), '')}'\n{line}" for line in lines)])
    env = {**os.environ, "COLUMNS": "100"}
    run = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=600, check=False)
    assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:])
    assert "Traceback" not in run.stderr
    for name in written_files(lines):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
