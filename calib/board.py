"""ChArUco boards: the board file (``board.json``), the OpenCV board, printable PNG and PDF.

The board frame is OpenCV's ChArUco object frame: origin at the outer corner of square (0, 0),
x along the columns (``squares_x``), y along the rows, z = x cross y (into the printed face);
chessboard corner ``id`` sits at ``board.getChessboardCorners()[id]`` (corner 0 at (s, s, 0)).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image

from manisplat.calib.errors import CalibrationError, InputError, read_json

BOARD_TYPE = "charuco"
MM_PER_INCH = 25.4
PAPER_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4), "a3": (297.0, 420.0)}


@dataclass(frozen=True)
class BoardSpec:
    """A printed ChArUco board, as ``board.json`` stores it.

    Attributes:
        type: always ``"charuco"``.
        dictionary: an OpenCV ArUco dictionary name, e.g. ``"DICT_5X5_100"``.
        squares_x, squares_y: number of chessboard squares along x (columns) and y (rows).
        square_length_m, marker_length_m: printed square and marker side lengths, metres
            (measure the print and store the measured square length).
        legacy_pattern: True for boards drawn by OpenCV < 4.6 (or calib.io) with an even
            number of rows: OpenCV places the markers differently there.
    """

    type: str = BOARD_TYPE
    dictionary: str = "DICT_5X5_100"
    squares_x: int = 7
    squares_y: int = 5
    square_length_m: float = 0.030
    marker_length_m: float = 0.022
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        problems = []
        if self.type != BOARD_TYPE:
            problems.append(f"type must be {BOARD_TYPE!r}; got {self.type!r}")
        if not (isinstance(self.dictionary, str) and self.dictionary.startswith("DICT_")
                and hasattr(cv2.aruco, self.dictionary)):
            problems.append(f"dictionary {self.dictionary!r} is no OpenCV ArUco dictionary (e.g. 'DICT_5X5_100')")
        for name in ("squares_x", "squares_y"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 2):
                problems.append(f"{name} must be an integer >= 2; got {v!r}")
        s, m = self.square_length_m, self.marker_length_m
        if not (isinstance(s, (int, float)) and math.isfinite(s) and s > 0):
            problems.append(f"square_length_m must be a positive number; got {s!r}")
        elif not (isinstance(m, (int, float)) and math.isfinite(m) and 0 < m < s):
            problems.append(f"marker_length_m must be positive and smaller than square_length_m ({s}); got {m!r}")
        if not isinstance(self.legacy_pattern, bool):
            problems.append(f"legacy_pattern must be true or false; got {self.legacy_pattern!r}")
        if not problems:
            n_markers = (self.squares_x * self.squares_y) // 2
            size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
            if n_markers > size:
                problems.append(f"{self.squares_x}x{self.squares_y} squares need {n_markers} markers; "
                                f"{self.dictionary} has only {size}")
        if problems:
            raise CalibrationError("board: " + "; ".join(problems))

    @property
    def corner_count(self) -> int:
        """Number of inner chessboard corners (ChArUco corner ids 0..corner_count-1)."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the pattern in metres (without the white margin)."""
        return self.squares_x * self.square_length_m, self.squares_y * self.square_length_m

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board (units: metres)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), float(self.square_length_m),
                                       float(self.marker_length_m), dictionary)
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def corners_3d(self) -> np.ndarray:
        """(N, 3) float64 chessboard corners in the board frame, metres, row = corner id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def pattern_image(self, px_per_square: int, margin_px: int = 0) -> np.ndarray:
        """(H, W) uint8 drawing of the pattern, ``px_per_square`` pixels per square, with a white
        margin of ``margin_px``. Pixel (u, v) covers board x in [u, u+1) / px_per_square * s."""
        if px_per_square < 8:
            raise CalibrationError(f"px_per_square must be >= 8 to draw the markers; got {px_per_square}")
        w, h = self.squares_x * px_per_square, self.squares_y * px_per_square
        img = self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)
        if img.shape != (h, w):
            raise CalibrationError(f"OpenCV drew the board at {img.shape[::-1]}, expected {(w, h)}")
        if margin_px:
            img = cv2.copyMakeBorder(img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
        return img

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, raw: Any, source: str = "board") -> BoardSpec:
        """Parse a board JSON object; errors name ``source`` and the bad or missing fields."""
        if not isinstance(raw, dict):
            raise InputError(f"{source}: must hold a JSON object; got {type(raw).__name__}")
        fields = ("type", "dictionary", "squares_x", "squares_y", "square_length_m", "marker_length_m",
                  "legacy_pattern")
        missing = [k for k in fields if k not in raw]
        if missing:
            raise InputError(f"{source}: missing field(s) {missing}")
        try:
            return cls(**{k: raw[k] for k in fields})
        except CalibrationError as exc:
            raise InputError(f"{source}: {exc}") from None


def load_board(path: str | Path) -> BoardSpec:
    """Read ``board.json``; errors name the file."""
    path = Path(path)
    return BoardSpec.from_dict(read_json(path, "board file"), source=str(path))


def save_board(path: str | Path, spec: BoardSpec) -> None:
    Path(path).write_text(json.dumps(spec.to_dict(), indent=1) + "\n", encoding="utf-8")


def printable_page(spec: BoardSpec, px_per_mm: int = 10, paper: str = "a4") -> np.ndarray:
    """(H, W) uint8 page at ``px_per_mm`` with the board centred, a 100 mm scale bar and a label.

    The square side is an integer number of pixels when ``square_length_m * 1000 * px_per_mm``
    is an integer (checked), so the print is exact at 100 % scale.
    """
    if paper not in PAPER_MM:
        raise CalibrationError(f"paper must be one of {sorted(PAPER_MM)}; got {paper!r}")
    px_sq = spec.square_length_m * 1000.0 * px_per_mm
    if abs(px_sq - round(px_sq)) > 1e-6:
        raise CalibrationError(f"square {spec.square_length_m * 1000:g} mm is not a whole number of pixels at "
                               f"{px_per_mm} px/mm; choose a square length in multiples of {1 / px_per_mm:g} mm")
    pattern = spec.pattern_image(int(round(px_sq)))
    margin = 15 * px_per_mm
    pw, ph = (int(round(v * px_per_mm)) for v in PAPER_MM[paper])
    fits = [(w, h) for w, h in ((pw, ph), (ph, pw))
            if pattern.shape[1] <= w - 2 * margin and pattern.shape[0] <= h - 4 * margin]
    if not fits:  # portrait first, else landscape
        raise CalibrationError(f"a {spec.size_m[0] * 1000:g} x {spec.size_m[1] * 1000:g} mm board does not fit on "
                               f"{paper} with 15 mm margins; use a larger paper or smaller squares")
    pw, ph = fits[0]
    page = np.full((ph, pw), 255, np.uint8)
    y0, x0 = (ph - pattern.shape[0]) // 2, (pw - pattern.shape[1]) // 2
    page[y0:y0 + pattern.shape[0], x0:x0 + pattern.shape[1]] = pattern
    # 100 mm scale bar under the board, ticks every 10 mm: measure it after printing.
    yb = y0 + pattern.shape[0] + 8 * px_per_mm
    xb = (pw - 100 * px_per_mm) // 2
    page[yb:yb + px_per_mm // 2 + 1, xb:xb + 100 * px_per_mm + 1] = 0
    for k in range(11):
        x = xb + k * 10 * px_per_mm
        page[yb - 2 * px_per_mm:yb + 1, max(x - 1, 0):x + 2] = 0
    label = (f"ChArUco {spec.squares_x}x{spec.squares_y} {spec.dictionary} square {spec.square_length_m * 1000:g} mm "
             f"marker {spec.marker_length_m * 1000:g} mm legacy={spec.legacy_pattern}. Print at 100% scale; "
             f"bar = 100 mm")
    scale = 0.09 * px_per_mm
    cv2.putText(page, label, (margin // 2, yb + 8 * px_per_mm), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, px_per_mm // 5), cv2.LINE_AA)
    return page


def write_printables(spec: BoardSpec, out_prefix: str | Path, px_per_mm: int = 10,
                     paper: str = "a4") -> dict[str, Path]:
    """Write ``PREFIX.png`` (the page), ``PREFIX.pdf`` (the page at true scale) and
    ``PREFIX.json`` (the board file). Returns the paths by kind."""
    out_prefix = Path(out_prefix)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    page = printable_page(spec, px_per_mm, paper)
    dpi = px_per_mm * MM_PER_INCH
    paths = {"png": out_prefix.with_suffix(".png"), "pdf": out_prefix.with_suffix(".pdf"),
             "json": out_prefix.with_suffix(".json")}
    img = Image.fromarray(page)
    img.save(paths["png"], dpi=(dpi, dpi))
    img.save(paths["pdf"], resolution=dpi)
    save_board(paths["json"], spec)
    return paths
