"""A stage's claim on its output: the pid file beside the partial output."""

from __future__ import annotations

import os
from pathlib import Path

from manisplat.batch.stages import _Claim


def test_the_pid_file_appears_whole_never_empty(tmp_path, monkeypatch):
    """Another process (the batch's status, a test killing the worker) reads the pid as soon as the file
    exists: it must never find it created but not yet written."""
    claim = _Claim(tmp_path / "recon" / "ep0")
    seen_while_writing: list[str | None] = []
    write_text = Path.write_text

    def slow_write_text(path: Path, text: str, *args, **kwargs) -> int:
        path.touch()  # a write is not atomic: the file exists before its bytes are in it
        seen_while_writing.append(claim.pid_file.read_text() if claim.pid_file.is_file() else None)
        return write_text(path, text, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", slow_write_text)
    with claim as partial:
        assert claim.pid_file.read_text() == str(os.getpid())
        partial.mkdir()
    assert seen_while_writing and "" not in seen_while_writing
    assert not claim.pid_file.exists() and not list(claim.pid_file.parent.glob("*.tmp"))
    assert claim.final.is_dir()
