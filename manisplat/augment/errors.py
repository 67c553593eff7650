"""Why a sample is discarded."""

from __future__ import annotations


class Rejected(Exception):
    """A sample that cannot become a valid demonstration.

    Attributes:
        reason: a short key: "ik_unreachable", "ik_discontinuous", "collision", "object_collision",
            "planner_timeout", "timing", "limits", "skill_pose", "continuity".
        detail: one sentence saying where and why.
    """

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason, self.detail = reason, detail

    def __reduce__(self):  # picklable across worker processes
        return (Rejected, (self.reason, self.detail))
