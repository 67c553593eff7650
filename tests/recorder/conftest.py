from __future__ import annotations

from pathlib import Path

import pytest

from tests.recorder.helpers import write_source


@pytest.fixture(scope="session")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2 s camera recording (60 frames, 64x48, 30 fps) for the replayed camera."""
    return write_source(tmp_path_factory.mktemp("camera") / "source")
