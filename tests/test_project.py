"""Project wiring: the namespaces install where DESIGN.md says, and the README's commands are
the ones CI runs."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
NAMESPACES = {"manisplat": "manisplat", "manisplat.drivers": "drivers", "manisplat.recorder": "recorder", "manisplat.calib": "calib"}


def test_top_level_folders_install_under_the_manisplat_namespace():
    for module, folder in NAMESPACES.items():
        mod = importlib.import_module(module)
        assert Path(mod.__file__).resolve().parent == ROOT / folder


def test_every_package_folder_is_listed_in_pyproject():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert config["package-dir"] == NAMESPACES
    listed = set(config["packages"])
    found = set()
    for module, folder in NAMESPACES.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            found.add(".".join([module, *rel.parts]))
    assert found == listed, f"not listed: {sorted(found - listed)}; listed but absent: {sorted(listed - found)}"


def test_readme_opens_with_the_two_commands_and_ci_runs_the_test_one():
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```(?:bash|sh)?\n(.*?)```", readme, flags=re.S)
    assert len(blocks) >= 2
    install_and_run, test = blocks[0].strip(), blocks[1].strip()
    head = readme[: readme.index(blocks[1]) + len(blocks[1])]
    assert len(head.splitlines()) <= 25, "the two commands must come first"
    intro = readme[: readme.index(blocks[0])]
    assert len(re.sub(r"^#.*$", "", intro, flags=re.M).split()) >= 20, "say what the project is before the command"
    assert "pip install torch==2.13.0" in install_and_run and "manisplat-episode sample" in install_and_run
    assert "manisplat-reconstruct" in install_and_run, "the first command runs the main job on the sample"
    assert ".[" not in install_and_run, "the first command is the base install: no extras ([dev] brings Ray and selenium)"
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install torch==2.13.0" in ci
    assert ci.strip().splitlines()[-1].strip() == test


def _doc_pages() -> list[Path]:
    """README.md and every page of the documentation site."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _readme_outputs() -> set[str]:
    """Paths the commands in README.md and docs/*.md write into the working folder (placeholders
    such as DIR or EP, and benchmarks/ whose results are committed, left out)."""
    found = set()
    for page in _doc_pages():
        for language, block in re.findall(r"```([a-z]*)\n(.*?)```", page.read_text(), flags=re.S):
            if language not in ("bash", "sh", "console"):
                continue
            found |= set(re.findall(r"(?:--out|--video|--report|episode sample)\s+([A-Za-z0-9_./-]+)", block))
    return {p.rstrip("/") for p in found if not p.startswith(("benchmarks/", "-")) and not re.search(r"[A-Z]{2}", p)}


def test_gitignore_covers_what_the_readmes_commands_write():
    import shutil
    import subprocess

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        import pytest

        pytest.skip("not a git checkout")
    outputs = sorted(_readme_outputs())
    assert "demo_twin" in outputs and "demo_lerobot" in outputs and "calibration.json" in outputs
    as_either = [form for p in outputs for form in (p, p + "/")]  # a file or a folder, as it will be
    proc = subprocess.run(["git", "check-ignore", "--no-index", *as_either], cwd=ROOT, capture_output=True, text=True)
    ignored = {p.rstrip("/") for p in proc.stdout.split()}
    assert ignored == set(outputs), f"not in .gitignore: {sorted(set(outputs) - ignored)}"


def _slug(heading: str) -> str:
    """The anchor GitHub (and mkdocs, for headings without runs of punctuation) gives a heading:
    markup dropped, lowercase, punctuation other than '-' and '_' removed, spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links and images: their text
    text = re.sub(r"[`*]", "", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # a '#' in a code block is no heading
    slugs, seen = set(), {}
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, flags=re.M):
        slug = _slug(heading)
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        slugs.add(slug if n == 0 else f"{slug}-{n}")
    return slugs


def _relative_links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)  # inline code is no link
    links = re.findall(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text)
    return [link for link in links if not re.match(r"[a-z][a-z0-9+.-]*:", link)]  # http:, https:, mailto:


def test_slug_follows_github():
    assert _slug("Recording and replay: `manisplat-record`, `manisplat-replay`") == "recording-and-replay-manisplat-record-manisplat-replay"
    assert _slug("LeRobot v3.0") == "lerobot-v30"
    assert _slug("calibration.json") == "calibrationjson"
    assert _slug("The built-in sample") == "the-built-in-sample"


def test_readme_links_and_anchors_resolve():
    """Every relative link in README.md names a file that exists, and every #anchor on it (or on
    the README itself) is a heading there. mkdocs build --strict (.ci/run) checks the links
    between docs/ pages the same way."""
    readme = ROOT / "README.md"
    links = _relative_links(readme)
    assert any(link.startswith("docs/") for link in links)
    broken = []
    for link in links:
        path, _, anchor = link.partition("#")
        target = (readme.parent / path).resolve() if path else readme
        if not target.exists():
            broken.append(f"{link}: no such file")
        elif anchor and (target.suffix != ".md" or anchor not in _anchors(target)):
            broken.append(f"{link}: no heading #{anchor} in {target.relative_to(ROOT)}")
    assert not broken, broken


def test_readme_is_short():
    lines = len((ROOT / "README.md").read_text().splitlines())
    assert lines <= 250, f"README.md has {lines} lines: details belong on the docs/ pages"


def test_the_development_data_folder_is_named_only_where_it_is_used():
    """A clone has no ../shared: user documentation describes such data; only the benchmarks page
    and the development page say where the benchmarks read it."""
    allowed = {ROOT / "docs" / "benchmarks.md", ROOT / "docs" / "development.md"}
    named = [str(page.relative_to(ROOT)) for page in _doc_pages() if page not in allowed and "../shared" in page.read_text()]
    assert not named, f"../shared in {named}"


def test_every_docs_page_is_in_the_site_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    missing = [page.name for page in sorted((ROOT / "docs").glob("*.md")) if not re.search(rf":\s*{re.escape(page.name)}\s*$", nav, flags=re.M)]
    assert not missing, f"not in mkdocs.yml's nav: {missing}"
