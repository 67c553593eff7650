"""import_act_hdf5(): ACT / Cobot Magic HDF5 files written here with h5py."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from episode_factory import ACT_FRAMES as T
from episode_factory import H, W, write_act

from manisplat.episode import EpisodeFormatError, import_act_hdf5, validate
from manisplat.episode.images import StoredChroma

K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("compress", [False, True])
@pytest.mark.parametrize("arm", ["left", "right"])
def test_dual_arm(tmp_path, compress, arm):
    data = write_act(tmp_path / "episode_0.hdf5", compress=compress)
    ep = import_act_hdf5(tmp_path / "episode_0.hdf5", tmp_path / "ep", K=K, arm=arm, fps=25.0,
                         gripper_scale=0.5, task="pick")
    cols = slice(0, 7) if arm == "left" else slice(7, 14)
    qpos, action = data["qpos"][:, cols], data["action"][:, cols]
    assert len(ep) == T and ep.meta.source == "import:act_hdf5" and ep.meta.extra["task"] == "pick"
    assert ep.meta.extra["import"]["compress"] is compress and ep.camera.name == "cam_high"
    assert ep.chroma_subsampling() == (StoredChroma("4:2:0", True) if compress else None)  # RGB arrays encoded
    assert np.array_equal(ep.frames.t, np.arange(T) / 25.0)
    assert np.array_equal(ep.frames.q, qpos[:, :6]) and np.array_equal(ep.frames.gripper, qpos[:, 6] * 0.5)
    assert np.array_equal(ep.frames.actions[:, :6], action[:, :6])
    assert np.array_equal(ep.frames.actions[:, 6], action[:, 6] * 0.5)
    assert np.array_equal(ep.frames.extra["gripper_effort"], data["effort"][:, cols][:, 6])  # the gripper's, as stored
    for i in range(T):
        assert np.array_equal(ep.rgb(i), data["images"]["cam_high"][i])  # stored arrays are RGB
    assert ep.meta.depth_scale == 0.001
    assert np.allclose(ep.depth(2), data["depth"][2] * 0.001, rtol=1e-6)
    assert np.array_equal(ep.camera.K, K)
    assert validate(ep.path).ok


def test_single_arm_no_depth_bgr(tmp_path):
    data = write_act(tmp_path / "a.hdf5", arms=1, depth=False, cameras=("top",))
    ep = import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep", K=K, arm="single", camera="top", bgr=True)
    assert np.array_equal(ep.frames.q, data["qpos"][:, :6]) and not ep.has_depth
    assert np.array_equal(ep.rgb(0), data["images"]["top"][0][..., ::-1])
    with pytest.raises(EpisodeFormatError, match=r"expected \(T, 14\).*arm='left'/'right'"):
        import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep2", K=K, arm="left", camera="top")


def test_jpeg_rows_of_bgr_arrays_kept_their_colours_in_order(tmp_path):
    write_act(tmp_path / "a.hdf5", arms=1, compress=True, depth=False, cameras=("top",))
    ep = import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep", K=K, arm="single", camera="top", bgr=True)
    assert ep.chroma_subsampling() == StoredChroma("4:2:0", False)


def test_errors_name_what_the_file_has(tmp_path):
    write_act(tmp_path / "a.hdf5")
    with pytest.raises(EpisodeFormatError, match="no camera 'cam_low'; cameras in the file: cam_high, cam_left_wrist"):
        import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep", K=K, camera="cam_low")
    with pytest.raises(EpisodeFormatError, match="store no camera intrinsics; pass K="):
        import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep")
    with h5py.File(tmp_path / "b.hdf5", "w") as f:
        f["observations/images/cam_high"] = np.zeros((T, H, W, 3), np.uint8)
    with pytest.raises(EpisodeFormatError, match=r"no dataset /observations/qpos; the file has: "
                                                 r"observations/images/cam_high \(6, 24, 32, 3\) uint8"):
        import_act_hdf5(tmp_path / "b.hdf5", tmp_path / "ep", K=K)
    with pytest.raises(EpisodeFormatError, match="principal point"):
        import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep", K=[[30, 0, 500], [0, 30, 12], [0, 0, 1]])


def test_attribute_contradicts_layout(tmp_path):
    write_act(tmp_path / "a.hdf5")
    with h5py.File(tmp_path / "a.hdf5", "a") as f:
        f.attrs["compress"] = True
    with pytest.raises(EpisodeFormatError, match="compress=True but /observations/images/cam_high"):
        import_act_hdf5(tmp_path / "a.hdf5", tmp_path / "ep", K=K)
