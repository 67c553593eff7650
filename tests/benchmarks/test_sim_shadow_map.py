"""benchmarks.bench_sim_shadow_map: the recorder's JPEG, the scored regions and their PSNR."""

from __future__ import annotations

import math

import cv2
import numpy as np

from benchmarks.bench_sim_shadow_map import chroma_as_recorded, recorder_jpeg, region_of, region_psnr
from manisplat.episode.images import StoredChroma

LABELS = ["background", "left/link1", "right/link6", "left/wrist_camera", "object/box", "object/can", "mat_left"]


def test_the_recorders_jpeg_keeps_the_channel_order_and_subsamples_the_swapped_chroma():
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[:, 16:, 0] = 255  # a red right half
    back = recorder_jpeg(rgb, 90)
    assert back.shape == rgb.shape and back.dtype == np.uint8
    assert back[:, 20:, 0].mean() > 240 and back[:, 20:, 2].mean() < 15  # still red, in channel 0
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    true_order = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.abs(back.astype(int) - true_order).max() > 10  # not what a BGR-correct recorder would store


def test_the_modelled_chroma_is_what_the_recorders_jpeg_kept_of_the_colour():
    rgb = np.zeros((32, 40, 3), np.uint8)
    rgb[:, :, 1] = np.linspace(40, 200, 40, dtype=np.uint8)
    rgb[5:20:2, 6:30, 0] = 230  # one-pixel red stripes: their colour is what 4:2:0 loses
    rgb[22:30, 9:17] = (20, 40, 220)
    stored = recorder_jpeg(rgb, 100)
    modelled = chroma_as_recorded(rgb[None], StoredChroma("4:2:0", red_blue_swapped=True))[0]
    unswapped = chroma_as_recorded(rgb[None], StoredChroma("4:2:0", red_blue_swapped=False))[0]

    def err(image):
        return float(((image.astype(float) - stored) ** 2).mean())
    assert modelled.dtype == np.uint8 and err(modelled) < 0.2 * err(rgb) and err(modelled) < 0.5 * err(unswapped)


def test_regions_split_robot_manipulated_objects_and_the_static_rest():
    regions = region_of(LABELS, ["box"])
    assert regions["robot"].tolist() == [1, 2, 3]
    assert regions["object"].tolist() == [4]
    assert regions["static"].tolist() == [0, 5, 6]  # a can left alone is scenery


def test_region_psnr_scores_each_region_on_its_own_pixels():
    reference = np.full((1, 4, 4, 3), 100, np.uint8)
    images = reference.copy()
    images[0, 0, :2] += 10  # two robot pixels off by 10
    labels = np.zeros((1, 4, 4), int)
    labels[0, 0, :2] = 1
    labels[0, 3, 3] = 4
    scores = region_psnr(images, reference, labels, region_of(LABELS, ["box", "can"]))
    assert math.isclose(scores["robot"], round(10 * math.log10(255 ** 2 / 100), 2))
    assert math.isclose(scores["full"], round(10 * math.log10(255 ** 2 / (100 * 2 / 16)), 2))
    assert scores["static"] == float("inf") and scores["object"] == float("inf")
    labels[0, 3, 3] = 0
    assert region_psnr(images, reference, labels, region_of(LABELS, ["box"]))["object"] is None
