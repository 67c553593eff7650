"""Vectorised decoding of whole CAN logs: numpy over all frames at once, same results as
:func:`~.protocol.decode` frame by frame.

    >>> frames = CanArrays.read("run.blf")                # any python-can log, by suffix
    >>> log = decode_arrays(frames)
    >>> log.counts()                                      # valid / invalid / unknown / undocumented
    >>> t, q, rows = log.joint_samples()                  # (S,), (S, 6) rad, rows of the 0x2A5s
    >>> log.tables["DriverHighSpeed"]["current"]          # (M,) A, one column per dataclass field

Every frame class gets a table: a dict of (M,) columns named like its dataclass fields (enums as
their raw int, ``None`` values as NaN, :class:`CollisionReply` levels as (M, 6), firmware data as
(M, 8) bytes with a ``length`` column), plus ``row`` (index into the log) and ``t``. The validity
rules are the scalar decoder's (tests compare the two frame by frame).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import can
import numpy as np

from manisplat.drivers.piper import protocol as P
from manisplat.drivers.piper.assembler import DEFAULT_WINDOW_S, assemble_joint_samples
from manisplat.drivers.piper.wire import MDEG, UM

FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR = 1, 2, 4
VALID, INVALID, UNKNOWN, UNDOCUMENTED = 0, 1, 2, 3
STATUS_NAMES = ("valid", "invalid", "unknown", "undocumented")

_NP_CODES = {"b": "i1", "B": "u1", "h": ">i2", "H": ">u2", "i": ">i4", "I": ">u4"}
_LUT = np.full(2048, -1, dtype=np.int16)
for _k, _cls in enumerate(P.FRAME_CLASSES):
    _LUT[list(_cls.ids())] = _k
_UNDOC = np.zeros(2048, dtype=bool)
_UNDOC[list(P.UNDOCUMENTED_IDS)] = True


@dataclass(frozen=True)
class CanArrays:
    """N CAN frames as arrays.

    Attributes:
        t: (N,) float64 timestamps, s.
        can_id: (N,) int64 arbitration IDs.
        length: (N,) int16 payload lengths in bytes (may exceed 8 for CAN FD frames).
        data: (N, 8) uint8 payloads, zero padded (bytes after the 8th dropped).
        flags: (N,) uint8 bits FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR.
    """

    t: np.ndarray
    can_id: np.ndarray
    length: np.ndarray
    data: np.ndarray
    flags: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def from_messages(cls, messages: Iterable[can.Message]) -> CanArrays:
        """Arrays of python-can messages."""
        t, ids, lengths, flags, payload = [], [], [], [], bytearray()
        for m in messages:
            t.append(m.timestamp)
            ids.append(m.arbitration_id)
            d = bytes(m.data)
            lengths.append(len(d))
            payload += d[:8].ljust(8, b"\0")
            flags.append(FLAG_EXTENDED * m.is_extended_id | FLAG_REMOTE * m.is_remote_frame
                         | FLAG_ERROR * m.is_error_frame)
        n = len(t)
        return cls(np.asarray(t, dtype=np.float64).reshape(n), np.asarray(ids, dtype=np.int64).reshape(n),
                   np.asarray(lengths, dtype=np.int16).reshape(n),
                   np.frombuffer(bytes(payload), dtype=np.uint8).reshape(n, 8).copy(),
                   np.asarray(flags, dtype=np.uint8).reshape(n))

    @classmethod
    def read(cls, path: str | Path) -> CanArrays:
        """Read a python-can log (format by suffix, :class:`can.LogReader`)."""
        with can.LogReader(path) as reader:
            return cls.from_messages(reader)

    def messages(self) -> Iterator[can.Message]:
        """The frames back as python-can messages (a payload longer than 8 bytes comes back as
        CAN FD, zero after its 8th byte: such frames are invalid for the PiPER anyway)."""
        for i in range(len(self)):
            f = int(self.flags[i])
            n = int(self.length[i])
            yield can.Message(timestamp=float(self.t[i]), arbitration_id=int(self.can_id[i]),
                              data=bytes(self.data[i, :n]).ljust(n, b"\0"), is_extended_id=bool(f & FLAG_EXTENDED),
                              is_remote_frame=bool(f & FLAG_REMOTE), is_error_frame=bool(f & FLAG_ERROR),
                              is_fd=n > 8, dlc=n, check=False)

    def slice(self, start: int, stop: int) -> CanArrays:
        return CanArrays(self.t[start:stop], self.can_id[start:stop], self.length[start:stop],
                         self.data[start:stop], self.flags[start:stop])


@dataclass(frozen=True)
class DecodedLog:
    """The decoded frames of a log (see the module docstring).

    Attributes:
        status: (N,) int8 VALID, INVALID, UNKNOWN or UNDOCUMENTED per frame.
        cls_index: (N,) int16 index into ``protocol.FRAME_CLASSES`` (-1 for unknown IDs).
        tables: class name -> column name -> (M,) array, valid frames only.
    """

    status: np.ndarray
    cls_index: np.ndarray
    tables: dict[str, dict[str, np.ndarray]]

    def counts(self) -> dict[str, int]:
        """Number of valid, invalid, unknown and undocumented frames."""
        c = np.bincount(self.status, minlength=4)
        return {name: int(c[i]) for i, name in enumerate(STATUS_NAMES)}

    def joint_samples(self, window_s: float = DEFAULT_WINDOW_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t (S,), q (S, 6) rad, row (S,))``: complete joint samples by the cycle rule of
        :mod:`.assembler`; ``row`` is the log row of each sample's 0x2A5 frame."""
        j = self.tables.get("JointFeedback")
        if j is None or len(j["row"]) == 0:
            return np.zeros(0), np.zeros((0, 6)), np.zeros(0, dtype=np.int64)
        t, q, first = assemble_joint_samples(j["pair"], np.stack([j["q_a"], j["q_b"]], axis=1), j["t"], window_s)
        return t, q, j["row"][first]


