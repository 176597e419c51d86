"""MkDocs hooks: pages built from the code at build time.

* ``api/*.md``: one API-reference page per public module of ``diffgyro`` (a
  package's page covers its public submodules), rendered by mkdocstrings from
  the docstrings; the nav's "API reference" section lists them.
* ``<!-- effect-vocabulary -->`` in a page: the table of registered effect terms
  (``diffgyro.effects.registry()``), so the page cannot fall behind the code.
* ``<!-- recipe-table -->``: the table of recipes (``diffgyro.recipes.RECIPES``).
"""

from __future__ import annotations

import pkgutil
import sys
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
#: Modules not in the API reference: the command line (its commands are documented in
#: the README and by ``--help``) and ``python -m diffgyro``.
SKIP = ("diffgyro.cli", "diffgyro.__main__")


def _src_on_path() -> None:
    src = str(ROOT / "src")
    if src not in sys.path:
        sys.path.insert(0, src)


def _public(name: str) -> bool:
    return not any(p.startswith("_") for p in name.split(".")) and \
        not any(name == s or name.startswith(s + ".") for s in SKIP)


def api_modules() -> dict[str, list[str]]:
    """Top-level public module -> the modules its page documents (itself first)."""
    pkg = ROOT / "src" / "diffgyro"
    pages: dict[str, list[str]] = {}
    for info in pkgutil.iter_modules([str(pkg)], "diffgyro."):
        if not _public(info.name):
            continue
        mods = [info.name]
        if info.ispkg:
            sub = pkg / info.name.split(".")[1]
            mods += [m.name for m in pkgutil.walk_packages([str(sub)], info.name + ".")
                     if _public(m.name)]
        pages[info.name.split(".")[1]] = mods
    return dict(sorted(pages.items()))


def _api_page(top: str, mods: list[str]) -> str:
    out = [f"# diffgyro.{top}\n", f"::: {mods[0]}\n    options:\n      show_root_heading: false\n"]
    out += [f"::: {m}\n" for m in mods[1:]]  # a package's submodules, each under its heading
    return "\n".join(out)


def on_config(config):
    nav = config.get("nav")
    if nav is not None:
        api = [{f"diffgyro.{top}": f"api/{top}.md"} for top in api_modules()]
        nav.append({"API reference": api})
    return config


def on_files(files, config):
    for top, mods in api_modules().items():
        files.append(File.generated(config, f"api/{top}.md", content=_api_page(top, mods)))
    return files


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def effect_table() -> str:
    """Markdown table of the registered effect terms: spec, physics, data, coefficients."""
    _src_on_path()
    from diffgyro.effects import parse_term, registry

    rows = ["| term | physics | needs | coefficients per axis |", "|---|---|---|---|"]
    for name, cls in registry().items():
        shown = f"{name}(k)" if cls.order_arg and cls.default_order is None else name
        try:
            term = parse_term(name if not cls.order_arg else f"{name}({cls.default_order or 1})")
            needs = ", ".join(sorted(term.requires())) or "—"
            coeffs = term.coefficient_summary()
        except Exception:  # a term whose example needs arguments the table cannot guess
            needs = coeffs = "—"
        rows.append(f"| `{shown}` | {_cell(cls.description)} | {_cell(needs)} | "
                    f"{_cell(coeffs) or '—'} |")
    return "\n".join(rows)


def recipe_table() -> str:
    """Markdown table of the recipes: name, source, what it does, data it needs."""
    _src_on_path()
    from diffgyro.recipes import RECIPES

    rows = ["| recipe | source | method | needs |", "|---|---|---|---|"]
    for r in RECIPES.values():
        rows.append(f"| `{r.name}` | {_cell(r.source)} | {_cell(r.summary)} | "
                    f"{', '.join(r.needs)} |")
    return "\n".join(rows)


def on_page_markdown(markdown, page, config, files):
    if "<!-- effect-vocabulary -->" in markdown:
        markdown = markdown.replace("<!-- effect-vocabulary -->", effect_table())
    if "<!-- recipe-table -->" in markdown:
        markdown = markdown.replace("<!-- recipe-table -->", recipe_table())
    return markdown
