import json
import re

import cv2
import numpy as np
import pytest

from manisplat.calib.board import BoardSpec, load_board, printable_page, write_printables
from manisplat.calib.detect import BoardDetector
from manisplat.calib.errors import CalibrationError, InputError


def test_board_json_round_trip(tmp_path):
    spec = BoardSpec(squares_x=8, squares_y=6, square_length_m=0.025, marker_length_m=0.018, legacy_pattern=True)
    paths = write_printables(spec, tmp_path / "b", px_per_mm=8)
    assert load_board(paths["json"]) == spec
    raw = json.loads(paths["json"].read_text())
    assert set(raw) == {"type", "dictionary", "squares_x", "squares_y", "square_length_m", "marker_length_m",
                        "legacy_pattern"}


@pytest.mark.parametrize("bad, word", [({"squares_x": 1}, "squares_x"), ({"marker_length_m": 0.04}, "marker_length_m"),
                                       ({"dictionary": "DICT_NOPE"}, "dictionary"), ({"type": "chessboard"}, "type"),
                                       ({"squares_x": 20, "squares_y": 20, "dictionary": "DICT_4X4_50"}, "markers")])
def test_invalid_board_is_refused(bad, word):
    with pytest.raises(CalibrationError, match=word):
        BoardSpec(**bad)


def test_board_file_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_board(tmp_path / "missing.json")
    (tmp_path / "b.json").write_text('{"type": "charuco"}')
    with pytest.raises(InputError, match=r"b.json: missing field"):
        load_board(tmp_path / "b.json")


def test_pdf_and_png_are_true_scale(tmp_path, spec):
    paths = write_printables(spec, tmp_path / "board", px_per_mm=10, paper="a4")
    pdf = paths["pdf"].read_bytes()
    box = [float(v) for v in re.search(rb"/MediaBox\s*\[\s*([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)", pdf).groups()]
    size = sorted([box[2] - box[0], box[3] - box[1]])
    assert size == pytest.approx([210 / 25.4 * 72, 297 / 25.4 * 72], abs=0.05)  # A4 in points
    page = cv2.imread(str(paths["png"]), cv2.IMREAD_GRAYSCALE)
    assert sorted(page.shape) == [2100, 2970]
    det = BoardDetector(spec).detect(page)
    assert len(det.ids) == spec.corner_count
    # corner spacing = 30 mm = 300 px at 10 px/mm
    pts = dict(zip(det.ids.tolist(), det.corners))
    assert np.linalg.norm(pts[1] - pts[0]) == pytest.approx(300.0, abs=0.05)


def test_square_must_be_whole_pixels():
    with pytest.raises(CalibrationError, match="whole number of pixels"):
        printable_page(BoardSpec(square_length_m=0.03025, marker_length_m=0.02), px_per_mm=10)
