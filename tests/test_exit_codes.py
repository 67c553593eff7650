"""One table of exit codes for every CLI (docs/exit-codes.md): the same situation ends with the same
code in every tool, and each tool's --help lists its codes in that numbering."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

import pytest

from manisplat.exit_codes import ExitCode

ROOT = Path(__file__).resolve().parent.parent


def _mains() -> dict[str, Callable[[list[str]], int]]:
    from manisplat.augment.cli import main as augment
    from manisplat.batch.cli import main as batch
    from manisplat.calib.cli import main as calibrate
    from manisplat.drivers.replay_cli import main as replay
    from manisplat.episode.cli import main as episode
    from manisplat.reconstruct.cli import main as reconstruct
    from manisplat.recorder.cli import main as record
    from manisplat.view.cli import main as view

    return {"manisplat-episode": episode, "manisplat-record": record, "manisplat-replay": replay,
            "manisplat-calibrate": calibrate, "manisplat-reconstruct": reconstruct, "manisplat-augment": augment,
            "manisplat-view": view, "manisplat-batch": batch}


def _exit(tool: str, argv: list[str]) -> int:
    """The exit status of ``tool argv``, whether main returns it or argparse raises it."""
    try:
        return int(_mains()[tool](argv))
    except SystemExit as exc:
        return 0 if exc.code is None else int(exc.code)


def test_every_cli_lists_its_exit_codes_in_the_shared_numbering(capsys: pytest.CaptureFixture) -> None:
    scripts = set(re.findall(r"^(manisplat-[a-z]+) =", (ROOT / "pyproject.toml").read_text(), flags=re.M))
    assert scripts == set(_mains()), "a CLI was added or removed: list it here"
    for tool in sorted(scripts):
        assert _exit(tool, ["--help"]) == ExitCode.OK
        text = capsys.readouterr().out
        block = text[text.index("Exit status (the same in every manisplat command"):]
        listed = {int(code) for code in re.findall(r"^  (\d+) ", block, flags=re.M)}
        assert ExitCode.OK in listed and ExitCode.BAD_INPUT in listed, tool
        assert listed <= {int(c) for c in ExitCode}, f"{tool} lists codes outside the table: {listed}"


def test_the_documented_table_is_the_codes_module() -> None:
    page = (ROOT / "docs" / "exit-codes.md").read_text()
    documented = {int(code) for code in re.findall(r"^\| (\d+) \|", page, flags=re.M)}
    assert documented == {int(c) for c in ExitCode}


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from manisplat.episode.synthetic import write_sample_episode

    return write_sample_episode(tmp_path_factory.mktemp("ep") / "sample", frames=8, width=32, height=24)


def test_a_missing_input_is_exit_2_in_every_tool(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    missing = str(tmp_path / "missing")
    out = str(tmp_path / "out")
    cases = {
        "manisplat-episode": [["info", missing], ["validate", missing], ["recover", missing],
                              ["export", missing, "--format", "lerobot", "--out", out],
                              ["copy", missing, out]],
        "manisplat-record": [["--sim", "--camera", f"replay:{missing}", "--out", out], ["--recover", missing]],
        "manisplat-replay": [[missing, "--sim"]],
        "manisplat-calibrate": [["latency", missing]],
        "manisplat-reconstruct": [[missing, "--out", out]],
        "manisplat-augment": [[missing, "--out", out, "-q"]],
        "manisplat-view": [[missing]],
        "manisplat-batch": [["run", missing + ".toml"], ["status", missing]],
    }
    for tool, runs in cases.items():
        for argv in runs:
            code = _exit(tool, argv)
            err = capsys.readouterr().err
            assert code == ExitCode.BAD_INPUT, f"{tool} {argv}: exit {code}: {err}"
            assert "missing" in err, f"{tool} {argv}: the message does not name the path: {err}"


def test_an_output_that_exists_is_exit_2_and_the_advice_is_for_the_shell(sample: Path, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture) -> None:
    used = tmp_path / "used"
    used.mkdir()
    (used / "keep.txt").write_text("earlier results")
    video = tmp_path / "v.mp4"
    video.write_bytes(b"earlier video")
    copied = tmp_path / "copied"
    assert _exit("manisplat-episode", ["copy", str(sample), str(copied)]) == ExitCode.OK
    cases = {
        "manisplat-episode": [["sample", str(sample)], ["copy", str(sample), str(copied)],
                              ["export", str(sample), "--format", "act-hdf5", "--out", str(used)]],
        "manisplat-reconstruct": [[str(sample), "--out", str(used)]],
        "manisplat-augment": [[str(used), "--out", str(used), "-q"]],
        "manisplat-view": [[str(sample), "--video", str(video)]],
    }
    for tool, runs in cases.items():
        for argv in runs:
            code = _exit(tool, argv)
            err = capsys.readouterr().err
            assert code == ExitCode.BAD_INPUT, f"{tool} {argv}: exit {code}: {err}"
            assert "--overwrite" in err and "Python" not in err, f"{tool} {argv}: {err}"
    assert (used / "keep.txt").read_text() == "earlier results" and video.read_bytes() == b"earlier video"
