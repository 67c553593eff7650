"""A small episode, its reconstruction (5 iterations) and one augmented demonstration, made once per
test session module: what manisplat-view shows."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from manisplat.augment.cli import main as augment
from manisplat.episode.synthetic import write_sample_episode
from manisplat.reconstruct.cli import main as reconstruct


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """{"episode", "recon", "aug"}: the episode (32 frames, 64x48) beside its twin and augmentation."""
    root = tmp_path_factory.mktemp("view")
    episode = write_sample_episode(root / "demo", frames=32, width=64, height=48)
    assert reconstruct([str(episode), "--out", str(root / "twin"), "--iters", "5", "-q"]) == 0
    assert augment([str(root / "twin"), "--n", "1", "--out", str(root / "aug"), "--seed", "1", "-q"]) == 0
    return {"episode": episode, "recon": root / "twin", "aug": root / "aug"}


@pytest.fixture
def free_port() -> int:
    """A TCP port free on localhost right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
