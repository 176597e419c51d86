"""The project stands alone: its code, docs and notebooks name the published methods by their
recipe names and point at nothing outside the repository."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: A file outside the repository, or a method code ("S0" … "S4") the repository never defines.
OUTSIDE = re.compile(r"DESIGN\.md|SEEDS\.md|\.\./shared|(?<![\w.])/?shared/|\bS[0-4]\b")


def _texts():
    """(where, text) for every docstring of the package and every docs page, notebook, README."""
    for path in sorted((ROOT / "src" / "diffgyro").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                doc = ast.get_docstring(node, clean=False)
                if doc:
                    yield f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}", doc
        # comments and strings too: an output line or a comment is read as well
        yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")
    for pattern in ("docs/**/*.md", "notebooks/*.py", "README.md", "mkdocs.yml"):
        for path in sorted(ROOT.glob(pattern)):
            yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")


def test_no_pointer_outside_the_repository():
    hits = [f"{where}: {m.group(0)!r} in {text[max(0, m.start() - 40):m.end() + 20]!r}"
            for where, text in _texts() for m in OUTSIDE.finditer(text)]
    assert not hits, "\n".join(hits)


def test_the_pattern_catches_what_it_should():
    for bad in ("see DESIGN.md §4", "(SEEDS.md)", "../shared/data", "the S2 profile", "S0, CN1"):
        assert OUTSIDE.search(bad), bad
    for good in ("s1_offset_filter", "fog-one-run", "rate_table_s2", "S20", "docs/formats.md"):
        assert not OUTSIDE.search(good), good


# --------------------------------------------------------------------------- the built site


def _hooks():
    """docs/hooks.py, the generator of the site's API, effect, recipe and CLI pages."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("diffgyro_docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_reference_lists_every_command_and_option():
    """The reference is read from the command objects; check it against the CLI as ``--help``
    shows it: every command heading, every option and argument name, every default."""
    import typer

    from diffgyro import cli

    hooks = _hooks()
    page = hooks.cli_reference()
    getattr(cli, "load_commands", lambda: None)()  # commands register on import
    root = typer.main.get_command(cli.app)
    ctx = root.context_class(root, info_name="diffgyro")
    names = root.list_commands(ctx)
    assert {"fit", "diagnose", "allan", "export", "recipe", "simulate"} <= set(names)
    for name in names:
        cmd = root.get_command(ctx, name)
        assert f"## `diffgyro {name}`" in page, name
        section = page.split(f"## `diffgyro {name}`")[1].split("\n## ")[0]
        sub = cmd.context_class(cmd, info_name=name, parent=ctx)
        rows = {line.split("`")[1]: line for line in section.splitlines() if line.startswith("| `")}
        for p in cmd.get_params(sub):
            row = next((r for k, r in rows.items()
                        if p.opts[0] in re.split(r"[ ,/]+", k.replace("...", ""))), None)
            assert row is not None, (name, p.opts)
            for opt in p.opts + p.secondary_opts:
                assert opt in row, (name, opt)
            default = p.get_default(sub, call=False)
            if p.param_type_name == "option" and getattr(p, "show_default", None) is not False \
                    and default not in (None, False, ()) and not callable(default):
                shown = str(default).lower() if not isinstance(default, bool) else p.name
                assert "default: " in row and (shown in row.lower() or str(default) in row), \
                    (name, p.opts, default, row)


def test_roles_become_links():
    """A docstring's Sphinx roles resolve from where they stand (absolute, relative, bare)."""
    import griffe

    hooks = _hooks()
    pkg = griffe.load("diffgyro", search_paths=[str(ROOT / "src")])
    hooks.SphinxRoles().on_package(pkg=pkg)
    text = "\n".join(o.docstring.value for o in hooks._walk(pkg) if o.docstring is not None)
    assert not hooks.ROLE.search(text)
    # absolute, ``~`` short title, and a bare name inside its own module
    assert '<autoref identifier="diffgyro.status.explain" optional><code>diffgyro.status.explain()' \
        in text
    assert '<autoref identifier="diffgyro.errors.DataError" optional><code>DataError</code>' in text
    detect = pkg["detect"].docstring.value
    assert '<autoref identifier="diffgyro.detect.variance_detector"' in detect
    # the front door of a module comes first on its page
    assert pkg["fit"].exports[0] == "fit"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The documentation site, built as CI builds it (``mkdocs build --strict``)."""
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                         cwd=ROOT, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]
    return out


def _page_text(html: str) -> str:
    """What a reader sees of a page: no icons, scripts or tags."""
    html = re.sub(r"<(svg|script|style)\b.*?</\1>", " ", html, flags=re.S)
    return re.sub(r"<[^>]+>", " ", html)


def test_built_site_has_no_raw_role_and_no_outside_pointer(site):
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 40
    raw, outside = [], []
    for page in pages:
        text = _page_text(page.read_text(encoding="utf-8"))
        raw += [f"{page.relative_to(site)}: {m.group(0)}" for m in
                re.finditer(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):\s*`?\w", text)]
        outside += [f"{page.relative_to(site)}: {m.group(0)}" for m in OUTSIDE.finditer(text)]
    assert not raw, raw[:20]
    assert not outside, outside[:20]
    # roles became links: the status module's explanation is one click from diffgyro.fit
    fit_page = (site / "api" / "fit" / "index.html").read_text(encoding="utf-8")
    assert 'href="../status/#diffgyro.status.explain"' in fit_page


def test_built_site_has_the_tutorial_the_cli_reference_and_the_notebooks(site):
    cli_page = (site / "cli" / "index.html").read_text(encoding="utf-8")
    for command in ("fit", "diagnose", "compensate", "allan", "export", "recipe", "simulate"):
        assert f'id="diffgyro-{command}"' in cli_page, command
    for step in ("first-calibration", "discovery", "batch", "autopilot", "noise"):
        assert (site / "tutorial" / step / "index.html").exists(), step
    for nb in (ROOT / "notebooks").glob("*.py"):
        assert (site / "notebooks" / nb.stem / "index.html").exists(), nb.name
