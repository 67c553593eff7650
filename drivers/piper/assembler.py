"""Joint samples from the three joint frames 0x2A5, 0x2A6, 0x2A7, never from two cycles.

The PiPER sends a joint vector as three frames per 5 ms cycle, with no cycle counter. The rule
(shared by the streaming :class:`JointAssembler` and the vectorised :func:`assemble_joint_samples`):

    A sample is three *consecutive* joint frames (other IDs may come between them) in the order
    0x2A5 -> 0x2A6 -> 0x2A7, with non-decreasing timestamps, the last at most ``window_s`` after
    the first. Anything else (a frame lost, repeated or reordered) drops the incomplete cycle.

``window_s`` (default 2.5 ms) is half the 5 ms cycle: the three frames of one cycle arrive within
about 0.5 ms of each other at 1 Mbit/s (1.1 ms with the whole 8-frame burst, a little more with
USB adapter batching), while halves of two cycles are >= 5 ms apart, so a lost frame can never
join two cycles. The sample's time is the receive time of its 0x2A5, the frame nearest the arm's
sampling instant.
"""

from __future__ import annotations

import numpy as np

DEFAULT_WINDOW_S = 0.0025


class JointAssembler:
    """Streaming assembly. Feed every valid joint frame in arrival order to :meth:`push`.

    Attributes:
        samples: complete samples emitted.
        discarded: joint frames thrown away as parts of incomplete cycles.
    """

    def __init__(self, window_s: float = DEFAULT_WINDOW_S) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s = float(window_s)
        self.samples = 0
        self.discarded = 0
        self._q = np.zeros(6)
        self._pending = 0  # joint frames of the current cycle held so far
        self._t_first = 0.0
        self._t_last = 0.0

    def push(self, pair: int, q_a: float, q_b: float, t: float) -> tuple[float, np.ndarray] | None:
        """Add joint frame ``pair`` (0, 1, 2 for 0x2A5..0x2A7) received at ``t`` (s).

        Returns ``(t_sample, q (6,) float64 rad)`` when it completes a cycle, else None.
        """
        if pair == 0:
            self.discarded += self._pending
            self._pending, self._t_first = 1, t
        elif (self._pending == pair and t >= self._t_last and t - self._t_first <= self.window_s):
            self._pending += 1
        else:
            self.discarded += self._pending + 1
            self._pending = 0
            return None
        self._t_last = t
        self._q[2 * pair] = q_a
        self._q[2 * pair + 1] = q_b
        if self._pending < 3:
            return None
        self._pending = 0
        self.samples += 1
        return self._t_first, self._q.copy()


def assemble_joint_samples(pair: np.ndarray, values: np.ndarray, t: np.ndarray,
                           window_s: float = DEFAULT_WINDOW_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised :class:`JointAssembler` over a log's valid joint frames, in arrival order.

    Args:
        pair: (M,) int 0, 1, 2 (0x2A5..0x2A7).
        values: (M, 2) float64 rad, the two angles of each frame.
        t: (M,) float64 receive times, s.

    Returns:
        ``(t_sample (S,), q (S, 6), first (S,))``: sample times, joint vectors (rad) and the index
        (into the M frames) of each sample's 0x2A5 frame. Identical to streaming the frames.
    """
    pair = np.asarray(pair)
    t = np.asarray(t, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64).reshape(-1, 2)
    m = len(pair)
    if m < 3:
        return np.zeros(0), np.zeros((0, 6)), np.zeros(0, dtype=np.int64)
    k = np.arange(m - 2)
    ok = ((pair[k] == 0) & (pair[k + 1] == 1) & (pair[k + 2] == 2)
          & (t[k + 1] >= t[k]) & (t[k + 2] >= t[k + 1]) & (t[k + 2] - t[k] <= window_s))
    first = np.flatnonzero(ok)
    q = np.concatenate([values[first], values[first + 1], values[first + 2]], axis=1)  # [S, 6]
    return t[first], q, first
