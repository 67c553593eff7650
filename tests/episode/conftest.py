"""Fixtures of the episode tests: small episodes written by the real writer into tmp_path."""

from __future__ import annotations

from pathlib import Path

import pytest
from episode_factory import write_episode


@pytest.fixture
def episode(tmp_path: Path) -> Path:
    """A complete 8-frame 32x24 episode with depth, masks, extra columns and joints.csv."""
    return write_episode(tmp_path / "ep")
