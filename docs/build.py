"""Build the documentation site whole, on a fresh clone: every notebook executed, then
``mkdocs build --strict``.

    python docs/build.py [--site-dir DIR] [--full] [--rerun] [--cell-timeout S]

Each notebook of notebooks/ (Jupytext percent format) runs in a Jupyter kernel (nbclient,
from the notebooks' folder, with this checkout's ``src`` first on the path) in its quick
mode (``DIFFGYRO_NOTEBOOK_QUICK=1``: smaller batches, the same steps; ``--full`` runs the
full sizes). The executed notebook is kept with the hash of its source in
``DIFFGYRO_NOTEBOOK_OUTPUTS`` or ``.notebook-outputs/``, where the site's hook
(docs/hooks.py) reads its printed output and figures; a notebook already kept for its
current source in the requested mode is not run again (``--rerun`` runs every one). The
test suite keeps the notebooks it runs in the same place and form, so after the suite
(as on CI) nothing is executed twice. The build fails when a notebook fails, and checks
that each notebook page of the built site holds the figures its run made.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"


def outputs_dir() -> Path:
    """Where executed notebooks are kept (the hook and the test suite use the same rule)."""
    return Path(os.environ.get("DIFFGYRO_NOTEBOOK_OUTPUTS") or ROOT / ".notebook-outputs")


def _with_src(pythonpath: str | None) -> str:
    return os.pathsep.join(p for p in (str(ROOT / "src"), pythonpath) if p)


def source_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _kept(path: Path):
    """The kept executed notebook of ``path``, or None (absent or unreadable)."""
    import nbformat

    kept = outputs_dir() / f"{path.stem}.ipynb"
    try:
        return nbformat.read(kept, as_version=4) if kept.exists() else None
    except Exception:  # a damaged or half-written file: run the notebook again
        return None


def is_current(path: Path, quick: bool) -> bool:
    """Whether ``path``'s kept run is of its current source, in the requested mode (a
    full-size run serves a quick build too)."""
    nb = _kept(path)
    meta = nb.metadata.get("diffgyro", {}) if nb is not None else {}
    return meta.get("source_sha256") == source_hash(path) and (quick or not meta.get("quick"))


def execute(path: Path, quick: bool, cell_timeout: int) -> None:
    """Run ``path`` top to bottom in a kernel and keep the executed notebook (atomically)."""
    import jupytext
    import nbformat
    from nbclient import NotebookClient

    nb = jupytext.read(path)
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    saved = dict(os.environ)
    os.environ.pop("DIFFGYRO_NOTEBOOK_QUICK", None)
    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend returns the figures
    if quick:
        os.environ["DIFFGYRO_NOTEBOOK_QUICK"] = "1"
    os.environ["PYTHONPATH"] = _with_src(saved.get("PYTHONPATH"))
    try:  # the kernel inherits this environment: this checkout's src first on the path
        NotebookClient(nb, timeout=cell_timeout, kernel_name="python3",
                       extra_arguments=["--IPKernelApp.log_level=ERROR"],  # no start-up chatter
                       resources={"metadata": {"path": str(path.parent)}}).execute()
    finally:
        os.environ.clear()
        os.environ.update(saved)
    nb.metadata["diffgyro"] = {"source": path.name, "source_sha256": source_hash(path),
                               "quick": quick}
    out = outputs_dir()
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{path.stem}.{os.getpid()}.tmp"
    nbformat.write(nb, tmp)
    tmp.replace(out / f"{path.stem}.ipynb")


def figures(path: Path) -> int:
    """How many figures the kept run of ``path`` made."""
    nb = _kept(path)
    return 0 if nb is None else sum("image/png" in o.get("data", {}) for c in nb.cells
                                    if c.cell_type == "code" for o in c.get("outputs", []))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--site-dir", default=str(ROOT / "site"), help="where the site goes (site/)")
    parser.add_argument("--full", action="store_true", help="run the notebooks at their full sizes")
    parser.add_argument("--rerun", action="store_true", help="run every notebook, kept or not")
    parser.add_argument("--cell-timeout", type=int, default=900, help="seconds one cell may take")
    args = parser.parse_args(argv)
    quick = not args.full

    for path in sorted(NOTEBOOKS.glob("*.py")):
        if not args.rerun and is_current(path, quick):
            print(f"{path.name}: kept run is current", flush=True)
            continue
        start = time.perf_counter()
        print(f"{path.name}: running{' (quick mode)' if quick else ''} ...", flush=True)
        try:
            execute(path, quick, args.cell_timeout)
        except Exception as err:  # a failed cell: name the notebook, show the kernel's error
            print(f"{path.name}: failed: {str(err)[-3000:]}", file=sys.stderr)
            return 1
        print(f"{path.name}: done in {time.perf_counter() - start:.0f} s", flush=True)

    env = {**os.environ, "DIFFGYRO_NOTEBOOK_OUTPUTS": str(outputs_dir()),
           "PYTHONPATH": _with_src(os.environ.get("PYTHONPATH"))}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                          "--site-dir", args.site_dir], cwd=ROOT, env=env, check=False)
    if run.returncode:
        return run.returncode

    missing, total = [], 0
    for path in sorted(NOTEBOOKS.glob("*.py")):
        page = Path(args.site_dir) / "notebooks" / path.stem / "index.html"
        shown = len(re.findall(r'<img [^>]*src="[^"]*cell\d+_\d+\.png"', page.read_text("utf-8")))
        total += shown
        if shown < figures(path):
            missing.append(f"{path.name}: {shown} of {figures(path)} figures on its page")
    if missing:
        print("the site lacks notebook figures:\n" + "\n".join(missing), file=sys.stderr)
        return 1
    print(f"site built in {args.site_dir}: {len(list(NOTEBOOKS.glob('*.py')))} notebook pages, "
          f"{total} figures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
