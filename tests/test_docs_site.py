"""The front page and the site's build: every relative link of README.md and
docs/index.md resolves (file and heading), the README's test command is CI's, the
architecture page draws its diagram, and docs/build.py runs a notebook in a kernel and
keeps it so that the site's page shows its printed output and its figure."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOME_PAGES = ("README.md", "docs/index.md")
#: ``[text](target)`` and ``![alt](target)``, outside code spans.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _module(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _prose(text: str) -> str:
    """Markdown without its fenced blocks and code spans (a link there is not a link)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def slug(heading: str) -> str:
    """The anchor MkDocs' toc gives a heading (and GitHub gives the same for these)."""
    text = re.sub(r"[`*]", "", heading).strip().lower()
    return re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text))


def anchors(path: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", path.read_text(encoding="utf-8"), flags=re.S | re.M)
    return {slug(h) for h in re.findall(r"^#{1,6} (.+?)\s*$", text, flags=re.M)}


def relative_links(page: str) -> list[str]:
    text = _prose((ROOT / page).read_text(encoding="utf-8"))
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:|#|/", t)]


def broken_links(page: str) -> list[str]:
    base = (ROOT / page).parent
    bad = []
    for target in relative_links(page):
        file, _, anchor = target.partition("#")
        path = (base / file).resolve()
        if not path.exists() or not path.is_relative_to(ROOT):
            bad.append(f"{page}: {target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            bad.append(f"{page}: {target}: no heading #{anchor} in {file}")
    return bad


@pytest.mark.parametrize("page", HOME_PAGES)
def test_every_relative_link_of_the_home_pages_resolves(page):
    assert len(relative_links(page)) >= 10, "the home page links into the docs"
    assert broken_links(page) == []


def test_the_link_check_finds_a_broken_link(tmp_path, monkeypatch):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## The part\n", encoding="utf-8")
    (tmp_path / "README.md").write_text(
        "[ok](docs/a.md) [ok](docs/a.md#the-part) `[code](x.md)` [web](https://x.org)\n"
        "[gone](docs/b.md) [bad anchor](docs/a.md#elsewhere)\n", encoding="utf-8")
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    assert broken_links("README.md") == ["README.md: docs/b.md: no such file",
                                         "README.md: docs/a.md#elsewhere: no heading "
                                         "#elsewhere in docs/a.md"]
    assert slug("`--static-only` keeps rest only") == "-static-only-keeps-rest-only"
    assert slug("Units: read from headers, checked for plausibility") == \
        "units-read-from-headers-checked-for-plausibility"


def test_the_front_page_reads_in_two_minutes_and_keeps_ci_command():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.split()) < 1100  # about two minutes of reading
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    command = 'pip install -e ".[dev]" && python -m pytest -n 2 -q'
    assert command in ci and f"```sh\n{command}\n```" in readme
    figure = ROOT / "docs" / "figures" / "discovery-loop.png"
    assert "(docs/figures/discovery-loop.png)" in readme
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size < 150_000
    # CI builds the site with the documented command
    assert "python docs/build.py" in ci


def test_architecture_page_draws_a_mermaid_diagram_not_ascii_art():
    page = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert "```mermaid\nflowchart" in page
    assert not re.search(r"[│┌┐└┘├┤┬┴┼►◄▼▲]", page)
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    assert "name: mermaid" in config and "fence_code_format" in config
    assert "stylesheets/extra.css" in config and (ROOT / "docs/stylesheets/extra.css").exists()


def test_docs_build_runs_a_notebook_and_the_page_shows_its_figure(tmp_path, monkeypatch):
    """docs/build.py's kernel run of a notebook, kept for the hook, which renders its
    printed text and its figure; a changed source makes the kept run stale."""
    build = _module("diffgyro_docs_build", ROOT / "docs" / "build.py")
    hooks = _module("diffgyro_docs_hooks_site", ROOT / "docs" / "hooks.py")
    monkeypatch.setenv("DIFFGYRO_NOTEBOOK_OUTPUTS", str(tmp_path / "kept"))
    nb = tmp_path / "nb" / "tiny.py"
    nb.parent.mkdir()
    nb.write_text("# %% [markdown]\n# # A tiny notebook\n\n# %%\nimport os\n\nimport matplotlib.pyplot as plt\n\n"
                  "plt.plot([0, 1], [1, 0])\nplt.show()\n"
                  "print('quick' if os.environ.get('DIFFGYRO_NOTEBOOK_QUICK') else 'full',"
                  " os.getcwd())\n", encoding="utf-8")
    assert not build.is_current(nb, quick=True)
    build.execute(nb, quick=True, cell_timeout=120)
    assert build.is_current(nb, quick=True) and not build.is_current(nb, quick=False)
    assert build.figures(nb) == 1
    page, images = hooks.notebook_page(nb)
    assert f"quick {nb.parent}" in page  # ran in quick mode, from the notebook's folder
    assert list(images) == ["cell1_0.png"] and images["cell1_0.png"][:4] == b"\x89PNG"
    assert "![figure of cell 1](tiny/cell1_0.png)" in page
    assert "output below is from its last run in quick mode" in page
    nb.write_text(nb.read_text(encoding="utf-8") + "\n# %%\n1\n", encoding="utf-8")
    assert not build.is_current(nb, quick=True)
    page, images = hooks.notebook_page(nb)  # a stale run is not shown: the source alone
    assert images == {} and f"quick {nb.parent}" not in page
    assert "once it has been run for this source: `python docs/build.py`" in page
