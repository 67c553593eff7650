"""The recording's chroma subsampling: read from JPEG headers and episode.json, modelled on renders
before they are compared with the images, in training and in the held-out scores."""

import json
import re
import shutil

import cv2
import numpy as np
import pytest
import torch

from manisplat.episode.format import EpisodeFormatError
from manisplat.episode.images import StoredChroma, jpeg_chroma_subsampling
from manisplat.episode.reader import Episode
from manisplat.episode.validation import validate
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.chroma import subsample_chroma, subsampled
from manisplat.reconstruct.cli import main
from manisplat.reconstruct.loss import frame_loss
from tests.episode.episode_factory import write_episode

FACTORS = {"4:4:4": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "4:2:2": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
           "4:2:0": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420, "4:4:0": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440,
           "4:1:1": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411}


def coloured_image(height: int = 48, width: int = 64) -> np.ndarray:
    """[H, W, 3] uint8: smooth colour gradients with sharp-edged coloured squares and stripes."""
    y, x = np.mgrid[:height, :width]
    image = np.stack([x * 255 / width, y * 255 / height, (x + y) * 127 / (width + height) + 64], -1)
    image[10:20, 8:30] = (230, 20, 40)
    image[25:41:2, 35:60] = (20, 60, 220)  # one-pixel stripes: only a full-colour image keeps them
    image[30:44, 5:12] = (30, 200, 60)
    return image.astype(np.uint8)


def jpeg(image: np.ndarray, scheme: str, quality: int = 100) -> bytes:
    """``image`` (RGB) as cv2.imencode stores it with ``scheme``."""
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality,
                                            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, FACTORS[scheme]])
    assert ok
    return data.tobytes()


def decoded(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)  # the stored array's channel order


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0 ** 2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


@pytest.mark.parametrize("scheme", sorted(FACTORS))
def test_the_scheme_is_read_from_the_jpeg_header(scheme):
    assert jpeg_chroma_subsampling(jpeg(coloured_image(), scheme, 90)) == scheme
    progressive = cv2.imencode(".jpg", coloured_image(), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1,
                                                          cv2.IMWRITE_JPEG_SAMPLING_FACTOR, FACTORS[scheme]])[1]
    assert jpeg_chroma_subsampling(progressive.tobytes() + b"\0" * 100) == scheme  # zero-padded HDF5 rows too


def test_a_grey_jpeg_has_no_chroma_and_other_bytes_are_refused():
    assert jpeg_chroma_subsampling(cv2.imencode(".jpg", coloured_image()[..., 0])[1].tobytes()) is None
    with pytest.raises(ValueError, match="not a JPEG stream"):
        jpeg_chroma_subsampling(cv2.imencode(".png", coloured_image())[1].tobytes())
    with pytest.raises(ValueError, match="no JPEG frame header"):
        jpeg_chroma_subsampling(b"\xff\xd8\xff\xda\x00\x02")


def encoded(image: np.ndarray, scheme: str, *, as_rgb_array: bool) -> np.ndarray:
    """``image`` (RGB) stored as JPEG at quality 100 (what is lost is the chroma) and decoded back
    to RGB: converted to BGR first as an image file is, or handed over as the RGB array it is
    (``as_rgb_array``), as ACT and Cobot Magic recorders do."""
    if as_rgb_array:
        return decoded(jpeg(image, scheme))
    return decoded(jpeg(image[..., ::-1].copy(), scheme))[..., ::-1]


@pytest.mark.parametrize("scheme", ["4:2:0", "4:2:2", "4:4:0"])
@pytest.mark.parametrize("as_rgb_array", [False, True])
def test_the_model_keeps_the_colour_as_the_jpeg_decoder_gives_it_back(scheme, as_rgb_array):
    image = coloured_image()
    stored = encoded(image, scheme, as_rgb_array=as_rgb_array)
    right = subsample_chroma(torch.from_numpy(image).double(), StoredChroma(scheme, as_rgb_array)).numpy()
    other = subsample_chroma(torch.from_numpy(image).double(), StoredChroma(scheme, not as_rgb_array)).numpy()
    assert psnr(right, stored) > psnr(image, stored) + 8
    assert psnr(right, stored) > psnr(other, stored) + 3
    assert psnr(right, stored) > 38


