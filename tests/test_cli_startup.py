"""Every command line answers ``--help`` and refuses bad arguments without importing torch or
OpenCV (each costs seconds in a fresh shell), and every numeric flag refuses nonsense."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("torch", "cv2", "kornia", "trimesh", "matplotlib", "depthai", "scipy")

ENTRY_POINTS = {
    "manisplat-episode": "manisplat.episode.cli",
    "manisplat-reconstruct": "manisplat.reconstruct.cli",
    "manisplat-record": "manisplat.recorder.cli",
    "manisplat-replay": "manisplat.drivers.replay_cli",
    "manisplat-calibrate": "manisplat.calib.cli",
    "manisplat-augment": "manisplat.augment.cli",
    "manisplat-view": "manisplat.view.cli",
    "manisplat-batch": "manisplat.batch.cli",
}

# (entry point, argv): every --help, top level and per subcommand, and argument errors.
HELP_CALLS = [
    ("manisplat-episode", ["--help"]),
    *[("manisplat-episode", [cmd, "--help"]) for cmd in ("info", "validate", "recover", "import-act", "sample",
                                                                 "set-robot", "copy", "import-lerobot")],
    ("manisplat-episode", ["export", "--help"]),
    ("manisplat-reconstruct", ["--help"]),
    ("manisplat-augment", ["--help"]),
    ("manisplat-view", ["--help"]),
    *[("manisplat-batch", argv) for argv in (["--help"], ["run", "--help"], ["status", "--help"])],
    ("manisplat-record", ["--help"]),
    ("manisplat-replay", ["--help"]),
    ("manisplat-calibrate", ["--help"]),
    *[("manisplat-calibrate", [cmd, "--help"]) for cmd in ("board", "intrinsics", "capture", "solve", "latency",
                                                          "apply")],
]

BAD_ARGUMENTS = [
    ("manisplat-reconstruct", ["ep", "--out", "o", "--iters", "-5"]),
    ("manisplat-augment", ["recon", "--out", "o", "--n", "0"]),
    ("manisplat-augment", ["recon", "--out", "o", "--speed", "1.5"]),
    ("manisplat-augment", ["recon", "--out", "o", "--object-range", "0.1,nan,3"]),
    ("manisplat-reconstruct", ["ep", "--out", "o", "--checkpoint-every", "0"]),
    ("manisplat-reconstruct", ["ep", "--out", "o", "--tau", "nan"]),
    ("manisplat-reconstruct", ["ep", "--out", "o", "--lambda-pose", "-1"]),
    ("manisplat-reconstruct", ["ep", "--out", "o", "--lambda-smooth", "nan"]),
    ("manisplat-episode", ["sample", "out", "--frames", "0"]),
    ("manisplat-episode", ["sample", "out", "--fps", "nan"]),
    ("manisplat-episode", ["import-act", "f.hdf5", "--out", "o", "--K", "30,30,16,12", "--fps", "-1"]),
    ("manisplat-record", ["--sim", "--duration", "-1"]),
    ("manisplat-replay", ["ep", "--speed", "0"]),
    ("manisplat-calibrate", ["latency", "ep", "--max-span", "0"]),
    ("manisplat-record", ["--sim", "--latency-ms", "nan"]),
    ("manisplat-replay", ["ep", "--arm-speed-pct", "0"]),
    ("manisplat-replay", ["ep", "--sim-start", "nan,0,0,0,0,0"]),
    ("manisplat-calibrate", ["solve", "ep", "--board", "b.json", "--out", "c.json", "--corner-offset", "inf"]),
    ("manisplat-calibrate", ["board", "--square-mm", "20", "--marker-mm", "25"]),
    ("manisplat-view", ["twin", "--port", "0"]),
    ("manisplat-view", ["twin", "--orbit", "30"]),
    ("manisplat-view", ["twin", "--port", "70000"]),
    ("manisplat-batch", ["run", "p.toml", "--workers", "0"]),
    ("manisplat-reconstruct", ["ep", "--out", "o", "--threads", "0"]),
    ("manisplat-augment", ["recon", "--out", "o", "--threads", "-1"]),
    ("manisplat-view", ["twin", "--threads", "two"]),
    ("manisplat-batch", ["run", "p.toml", "--threads", "0"]),
    ("manisplat-batch", ["run"]),
    ("manisplat-episode", ["export", "ep", "--format", "lerobot", "--out", "o", "--crf", "99"]),
    ("manisplat-episode", ["export", "ep", "--format", "lerobot", "--out", "o", "--codec", "vp9"]),
    ("manisplat-episode", ["export", "ep", "--format", "lerobot", "--out", "o", "--fps", "0"]),
    ("manisplat-episode", ["import-lerobot", "ds", "--episode", "-1", "--camera", "c", "--K", "1,1,1,1", "--out", "o"]),
]

_PROBE = """
import json, sys
from {module} import main
try:
    code = main({argv!r})
except SystemExit as exc:
    code = exc.code
heavy = [m for m in {heavy!r} if m in sys.modules]
print(json.dumps({{"code": code, "heavy": heavy}}))
"""


def _probe(entry: str, argv: list[str]) -> dict:
    script = _PROBE.format(module=ENTRY_POINTS[entry], argv=argv, heavy=HEAVY)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]) | {"stderr": proc.stderr}


@pytest.mark.parametrize(("entry", "argv"), HELP_CALLS, ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_help_imports_nothing_heavy(entry, argv):
    result = _probe(entry, argv)
    assert result["code"] in (0, None)
    assert result["heavy"] == [], f"{entry} {' '.join(argv)} imported {result['heavy']}"


@pytest.mark.parametrize(("entry", "argv"), BAD_ARGUMENTS, ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_bad_numbers_are_usage_errors_before_anything_heavy(entry, argv):
    result = _probe(entry, argv)
    assert result["code"] == 2, result["stderr"]
    assert "error" in result["stderr"]
    assert result["heavy"] == [], f"{entry} {' '.join(argv)} imported {result['heavy']} to refuse its arguments"


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_version(entry):
    from manisplat import __version__

    script = _PROBE.format(module=ENTRY_POINTS[entry], argv=["--version"], heavy=HEAVY)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    lines = proc.stdout.strip().splitlines()
    assert lines[0] == f"{entry} {__version__}"
    assert json.loads(lines[-1]) == {"code": 0, "heavy": []}
