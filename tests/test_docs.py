"""The documentation: the manual builds in strict mode with every public API name documented, and the README is a
short landing page whose links resolve and whose commands run.

The README's shell blocks are run as written, line by line (continuation lines joined), with bash, in a
temporary folder that holds a copy of ``examples/procedural`` (so relative paths mean what they mean at the
repository root, and nothing is written into the checkout), and with this interpreter's ``bin`` folder first on
PATH, so ``usdrelight`` is the console script installed beside ``sys.executable``. ``make`` lines are what CI
runs (only their targets are checked here); ``usdrelight serve`` starts a server, so ``usdrelight serve --help``
stands in for it. Its Python blocks then run in the same folder.
"""
from __future__ import annotations

import ast
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MKDOCS_YML = ROOT / "docs" / "mkdocs.yml"
BIN = Path(sys.executable).parent
USDRELIGHT = BIN / "usdrelight"
#: The commands the README's tour must show.
TOUR_COMMANDS = {"build", "validate", "fit", "render", "relight", "convert", "serve", "batch"}
MAX_README_LINES = 200


def _readme() -> str:
    return README.read_text(encoding="utf-8")


def _code_blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", text, re.M | re.S)


def _shell_lines(block: str) -> list[str]:
    """The block's commands: continuation lines joined, blank lines and comment lines dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    return [line.strip() for line in joined.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _readme_commands() -> list[str]:
    return [line for block in _code_blocks(_readme(), "bash") for line in _shell_lines(block)]


def _api_names() -> list[str]:
    """``usdrelight.api.__all__``, read from the source (nothing imported)."""
    tree = ast.parse((ROOT / "usdrelight" / "api.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            return list(ast.literal_eval(node.value))
    raise AssertionError("usdrelight/api.py defines no __all__")


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["NO_MKDOCS_2_WARNING"] = "1"
    env["PYTHONFAULTHANDLER"] = "1"  # a crash of a command shows its Python stack in the failure message
    return env


# --- the manual ---------------------------------------------------------------------------------------------

def test_manual_builds_strict_with_every_api_name(tmp_path):
    site = tmp_path / "site"
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(MKDOCS_YML),
                           "-d", str(site)], cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    assert "WARNING" not in proc.stderr, proc.stderr
    # every page of docs/manual was built (strict mode also fails on a page missing from nav)
    pages = sorted(p.relative_to(ROOT / "docs" / "manual") for p in (ROOT / "docs" / "manual").rglob("*.md"))
    assert len(pages) >= 10
    for page in pages:
        html = site / page.parent / ("index.html" if page.stem == "index" else Path(page.stem, "index.html"))
        assert html.is_file(), f"{page} was not built"
    api_html = (site / "api" / "index.html").read_text(encoding="utf-8")
    missing = [name for name in _api_names() if f'id="usdrelight.api.{name}"' not in api_html]
    assert not missing, f"API reference lacks {missing}"
    # the images the pages show were copied into the site
    assert (site / "images" / "serve_screenshot.png").stat().st_size > 10_000


def test_manual_references_only_the_public_api():
    """Pages document ``usdrelight.api.<name>`` only: internal module paths move with refactoring."""
    deep = []
    for page in (ROOT / "docs" / "manual").rglob("*.md"):
        for ref in re.findall(r"^:::\s*(\S+)", page.read_text(encoding="utf-8"), re.M):
            if ref != "usdrelight.api" and not re.fullmatch(r"usdrelight\.api\.\w+", ref):
                deep.append(f"{page.name}: {ref}")
    assert not deep, deep


# --- the README ---------------------------------------------------------------------------------------------

def test_readme_is_a_landing_page():
    lines = _readme().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines (at most {MAX_README_LINES})"


def test_readme_relative_links_exist():
    text = _readme()
    targets = re.findall(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text)
    relative = [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]
    assert len(relative) >= 5, f"expected links into the manual, found {relative}"
    broken = [t for t in relative if not (ROOT / t.split("#", 1)[0]).exists()]
    assert not broken, f"README.md links to missing files: {broken}"
    images = [t for t in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:", t)]
    assert images and all(t.startswith("docs/manual/images/") for t in images), images


def test_readme_make_targets_exist():
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    targets = [shlex.split(line)[1] for line in _readme_commands() if line.startswith("make ")]
    assert sorted(targets) == ["demo", "test"], targets
    for target in targets:
        assert re.search(rf"^{re.escape(target)}:", makefile, re.M), f"no make target {target!r}"


@pytest.fixture(scope="module")
def tour(tmp_path_factory):
    """Runs every README shell command in a fresh folder; returns (folder, [(command, argv, proc)])."""
    assert USDRELIGHT.is_file(), f"no usdrelight script beside {sys.executable}"
    work = tmp_path_factory.mktemp("readme_tour")
    shutil.copytree(ROOT / "examples" / "procedural", work / "examples" / "procedural")
    env = _env()
    assert shutil.which("usdrelight", path=env["PATH"]) == str(USDRELIGHT)
    runs = []
    for line in _readme_commands():
        if line.startswith("make "):
            continue
        argv = shlex.split(line, comments=True)
        if argv[:2] == ["usdrelight", "serve"]:
            argv = ["usdrelight", "serve", "--help"]  # a server: only its start-up parsing is checked here
            cmd = shlex.join(argv)
        else:
            cmd = line
        proc = subprocess.run(["bash", "-c", cmd], cwd=work, env=env, capture_output=True, text=True, timeout=300)
        runs.append((line, argv, proc))
    return work, runs


def test_readme_tour_covers_the_cli(tour):
    _, runs = tour
    shown = {argv[1] for _, argv, _ in runs if argv[0] == "usdrelight" and len(argv) > 1}
    assert TOUR_COMMANDS <= shown, f"the README tour lacks {sorted(TOUR_COMMANDS - shown)}"


def test_readme_tour_commands_run(tour):
    work, runs = tour
    assert runs
    for line, argv, proc in runs:
        assert proc.returncode == 0, f"README command failed ({proc.returncode}): {line}\n{proc.stderr[-3000:]}"
        if argv[0] != "usdrelight":
            continue
        sub, args = argv[1], argv[2:]
        out = Path(work, args[args.index("-o") + 1]) if "-o" in args else None
        if sub == "build":
            assert (out / "scene.usda").is_file(), line
        elif sub == "fit" and "--report" in args:
            report = json.loads((work / args[args.index("--report") + 1] / "fit_report.json").read_text())
            assert report["psnr_db"] > 20, report
        elif sub == "render":
            assert list((out / "renders").glob("*.exr")), line
        elif sub == "relight":
            assert (out / "relit.png").stat().st_size > 0 and (out / "relit.exr").is_file(), line
        elif sub == "convert":
            assert (work / args[1]).stat().st_size > 0, line
        elif sub == "batch":
            rows = [json.loads(r) for r in (out / "manifest.jsonl").read_text().splitlines() if r.strip()]
            assert rows and all(r["status"] == "done" for r in rows), rows
        elif sub == "serve":
            assert "usage: usdrelight serve" in proc.stdout


def test_readme_python_api_runs(tour):
    work, runs = tour
    assert all(proc.returncode == 0 for _, _, proc in runs), "the CLI tour failed first"
    blocks = _code_blocks(_readme(), "python")
    assert blocks, "README.md shows no Python"
    for block in blocks:
        proc = subprocess.run([sys.executable, "-c", block], cwd=work, env=_env(), capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f"README Python block failed:\n{block}\n{proc.stderr[-3000:]}"
        assert proc.stdout.strip(), "the README's Python block printed nothing"


def test_generalisation_tables_in_the_manual_are_the_benchmark_json():
    """The held-out tables of docs/manual/relighting.md are benchmarks/generalisation_tables.py's rendering of
    benchmarks/results/generalisation.json, digit for digit (a re-run of the benchmark must update the docs)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from generalisation_tables import tables
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    manual = (ROOT / "docs" / "manual" / "relighting.md").read_text()
    found = tables(json.loads((ROOT / "benchmarks" / "results" / "generalisation.json").read_text()))
    assert len(found) == 3 and all(t.count("\n") >= 5 for t in found)  # header, rule, 4+ rows
    for table in found:
        assert table in manual, table.splitlines()[0]
