"""The exit codes every ``manisplat-*`` command shares (docs/exit-codes.md): the same situation gets
the same code in every tool, so a script can tell what happened without reading the log."""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    OK = 0
    """The job finished (also ``--help``, ``--version``, a passing ``--dry-run``)."""
    FAILED = 1
    """The job ran and failed: an episode that does not validate, fewer demonstrations than asked for,
    a diverged calibration, a replay stopped midway, failed batch tasks."""
    BAD_INPUT = 2
    """Bad arguments or input, nothing done: a malformed option, a missing or damaged file, numbers
    that are not finite, an output that exists without ``--overwrite``. argparse's own code."""
    DEVICE = 3
    """A device cannot be reached: a CAN interface, an arm without feedback, a camera, a CUDA device."""
    REFUSED = 4
    """A safety check refused the job before anything moved (``manisplat-replay``)."""
    INSUFFICIENT_DATA = 5
    """The data cannot determine the result: too few views, degenerate motion."""
    INTERRUPTED = 130
    """Ctrl-C or SIGTERM (128 + SIGINT, as shells report it); what was recorded is kept."""


def exit_status_help(meanings: dict[ExitCode, str]) -> str:
    """The "Exit status" block of a command's ``--help``: ``meanings`` says what each code it can end
    with means for that command, in the shared numbering. Lines are wrapped by the caller."""
    width = max(len(str(int(code))) for code in meanings)
    lines = ["Exit status (the same in every manisplat command: docs/exit-codes.md):"]
    for code in sorted(meanings):
        text = meanings[code].replace("\n", "\n" + " " * (width + 4))
        lines.append(f"  {int(code):<{width}}  {text}")
    return "\n".join(lines) + "\n"
