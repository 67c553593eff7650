"""The C++ rasterizer's build cache: keyed by content, not by where the checkout is (issue 11)."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

from tqdm import tqdm

from manisplat.splat.backends import cpu_raster

NAMES = cpu_raster.SOURCE_NAMES + cpu_raster.HEADER_NAMES


def checkout(root: Path) -> Path:
    """A copy of the rasterizer's sources, as another checkout of the project would have them."""
    csrc = root / "manisplat" / "splat" / "csrc"
    csrc.mkdir(parents=True)
    for name in NAMES:
        shutil.copyfile(cpu_raster.CSRC / name, csrc / name)
    return csrc


def test_identical_sources_in_two_checkouts_share_one_build(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    a, b = checkout(tmp_path / "a"), checkout(tmp_path / "b")
    key = cpu_raster.extension_key(a, compiler="c++ 12.2")
    assert key == cpu_raster.extension_key(b, compiler="c++ 12.2")
    assert key == cpu_raster.extension_key(cpu_raster.CSRC, compiler="c++ 12.2")
    assert cpu_raster.build_directory(key) == tmp_path / "ext" / key
    assert cpu_raster.extension_key(a) == cpu_raster.extension_key(b)  # with this machine's flags and compiler


def test_a_changed_source_flag_or_compiler_gets_another_build(tmp_path):
    base = checkout(tmp_path / "base")
    key = cpu_raster.extension_key(base, flags=["-O3"], compiler="c++ 12.2")
    keys = {key}
    for i, name in enumerate(NAMES):
        edited = checkout(tmp_path / f"edit{i}")
        with open(edited / name, "a") as f:
            f.write("\n// an edit\n")
        keys.add(cpu_raster.extension_key(edited, flags=["-O3"], compiler="c++ 12.2"))
    keys.add(cpu_raster.extension_key(base, flags=["-O2"], compiler="c++ 12.2"))
    keys.add(cpu_raster.extension_key(base, flags=["-O3"], compiler="c++ 13.1"))
    assert len(keys) == len(NAMES) + 3
    assert len({cpu_raster.build_directory(k) for k in keys}) == len(keys)


def test_concurrent_first_copies_of_the_sources_are_whole(tmp_path):
    desc = {"test": True}
    results, errors = [], []

    def copy():
        try:
            results.append(cpu_raster._copy_sources(cpu_raster.CSRC, tmp_path, desc))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=copy) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and set(results) == {tmp_path / "src"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no temporary directory left
    for name in NAMES:
        assert (tmp_path / "src" / name).read_bytes() == (cpu_raster.CSRC / name).read_bytes()
    assert json.loads((tmp_path / "src" / "key.json").read_text()) == desc


LOAD_ELSEWHERE = """
import json, logging, sys
from pathlib import Path
logging.basicConfig(level=logging.DEBUG, format="%(name)s: %(message)s")
import torch.utils.cpp_extension as ce
def no_build(*args, **kwargs):
    raise AssertionError("cpp_extension.load was called: a build (ninja) for a cached extension")
ce.load = no_build
from manisplat.splat.backends import cpu_raster
ext = cpu_raster._load(Path(sys.argv[1]))
ops = [n for n in ("forward", "backward", "project_forward") if hasattr(ext, n)]
print(json.dumps({"file": ext.__file__, "ops": ops}))
"""


def test_a_cached_build_loads_from_another_checkout_without_building_or_a_notice(tmp_path):
    cpu_raster.load_extension()  # the suite's one build (or a wait for another worker's), if not cached yet
    name = cpu_raster.extension_key()
    library = cpu_raster._library(cpu_raster.build_directory(name), name)
    mtime = library.stat().st_mtime_ns
    other = checkout(tmp_path / "elsewhere")
    run = subprocess.run([sys.executable, "-c", LOAD_ELSEWHERE, str(other)], capture_output=True, text=True,
                         timeout=300, env=os.environ)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert Path(out["file"]) == library and out["ops"] == ["forward", "backward", "project_forward"]
    assert library.stat().st_mtime_ns == mtime
    assert "building" not in run.stderr and "first build" not in run.stderr, run.stderr
    build_ninja = (library.parent / "build.ninja").read_text()
    assert str(tmp_path) not in build_ninja and str(cpu_raster.CSRC) not in build_ninja  # the cache's own copy


def test_the_build_notice_is_a_line_of_its_own_under_a_progress_bar(capsys, caplog):
    caplog.set_level(logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    logging.getLogger().addHandler(handler)
    try:
        with tqdm(total=10, desc="reconstructing", file=sys.stderr, mininterval=0) as bar:
            bar.update(1)
            cpu_raster._notice("building the C++ rasterizer in %s", "here")
            bar.update(1)
    finally:
        logging.getLogger().removeHandler(handler)
    err = capsys.readouterr().err
    assert re.search(r"(^|[\r\n])building the C\+\+ rasterizer in here\n", err), repr(err)
