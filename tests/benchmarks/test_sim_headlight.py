"""benchmarks.bench_sim_headlight: the scene's headlight switched off and nothing else, the
generator's arguments repeated, the headlight's share measured per region."""

from __future__ import annotations

import json

import cv2
import h5py
import numpy as np
import pytest

from benchmarks.bench_sim_headlight import drawn_again, generator_args, headlight_share, without_headlight

SCENE = """<mujoco>
  <visual>
    <headlight ambient="0.25 0.25 0.25" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
  </visual>
  <worldbody><light name="key" diffuse="0.6 0.6 0.6" dir="0 0 -1"/></worldbody>
</mujoco>"""


def test_only_the_headlights_diffuse_part_is_switched_off():
    patched = without_headlight(SCENE)
    assert '<headlight ambient="0.25 0.25 0.25" diffuse="0 0 0" specular="0 0 0"/>' in patched
    assert '<light name="key" diffuse="0.6 0.6 0.6"' in patched  # the scene's own lights stay
    assert patched.replace('diffuse="0 0 0"', 'diffuse="0.35 0.35 0.35"', 1) == SCENE


@pytest.mark.parametrize("scene", ["<mujoco/>", SCENE.replace(' diffuse="0.35 0.35 0.35"', ""),
                                   SCENE.replace("</visual>", '<headlight diffuse="1 1 1"/></visual>')],
                         ids=["no headlight", "no diffuse", "two headlights"])
def test_a_scene_without_one_headlight_to_switch_off_is_refused(scene):
    with pytest.raises(ValueError, match="headlight"):
        without_headlight(scene)


def test_the_generators_recorded_arguments_are_passed_back_as_flags():
    args = {"task": "handover", "seed": 3, "object_range": [0.04, 0.04, 0.6], "width": 640, "height": 480,
            "fps": 30.0, "frames": 120, "compress": True, "jpeg_quality": 50, "record_noise": True, "noise_seed": 7,
            "cam_high_pos": [-0.25, 0.0, 0.75], "cam_high_target": [0.3, 0.0, 0.05], "cam_high_fovy": 60.0,
            "tilt_deg": 25.0, "timestep": 0.0005, "control_dt": 0.002, "no_shadows": False}
    flags = generator_args({"args": args})
    assert flags[flags.index("--seed") + 1] == "3" and flags[flags.index("--width") + 1] == "640"
    assert flags[flags.index("--frames") + 1] == "120" and flags[flags.index("--noise-seed") + 1] == "7"
    assert "--compress" in flags and "--record-noise" in flags and "--no-shadows" not in flags
    at = flags.index("--object-range")
    assert flags[at + 1:at + 4] == ["0.04", "0.04", "0.6"]


def _sample(folder, brightness: int):
    """A one-frame, three-camera sample whose box (label 1) is ``brightness`` and the rest 100."""
    folder.mkdir()
    masks = np.zeros((1, 16, 16), np.uint8)
    masks[0, :, :8] = 1  # 128 pixels: enough for a share
    image = np.where(masks[0, ..., None] == 1, brightness, 100).astype(np.uint8).repeat(3, -1)
    ok, buf = cv2.imencode(".png", image)  # lossless: the recording's bytes decode to the image
    np.savez(folder / "episode_0.gt.npz", label_names=np.array(["background", "object/box"]),
             **{f"masks_{c}": masks for c in ("cam_high", "cam_left_wrist", "cam_right_wrist")})
    (folder / "episode_0.objects.json").write_text(json.dumps({"objects": {"box": {"role": "manipulated"}}}))
    with h5py.File(folder / "episode_0.hdf5", "w") as f:
        for camera in ("cam_high", "cam_left_wrist", "cam_right_wrist"):
            f.create_dataset(f"observations/images/{camera}", data=buf.reshape(1, -1))


def test_the_headlights_share_is_measured_on_each_regions_own_pixels(tmp_path):
    _sample(tmp_path / "lit", 200)
    _sample(tmp_path / "unlit", 150)
    share = headlight_share(tmp_path / "lit", tmp_path / "unlit", [0])["cam_high"]
    assert share["object"]["median"] == pytest.approx(0.25)  # 1 - 150 / 200 on the box
    assert share["static"]["median"] == pytest.approx(0.0)  # the background the same in both
    assert share["full"]["median"] == pytest.approx(1 - (150 + 100) / (200 + 100), abs=1e-3)


def _drawn(folder, box_x: float):
    """A sample folder already drawn (its HDF5 present): one frame's joints and the box's pose."""
    folder.mkdir()
    (folder / "episode_0.hdf5").write_bytes(b"")
    box = np.eye(4)[None].copy()
    box[0, 0, 3] = box_x
    np.savez(folder / "episode_0.gt.npz", q=np.zeros((1, 14)), gripper=np.zeros((1, 2)), T_world_box=box,
             info=json.dumps({"args": {}}))


def test_a_copy_is_the_sample_drawn_again_only_when_its_states_agree(tmp_path):
    _drawn(tmp_path / "sample", 0.3)
    _drawn(tmp_path / "same", 0.3 + 1e-12)  # another machine's physics: the same states
    _drawn(tmp_path / "moved", 0.301)  # a box a millimetre elsewhere: another episode
    assert drawn_again(tmp_path / "python", tmp_path, tmp_path / "sample", tmp_path / "same") == tmp_path / "same"
    with pytest.raises(RuntimeError, match="T_world_box"):
        drawn_again(tmp_path / "python", tmp_path, tmp_path / "sample", tmp_path / "moved")
