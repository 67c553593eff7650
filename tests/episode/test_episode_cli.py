"""manisplat-episode: every subcommand through main(argv), with exit codes and output."""

from __future__ import annotations

import json

import pytest
from episode_factory import write_act

from manisplat.episode import Episode, validate
from manisplat.episode.cli import main


def test_info(episode, capsys):
    assert main(["info", str(episode)]) == 0
    out = capsys.readouterr().out
    assert "frames    8 (frame_count 8)" in out and "declared 10, measured" in out
    assert " deg" in out and "] mm" in out and "joints.csv 32 rows" in out and "complete  yes" in out


def test_validate_exit_codes(episode, tmp_path, capsys):
    assert main(["validate", str(episode)]) == 0
    assert "OK (8 frames" in capsys.readouterr().out
    (episode / "rgb" / "000002.png").unlink()
    assert main(["validate", "--quick", str(episode)]) == 1
    assert "rgb/000002.png (frames.csv line 4): error: missing image" in capsys.readouterr().out
    assert main(["validate"]) == 2
    assert main(["validate", str(tmp_path / "nowhere")]) == 2  # missing input, as everywhere


def test_recover(episode, capsys):
    meta = json.loads((episode / "episode.json").read_text())
    (episode / "episode.json").write_text(json.dumps({**meta, "complete": False}))
    png = episode / "rgb" / "000003.png"
    png.write_bytes(png.read_bytes()[:50])
    assert main(["recover", str(episode)]) == 2  # refused without --drop-damaged: nothing done
    assert "--drop-damaged" in capsys.readouterr().err
    assert main(["-v", "recover", "--drop-damaged", str(episode)]) == 0
    assert "recovered 7 frames" in capsys.readouterr().out
    assert main(["recover", str(episode)]) == 0
    assert "nothing to do" in capsys.readouterr().out


def test_import_act(tmp_path, capsys):
    write_act(tmp_path / "e.hdf5")
    out = tmp_path / "ep"
    argv = ["import-act", str(tmp_path / "e.hdf5"), "--out", str(out), "--arm", "right", "--camera", "cam_high",
            "--K", "30,30,16,12", "--fps", "15"]
    assert main(argv) == 0
    assert "imported 6 frames" in capsys.readouterr().out
    ep = Episode.open(out)
    assert ep.camera.K[0, 0] == 30 and ep.meta.fps == 15 and validate(out).ok
    assert main(argv) == 2  # exists
    assert "already exists" in capsys.readouterr().err
    assert main(argv[:-4]) == 2  # no --K
    assert main([*argv[:8], "--K", "30,30,16", "--overwrite"]) == 2


@pytest.mark.parametrize("command", ["info", "validate", "recover", "import-act", "sample", "set-robot", "copy"])
def test_help(command, capsys):
    assert main([command, "--help"]) == 0
    assert "usage: manisplat-episode " + command in capsys.readouterr().out


def test_no_command(capsys):
    assert main([]) == 2


BAD_NUMBERS = [
    ["sample", "out", "--frames", "0"],
    ["sample", "out", "--frames", "7"],  # the sample needs 8
    ["sample", "out", "--frames", "2.5"],
    ["sample", "out", "--fps", "-16"],
    ["sample", "out", "--fps", "nan"],
    ["sample", "out", "--width", "nan"],
    ["sample", "out", "--height", "0"],
    ["sample", "out", "--seed", "-1"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "30,30,16,12", "--fps", "0"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "30,30,16,12", "--fps", "inf"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "30,30,16,12", "--gripper-scale", "nan"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "30,nan,16,12"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "0,30,16,12"],
    ["import-act", "f.hdf5", "--out", "o", "--K", "30,30,16,12", "--dist", "0.1,nan,0,0"],
]


@pytest.mark.parametrize("argv", BAD_NUMBERS, ids=" ".join)
def test_bad_numbers_are_usage_errors(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error: argument" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "o").exists()


def _subparsers():
    import argparse

    from manisplat.episode.cli import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return parser, sub.choices


def test_every_argument_has_help_and_shows_its_default():
    import argparse

    parser, commands = _subparsers()
    for name, p in [("", parser), *commands.items()]:
        for action in p._actions:
            if isinstance(action, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)):
                continue
            text = action.help or ""
            assert text, f"{name} {action.dest} has no help"
            needs_default = action.option_strings and not action.required or action.nargs == "?"
            assert not needs_default or "default" in text, f"{name} {action.dest}: help does not show its default"


def test_help_shows_the_defaults(capsys):
    assert main(["sample", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(default: 64)" in out and "(default: 8.0)" in out and "(default: off," in out
    assert main(["--help"]) == 0
    assert "-v, --verbose" in capsys.readouterr().out


def test_import_act_arm_choices_are_the_importers():
    from manisplat.episode.importers.act_hdf5 import ARM_COLUMNS

    _, commands = _subparsers()
    (arm,) = [a for a in commands["import-act"]._actions if a.dest == "arm"]
    assert sorted(arm.choices) == sorted(ARM_COLUMNS)
