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
    assert main(["validate", str(tmp_path / "nowhere")]) == 1


def test_recover(episode, capsys):
    meta = json.loads((episode / "episode.json").read_text())
    (episode / "episode.json").write_text(json.dumps({**meta, "complete": False}))
    png = episode / "rgb" / "000003.png"
    png.write_bytes(png.read_bytes()[:50])
    assert main(["recover", str(episode)]) == 1
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
    assert main(argv) == 1  # exists
    assert "already exists" in capsys.readouterr().err
    assert main(argv[:-4]) == 2  # no --K
    assert main([*argv[:8], "--K", "30,30,16", "--overwrite"]) == 2


@pytest.mark.parametrize("command", ["info", "validate", "recover", "import-act", "sample"])
def test_help(command, capsys):
    assert main([command, "--help"]) == 0
    assert "usage: manisplat-episode " + command in capsys.readouterr().out


def test_no_command(capsys):
    assert main([]) == 2
