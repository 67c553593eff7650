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
    assert len(head.splitlines()) <= 20, "the two commands must come first"
    assert "pip install torch==2.13.0" in install_and_run and "manisplat-episode sample" in install_and_run
    assert "manisplat-reconstruct" in install_and_run, "the first command runs the main job on the sample"
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install torch==2.13.0" in ci
    assert ci.strip().splitlines()[-1].strip() == test


def _readme_outputs() -> set[str]:
    """Paths the README's commands write into the working folder (placeholders such as DIR or EP, and
    benchmarks/ whose results are committed, left out)."""
    blocks = re.findall(r"```([a-z]*)\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    found = set()
    for language, block in blocks:
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
    assert "demo_twin" in outputs and "demo_lerobot" in outputs
    as_either = [form for p in outputs for form in (p, p + "/")]  # a file or a folder, as it will be
    proc = subprocess.run(["git", "check-ignore", "--no-index", *as_either], cwd=ROOT, capture_output=True, text=True)
    ignored = {p.rstrip("/") for p in proc.stdout.split()}
    assert ignored == set(outputs), f"not in .gitignore: {sorted(set(outputs) - ignored)}"
