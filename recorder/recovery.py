"""Recovery of episodes a recorder left incomplete (killed, power lost, disk full).

``manisplat-record --recover DIR`` and every start of ``manisplat-record`` (on its ``--out``
folder) run :func:`recover_all`: for each episode with ``complete: false`` the CAN log is cut
back to its last whole line (every arm's: ``can.asc`` or ``can_<arm>.asc``;
:func:`~.canlog.repair_can_log`), then
:func:`manisplat.episode.recover` keeps every frame whose image and ``frames.csv`` row were both
written, moves crash artefacts aside into ``<episode>/.recovered/`` (nothing is deleted) and
marks the episode complete.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from dataclasses import dataclass
from pathlib import Path

from manisplat.episode import EpisodeFormatError, RecoveryReport, recover
from manisplat.episode.format import META_FILE, RECOVERED_DIR
from manisplat.recorder.canlog import repair_can_log

log = logging.getLogger(__name__)


@dataclass
class Recovered:
    """The outcome for one episode: ``report`` when recovered, ``error`` when it could not be."""

    path: Path
    report: RecoveryReport | None = None
    can_bytes_cut: int = 0
    error: str | None = None

    def __str__(self) -> str:
        if self.error:
            return f"{self.path}: NOT recovered: {self.error}"
        cut = f"; cut torn CAN log lines ({self.can_bytes_cut} bytes)" if self.can_bytes_cut else ""
        return f"{self.report}{cut}"


def _is_incomplete(path: Path) -> bool:
    try:
        raw = json.loads((path / META_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return True  # unreadable episode.json: let recover() say what is wrong
    return raw.get("complete") is not True


def incomplete_episodes(folder: str | Path) -> list[Path]:
    """``folder`` itself when it is an incomplete episode, else its incomplete episode sub-folders."""
    folder = Path(folder)
    if (folder / META_FILE).is_file():
        return [folder] if _is_incomplete(folder) else []
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_dir() and (p / META_FILE).is_file() and _is_incomplete(p))


def recover_episode(path: str | Path) -> Recovered:
    """Recover one episode (module docstring); errors are returned, not raised."""
    path = Path(path)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    try:
        cut = sum(repair_can_log(log_file, path / RECOVERED_DIR / f"{stamp}-can")
                  for log_file in sorted(path.glob("can*.asc")))
        report = recover(path)
    except (EpisodeFormatError, OSError) as exc:
        return Recovered(path, error=str(exc))
    if report.validation is not None and not report.validation.ok:
        return Recovered(path, report, cut, error=f"still invalid after recovery:\n{report.validation}")
    return Recovered(path, report, cut)


def recover_all(folder: str | Path) -> list[Recovered]:
    """Recover every incomplete episode in (or at) ``folder``."""
    results = []
    for path in incomplete_episodes(folder):
        result = recover_episode(path)
        (log.error if result.error else log.info)("%s", result)
        results.append(result)
    return results