def test_the_model_keeps_brightness_and_greys_and_passes_gradients():
    image = torch.from_numpy(coloured_image(47, 63)).double().div(255).requires_grad_()  # odd sizes keep their shape
    out = subsample_chroma(image, StoredChroma("4:2:0"))
    assert out.shape == image.shape
    luma = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
    assert torch.allclose(out @ luma, image @ luma, atol=1e-5)
    assert not torch.allclose(out, image, atol=0.05)  # the stripes' colour is gone
    out.sum().backward()
    assert image.grad is not None and torch.isfinite(image.grad).all()
    grey = torch.rand(10, 12, 1).expand(-1, -1, 3)
    assert torch.allclose(subsample_chroma(grey, StoredChroma("4:2:0", True)), grey, atol=1e-5)


def test_only_a_subsampling_scheme_is_modelled():
    assert subsampled(None) is None and subsampled(StoredChroma("4:4:4", True)) is None
    assert subsampled(StoredChroma("4:2:0")) == StoredChroma("4:2:0") and StoredChroma("4:2:2").block == (2, 1)


def test_a_render_as_sharp_as_the_scene_costs_nothing_against_a_subsampled_recording():
    scene = torch.from_numpy(coloured_image()).float() / 255
    recording = torch.from_numpy(decoded(jpeg(coloured_image(), "4:2:0")))  # RGB stored, RGB back
    args = (torch.zeros(48, 64), recording, None, None, None, [], (0.2, 0.0, 0.0, 0.0))
    blurred_loss, _ = frame_loss(scene, *args, StoredChroma("4:2:0", True))
    sharp_loss, _ = frame_loss(scene, *args)
    assert float(blurred_loss) < 0.3 * float(sharp_loss)


def test_an_episode_says_how_its_colour_was_stored(tmp_path):
    png = Episode.open(write_episode(tmp_path / "png", frames=3))
    assert png.chroma_subsampling() is None
    stored = Episode.open(write_episode(tmp_path / "jpg", frames=3, image_format="jpg"))
    assert stored.chroma_subsampling() == StoredChroma("4:2:0", False)  # from the first image's header
    meta_path = tmp_path / "png" / "episode.json"
    meta = json.loads(meta_path.read_text())
    meta["camera"]["chroma_subsampling"] = "4:2:2"
    meta_path.write_text(json.dumps(meta))
    assert Episode.open(tmp_path / "png").chroma_subsampling() == StoredChroma("4:2:2", False)
    meta["camera"]["chroma_red_blue_swapped"] = True
    meta_path.write_text(json.dumps(meta))
    assert Episode.open(tmp_path / "png").chroma_subsampling() == StoredChroma("4:2:2", True)
    wrong = {"chroma_subsampling": ("420", r"camera.chroma_subsampling must be one of 4:4:4, .*; got '420'"),
             "chroma_red_blue_swapped": ("yes", r"camera.chroma_red_blue_swapped must be true or false; got 'yes'")}
    for key, (value, message) in wrong.items():
        meta_path.write_text(json.dumps({**meta, "camera": {**meta["camera"], key: value}}))
        with pytest.raises(EpisodeFormatError, match=message):
            Episode.open(tmp_path / "png")
        report = validate(tmp_path / "png")  # named by validate too, as any field of episode.json
        assert not report.ok and re.search(message, str(report))
    without_scheme = {k: v for k, v in meta["camera"].items() if k != "chroma_subsampling"}
    meta_path.write_text(json.dumps({**meta, "camera": without_scheme}))
    with pytest.raises(EpisodeFormatError, match="chroma_red_blue_swapped is given without chroma_subsampling"):
        Episode.open(tmp_path / "png")


@pytest.fixture(scope="module")
def pick(tmp_path_factory):
    return write_sample_episode(tmp_path_factory.mktemp("pick") / "ep", frames=16, width=64, height=48)


def test_a_camera_stored_subsampled_is_trained_and_scored_as_stored(pick, tmp_path):
    copy = tmp_path / "stored_420"
    shutil.copytree(pick, copy)
    meta = json.loads((copy / "episode.json").read_text())
    meta["camera"].update(chroma_subsampling="4:2:0", chroma_red_blue_swapped=True)
    (copy / "episode.json").write_text(json.dumps(meta))
    for episode, out in ((pick, tmp_path / "full"), (copy, tmp_path / "subsampled")):
        assert main([str(episode), "--out", str(out), "--iters", "6", "-q"]) == 0
    full = json.loads((tmp_path / "full" / "metrics.json").read_text())
    subsampled = json.loads((tmp_path / "subsampled" / "metrics.json").read_text())
    assert "psnr_full_colour" not in full
    assert set(subsampled["psnr_full_colour"]) == {"full", "robot", "object"}
    assert subsampled["psnr"]["full"] != subsampled["psnr_full_colour"]["full"]
