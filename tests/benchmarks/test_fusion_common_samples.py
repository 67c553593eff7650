"""benchmarks.bench_reconstruct_fusion._common_samples: twins compared at new poses only over the
samples each of them turned into a demonstration (a sample one twin refuses is left out)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.bench_reconstruct_fusion import _common_samples


def _twin(folder: Path, valid: dict[int, float]) -> dict:
    """A twin whose manisplat-augment run accepted the samples (seed -> object PSNR) in ``valid``
    out of seeds 0-5, its demonstrations numbered in seed order."""
    folder.mkdir()
    samples, rows = [], {}
    for seed in range(6):
        episode = f"episode_{len(rows):04d}" if seed in valid else None
        samples.append({"seed": seed, "valid": seed in valid, "episode": episode})
        if episode:
            rows[episode] = {"psnr_object": valid[seed], "same_states": {"psnr_object": valid[seed] + 2}}
    (folder / "augment_report.json").write_text(json.dumps({"samples": samples}))
    return {"new_poses": {"demonstrations": rows}}


def test_only_the_samples_every_twin_made_are_compared(tmp_path: Path) -> None:
    twins = {1: _twin(tmp_path / "a", {1: 20.0, 2: 10.0, 4: 22.0}), 5: _twin(tmp_path / "b", {1: 21.0, 3: 30.0, 4: 23.0})}
    common = _common_samples({1: tmp_path / "a", 5: tmp_path / "b"}, twins)
    assert common["samples"] == [1, 4]
    assert common["mean"] == {"1": {"psnr_object": 21.0}, "5": {"psnr_object": 22.0}}
    assert common["mean_same_states"]["5"] == {"psnr_object": 24.0}