def decode_arrays(frames: CanArrays, workers: int = 1) -> DecodedLog:
    """Decode every frame of ``frames``; ``workers`` > 1 splits the rows over that many threads
    (numpy releases the GIL in most of the work)."""
    n = len(frames)
    if workers <= 1 or n < 2 * workers:
        return _decode(frames, 0)
    bounds = np.linspace(0, n, workers + 1).astype(int)
    with ThreadPoolExecutor(workers) as pool:
        parts = list(pool.map(lambda k: _decode(frames.slice(bounds[k], bounds[k + 1]), int(bounds[k])),
                              range(workers)))
    tables: dict[str, dict[str, np.ndarray]] = {}
    for name in {name for part in parts for name in part.tables}:
        present = [part.tables[name] for part in parts if name in part.tables]
        tables[name] = {col: np.concatenate([t[col] for t in present]) for col in present[0]}
    return DecodedLog(np.concatenate([p.status for p in parts]), np.concatenate([p.cls_index for p in parts]), tables)


def _decode(frames: CanArrays, offset: int) -> DecodedLog:
    ids, flags, length = frames.can_id, frames.flags, frames.length.astype(np.int64)
    n = len(ids)
    small = (ids >= 0) & (ids < 2048)
    safe = np.where(small, ids, 0)
    ci = np.where(small, _LUT[safe], -1).astype(np.int16)
    error = (flags & FLAG_ERROR) != 0
    plain = (flags & (FLAG_EXTENDED | FLAG_REMOTE)) == 0
    status = np.full(n, UNKNOWN, dtype=np.int8)
    status[small & _UNDOC[safe] & plain & (length <= 8)] = UNDOCUMENTED
    known = ci >= 0
    status[known] = INVALID
    status[error] = INVALID
    candidate = known & ~error & plain & (length <= 8)
    tables: dict[str, dict[str, np.ndarray]] = {}
    for k, cls in enumerate(P.FRAME_CLASSES):
        rows = np.flatnonzero(candidate & (ci == k) & (length >= cls.SIZE))
        if rows.size == 0:
            continue
        data = np.ascontiguousarray(frames.data[rows])
        ok, columns = _decode_class(cls, ids[rows], data, length[rows])
        rows = rows[ok]
        status[rows] = VALID
        table = {"row": rows + offset, "t": frames.t[rows]}
        table.update({name: col[ok] for name, col in columns.items()})
        tables[cls.__name__] = table
    return DecodedLog(status, ci, tables)


