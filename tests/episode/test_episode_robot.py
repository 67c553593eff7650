"""An episode's robot.description after the episode moves: clear errors, set-robot, copy, --embed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import trimesh

from manisplat.episode import validate
from manisplat.episode.cli import main
from manisplat.robot import RobotModelError, load_robot

TOY_URDF = """<?xml version="1.0"?>
<robot name="toy">
  <link name="base"><visual><geometry><mesh filename="../meshes/base.stl"/></geometry></visual></link>
  <link name="arm">
    <visual><geometry><mesh filename="package://toy/meshes/arm.stl" scale="1 1 1"/></geometry></visual>
    <collision><geometry><mesh filename="package://toy/meshes/arm.stl"/></geometry></collision>
  </link>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="arm"/><origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" velocity="1" effort="1"/>
  </joint>
</robot>
"""


def write_toy(root: Path) -> Path:
    """``root/toy/urdf/toy.urdf`` with a relative mesh and a package:// mesh (package "toy")."""
    (root / "toy" / "urdf").mkdir(parents=True)
    (root / "toy" / "meshes").mkdir()
    trimesh.creation.box(extents=(0.1, 0.1, 0.02)).export(root / "toy" / "meshes" / "base.stl")
    trimesh.creation.icosphere(radius=0.03).export(root / "toy" / "meshes" / "arm.stl")
    urdf = root / "toy" / "urdf" / "toy.urdf"
    urdf.write_text(TOY_URDF)
    return urdf


def description(episode: Path) -> str:
    return json.loads((episode / "episode.json").read_text())["robot"]["description"]


def set_description(episode: Path, value: str) -> None:
    meta = json.loads((episode / "episode.json").read_text())
    meta["robot"]["description"] = value
    (episode / "episode.json").write_text(json.dumps(meta))


@pytest.fixture
def toy(tmp_path: Path) -> Path:
    return write_toy(tmp_path / "robots")


@pytest.fixture
def relative_episode(episode: Path, toy: Path) -> Path:
    """The factory episode naming the toy URDF by a path relative to the episode folder."""
    set_description(episode, "../robots/toy/urdf/toy.urdf")
    assert load_robot(description(episode), base_dir=episode, load_meshes=False).name.endswith("toy.urdf")
    return episode


def test_missing_description_says_where_it_looked_and_how_to_fix_it(relative_episode, tmp_path):
    copy = tmp_path / "elsewhere" / "ep"
    shutil.copytree(relative_episode, copy)
    with pytest.raises(FileNotFoundError) as err:
        load_robot(description(copy), base_dir=copy)
    message = str(err.value)
    assert "robot.description" in message and "'../robots/toy/urdf/toy.urdf'" in message
    assert f"looked at {tmp_path / 'elsewhere' / 'robots' / 'toy' / 'urdf' / 'toy.urdf'}" in message
    assert "--robot URDF|builtin:agilex_piper" in message and f"manisplat-episode set-robot {copy}" in message
    # validate points at it too, without failing the episode (the joint data are fine)
    report = validate(copy)
    assert report.ok
    assert any(p.file == "episode.json" and "set-robot" in p.message for p in report.warnings)


def test_unknown_builtin_lists_the_known_ones():
    with pytest.raises(RobotModelError, match="unknown built-in robot 'builtin:franka'; known: builtin:agilex_piper"):
        load_robot("builtin:franka")


def test_copy_rewrites_a_relative_description(relative_episode, toy, tmp_path, capsys):
    dst = tmp_path / "copies" / "ep"
    assert main(["copy", str(relative_episode), str(dst)]) == 0
    assert description(dst) == str(toy.resolve())
    assert description(relative_episode) == "../robots/toy/urdf/toy.urdf"  # the source is untouched
    assert load_robot(description(dst), base_dir=dst, load_meshes=False).name == str(toy.resolve())
    files = sorted(p.relative_to(relative_episode) for p in relative_episode.rglob("*"))
    assert sorted(p.relative_to(dst) for p in dst.rglob("*")) == files
    assert (dst / "frames.csv").read_bytes() == (relative_episode / "frames.csv").read_bytes()
    assert validate(dst).ok and not validate(dst).warnings

    assert main(["copy", str(relative_episode), str(dst)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["copy", str(relative_episode), str(dst), "--overwrite"]) == 0
    assert main(["copy", str(relative_episode), str(relative_episode / "inside")]) == 2
    assert "inside" in capsys.readouterr().err


def test_copy_embed_makes_a_self_contained_episode(relative_episode, toy, tmp_path):
    dst = tmp_path / "copies" / "ep"
    assert main(["copy", "--embed", str(relative_episode), str(dst)]) == 0
    shutil.move(tmp_path / "robots", tmp_path / "gone")  # the original robot files are no longer there
    assert description(dst) == "robot/toy.urdf"
    model = load_robot(description(dst), base_dir=dst)  # with its meshes
    assert sorted(model.visuals) == ["arm", "base"]
    assert all(Path(v.source).is_relative_to(dst / "robot") for vs in model.visuals.values() for v in vs)
    moved = tmp_path / "moved"
    shutil.move(dst, moved)  # and the embedded copy moves with the episode
    assert len(load_robot(description(moved), base_dir=moved).visuals) == 2
    assert validate(moved).ok and not validate(moved).warnings


def test_set_robot(relative_episode, toy, tmp_path, capsys, monkeypatch):
    ep = relative_episode
    assert main(["set-robot", str(ep), "builtin:agilex_piper"]) == 0
    assert description(ep) == "builtin:agilex_piper"
    monkeypatch.chdir(tmp_path)
    assert main(["set-robot", str(ep), "robots/toy/urdf/toy.urdf"]) == 0  # relative to where the user is
    assert description(ep) == str(toy.resolve())
    assert "builtin:agilex_piper" in capsys.readouterr().out  # says what it replaced

    before = (ep / "episode.json").read_bytes()
    for bad, said in (("builtin:franka", "known: builtin:agilex_piper"), ("nowhere.urdf", "not found")):
        assert main(["set-robot", str(ep), bad]) == 2
        assert said in capsys.readouterr().err
        assert (ep / "episode.json").read_bytes() == before  # unchanged
    assert main(["set-robot", str(ep), "builtin:agilex_piper", "--embed"]) == 2
    assert "nothing to embed" in capsys.readouterr().err

    assert main(["set-robot", str(ep), "--embed"]) == 0  # embeds the current description
    assert description(ep) == "robot/toy.urdf" and len(load_robot("robot/toy.urdf", base_dir=ep).visuals) == 2
    assert main(["set-robot", str(ep), "--embed"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["set-robot", str(ep), "--embed", "--overwrite"]) == 0  # from the embedded copy itself
    assert len(load_robot(description(ep), base_dir=ep).visuals) == 2
    assert sorted(p.name for p in (ep / "robot").rglob("*.stl")) == ["arm.stl", "base.stl"]
    assert validate(ep).ok
