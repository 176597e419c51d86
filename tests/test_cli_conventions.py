"""Two of the command line's conventions on the README walkthrough's batch (two gyros whose
bias follows temperature and dT/dt):

* ``fit`` says in one line when a device's held-out RMS stands several times above its
  noise floor, and points to ``diagnose``; a model that holds every effect gets no such
  line, and ``--json`` keeps stdout pure (the ratio is a field there);
* ``diagnose``'s table in an 80-column terminal splits no number and cuts no word: the
  columns the output gives elsewhere (the close alternatives and the residual's noise in
  each device's explanation, the in-sample RMS in --json) are left out, in that order,
  with one line saying so; a wide terminal shows every column and no such line.
"""

from __future__ import annotations

import io
import json
import re

import pytest
from rich.console import Console

from diffgyro.cli import _tables, main
from diffgyro.cli.diagnose import print_diagnosis

NOTE = re.compile(r"^(dev\d{3}): held-out RMS ([\d.]+)x its noise floor: .*diffgyro diagnose",
                  re.M)


@pytest.fixture(scope="module")
def walkthrough(tmp_path_factory):
    """The walkthrough's batch (``diffgyro simulate --plan thermal --devices 2 --duration
    3600 --rate 2 --effects 'bias_poly(2)+gradient'``) and its CSV file."""
    from diffgyro.io import save
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 2, effects="bias_poly(2)+gradient", seed=0, duration=3600.0,
                        sample_rate=2.0)
    return batch, save(batch, tmp_path_factory.mktemp("conventions") / "x.csv")


@pytest.fixture(scope="module")
def diagnosis(walkthrough):
    from diffgyro.diagnose import diagnose

    return diagnose("bias_poly(2)", walkthrough[0])


def test_fit_names_a_residual_above_the_floor_and_points_to_diagnose(walkthrough, capsys,
                                                                      monkeypatch):
    _, walkthrough = walkthrough
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)"]) == 0
    out = capsys.readouterr().out
    notes = NOTE.findall(out)
    assert len([line for line in out.splitlines() if "noise floor:" in line]) == len(notes)

    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)  # stdout is the JSON object alone
    above = [(d["device"], f"{d['residual_ratio']:.3g}") for d in doc["devices"]
             if d["residual_ratio"] > 3.0]
    # a line for each device above three times its floor (dev000, 4.7x), none for the other
    assert notes == above and [d for d, _ in notes] == ["dev000"], (notes, above)
    assert all(float(r) <= 10.0 for _, r in notes)  # several times: written, not refused

    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)+gradient"]) == 0
    assert not NOTE.search(capsys.readouterr().out)  # the right model: nothing to say


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