def _decode_class(cls: type, ids: np.ndarray, data: np.ndarray,
                  length: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``(ok (M,), columns)`` for M frames of one class; ``data`` (M, 8) uint8."""
    m = len(ids)
    ok = np.ones(m, dtype=bool)
    if cls is P.FirmwareData:
        return ok, {"data": data, "length": length}
    if cls is P.JointMitCtrl:
        return _decode_mit(ids, data)
    cols: dict[str, np.ndarray] = {}
    if cls.INDEX is not None:
        name, first, _ = cls.INDEX
        cols[name] = ids - cls.BASE_ID + first
    offsets, formats = [], []
    pos = 0
    for f in cls.FIELDS:
        offsets.append(pos)
        formats.append(_NP_CODES[f.code])
        pos += np.dtype(_NP_CODES[f.code]).itemsize
    dtype = np.dtype({"names": [f.name for f in cls.FIELDS], "formats": formats, "offsets": offsets, "itemsize": 8})
    packed = data.view(dtype).reshape(m)
    for f in cls.FIELDS:
        raw = packed[f.name].astype(np.int64)
        is_none = raw == f.none_raw if f.none_raw is not None else np.zeros(m, dtype=bool)
        if f.flag is not None:
            ok &= np.isin(raw, f.flag) | is_none
            cols[f.name] = raw == f.flag[1]
            continue
        if f.domain is not None:
            ok &= np.isin(raw, np.fromiter(f.domain, dtype=np.int64)) | is_none
        if f.scale is not None:
            value = raw / f.scale[0] * f.scale[1]
            value[is_none] = np.nan
            cols[f.name] = value
        else:
            cols[f.name] = raw
    if cls in (P.EndPoseFeedback, P.EndPoseCtrl):  # per-part units: 0.001 mm or 0.001 deg
        part = cols["part"]
        for name, which in (("a", 0), ("b", 1)):
            raw = packed[name].astype(np.int64)
            cols[name] = np.where(_POSE_ANGLE[part, which], raw / MDEG[0] * MDEG[1], raw / UM[0] * UM[1])
    if cls in (P.CollisionReply, P.CollisionConfig):
        cols["levels"] = np.stack([cols.pop(f"level{i}") for i in range(1, 7)], axis=1)
    return ok, cols


_POSE_ANGLE = np.array([[False, False], [False, True], [True, True]])


def _decode_mit(ids: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    d = d.astype(np.int64)
    crc = d[:, 0] ^ d[:, 1] ^ d[:, 2] ^ d[:, 3] ^ d[:, 4] ^ d[:, 5] ^ d[:, 6]
    ok = (crc & 0xF) == (d[:, 7] & 0xF)
    raw = {"position": d[:, 0] << 8 | d[:, 1], "velocity": d[:, 2] << 4 | d[:, 3] >> 4,
           "kp": (d[:, 3] & 0xF) << 8 | d[:, 4], "kd": d[:, 5] << 4 | d[:, 6] >> 4,
           "torque": (d[:, 6] & 0xF) << 4 | d[:, 7] >> 4}
    cols: dict[str, np.ndarray] = {"motor": ids - 0x159}
    for name, r in raw.items():
        lo, hi, bits = P.MIT_RANGES[name]
        cols[name] = lo + r * (hi - lo) / ((1 << bits) - 1)
    return ok, cols
