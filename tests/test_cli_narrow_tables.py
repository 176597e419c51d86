"""``diagnose``'s table in an 80-column terminal: no number split and no word cut. The
columns the output gives elsewhere (the close alternatives and the residual's noise in
each device's explanation, the in-sample RMS in --json) are left out, in that order,
with one line saying so; a wide terminal shows every column and no such line."""

from __future__ import annotations

import io
import re

import pytest
from rich.console import Console

from diffgyro.cli import _tables
from diffgyro.cli.diagnose import print_diagnosis


@pytest.fixture(scope="module")
def diagnosis():
    """The README walkthrough's diagnose: two gyros whose bias follows dT/dt, bias_poly(2)."""
    from diffgyro.diagnose import diagnose
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 2, effects="bias_poly(2)+gradient", seed=0, duration=3600.0,
                        sample_rate=2.0)
    return diagnose("bias_poly(2)", batch)


def _printed(diag, width: int) -> str:
    out = io.StringIO()
    print_diagnosis(diag, Console(file=out, width=width, color_system=None))
    return out.getvalue()


def _table_rows(text: str) -> list[list[str]]:
    return [[c.strip() for c in line.split("│")[1:-1]] for line in text.splitlines()
            if line.startswith("│")]


def test_diagnose_table_at_80_columns_cuts_no_word(diagnosis):
    text = _printed(diagnosis, 80)
    drawn = [line for line in text.splitlines() if line[:1] in "┏┃┡│└"]
    assert drawn and max(map(len, drawn)) <= 80, text
    head = [c.strip() for c in drawn[1].split("┃")[1:-1]]
    assert head == ["device", "verdict", "held-out", "floor", "add", "held-out with it"], text
    rows = _table_rows(text)
    assert len(rows) == 2, text  # one line per device: nothing folded
    for d, cells in zip(diagnosis.devices, rows):
        assert cells[:2] == [d.device, d.verdict] and cells[4] == d.best.term, cells
        assert all(re.fullmatch(r"[\d.e+-]+", c) for c in (cells[2], cells[3], cells[5])), cells
    note = next(line for line in text.splitlines() if line.startswith("(at 80 columns"))
    assert note == "(at 80 columns: close alternatives, rms left out; see below and --json)"
    assert len(note) <= 80
    # what the table leaves out is in the explanations that follow
    for d in diagnosis.devices:
        assert d.explanation in text.splitlines()
        assert d.alternatives and all(f"`{c.term}`" in d.explanation for c in d.alternatives)


def test_diagnose_table_in_a_wide_terminal_shows_every_column(diagnosis):
    text = _printed(diagnosis, 160)
    assert "close alternatives" in text and "rms" in text and "(at 160 columns" not in text
    rows = _table_rows(text)
    assert len(rows) == 2 and rows[0][7].startswith(diagnosis.devices[0].alternatives[0].term)


def test_fit_columns_leaves_out_empty_text_and_optional_columns_only_as_needed():
    cols = [("device", "text"), ("x", "number"), ("note", "text"), ("more", "text")]
    rows = [["dev000", "1.5", "", "a long piece of text"], ["dev001", "2.5", "", "more text"]]
    kept, shown, dropped = _tables.fit_columns(cols, rows, 200, optional=("more",))
    assert [c for c, _ in kept] == ["device", "x", "more"] and dropped == []  # empty: gone
    assert shown[0] == ["dev000", "1.5", "a long piece of text"]
    kept, shown, dropped = _tables.fit_columns(cols, rows, 30, optional=("more",))
    assert [c for c, _ in kept] == ["device", "x"] and dropped == ["more"]
