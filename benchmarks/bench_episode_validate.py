"""Episode validation: time and findings on shared/data episodes and on corrupted copies of them.

Each sample episode is validated as is (full decode, and ``--quick``), then copied to a temporary
folder three times and corrupted: one rgb image deleted, a NaN joint in one frames.csv row, and
one rgb PNG truncated at half its bytes. A row says whether the result was valid, whether that
is what was expected, how many problems were reported, the first one, and the median time.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

from benchmarks._harness import BenchContext, time_call
from manisplat.episode import validate
from manisplat.episode.images import find_image

THREADED = False


def _delete_frame(path: Path, index: int) -> None:
    find_image(path / "rgb", index).unlink()


def _nan_row(path: Path, index: int) -> None:
    lines = (path / "frames.csv").read_text().splitlines(keepends=True)
    fields = lines[index + 1].split(",")
    fields[4] = "nan"  # q3
    lines[index + 1] = ",".join(fields)
    (path / "frames.csv").write_text("".join(lines))


def _truncate_png(path: Path, index: int) -> None:
    image = find_image(path / "rgb", index)
    data = image.read_bytes()
    image.write_bytes(data[: len(data) // 2])


CORRUPTIONS: dict[str, Callable[[Path, int], None]] = {
    "deleted frame": _delete_frame,
    "NaN row": _nan_row,
    "truncated PNG": _truncate_png,
}


def _row(name: str, case: str, path: Path, expect_ok: bool, *, decode: bool, repeat: int) -> dict[str, Any]:
    report = validate(path, decode_images=decode)
    seconds = time_call(lambda: validate(path, decode_images=decode), repeat=repeat, warmup=0)
    return {"episode": name, "case": case, "frames": report.frame_rows, "valid": report.ok,
            "as_expected": report.ok == expect_ok, "problems": len(report.problems),
            "first_problem": str(report.problems[0]) if report.problems else "", "time_s": seconds}


def run(ctx: BenchContext) -> list[dict[str, Any]]:
    data = ctx.require_shared("data")
    episodes = sorted(p for p in data.iterdir() if (p / "episode.json").is_file())
    if ctx.quick:
        episodes = episodes[:1]
    repeat = 1 if ctx.quick else 3
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_episode_validate_") as tmp:
        for episode in episodes:
            rows.append(_row(episode.name, "as is", episode, True, decode=True, repeat=repeat))
            rows.append(_row(episode.name, "as is, --quick", episode, True, decode=False, repeat=repeat))
            middle = rows[-1]["frames"] // 2
            for case, corrupt in CORRUPTIONS.items():
                copy = Path(tmp) / f"{episode.name}-{case.replace(' ', '_')}"
                shutil.copytree(episode, copy)
                corrupt(copy, middle)
                rows.append(_row(episode.name, f"{case} (frame {middle})", copy, False, decode=True, repeat=repeat))
    ctx.notes.append("time_s: median wall time of validate() (full decode unless --quick); "
                     "episodes from shared/data, corrupted copies in a temporary folder")
    return rows
