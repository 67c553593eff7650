"""Wire-level building blocks of the PiPER protocol: units, field descriptions, and the frame
base classes. :mod:`.frames` declares the frames with them; :mod:`.protocol` decodes and encodes.
"""

from __future__ import annotations

import math
import operator
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar

# Wire units as (divisor, factor): SI value = raw / divisor * factor (correctly rounded for the
# decimal units: 50000 um -> exactly 0.05 m), raw = round(value / factor * divisor).
Unit = tuple[float, float]
_RAD = math.pi / 180.0
MDEG: Unit = (1000.0, _RAD)  # 0.001 deg -> rad
DECIDEG: Unit = (10.0, _RAD)  # 0.1 deg -> rad
UM: Unit = (1e6, 1.0)  # 0.001 mm -> m
MILLI: Unit = (1000.0, 1.0)
CENTI: Unit = (100.0, 1.0)
DECI: Unit = (10.0, 1.0)
ONE: Unit = (1.0, 1.0)

#: piper_sdk's effort = current x coefficient (N*m per A) for joints 1-3 and 4-6
#: (``feedback/arm_feedback_high_spd.py``; firmware <= 1.8-2 reports J1-3 four times too low).
EFFORT_PER_AMP = (1.18125, 1.18125, 1.18125, 0.95844, 0.95844, 0.95844)


# ----------------------------------------------------------------------------------------------
# field descriptions

_RANGES = {"b": (-(1 << 7), (1 << 7) - 1), "B": (0, 0xFF), "h": (-(1 << 15), (1 << 15) - 1),
           "H": (0, 0xFFFF), "i": (-(1 << 31), (1 << 31) - 1), "I": (0, 0xFFFFFFFF)}


@dataclass(frozen=True)
class Field:
    """One wire field: its struct code, and how a raw integer maps to the Python value.

    Attributes:
        name: the dataclass field it fills.
        code: struct code (b B h H i I), big-endian.
        scale: ``(divisor, factor)``: value = raw / divisor * factor (float); None for integers.
        enum: IntEnum the raw value is decoded into when it is a member.
        domain: raw values a valid frame may carry (commands; None = any).
        none_raw: raw value meaning "not set" (0x7FFF on the limit commands) -> None.
        flag: (false_raw, true_raw): a boolean field; other raw values are invalid.
    """

    name: str
    code: str
    scale: Unit | None = None
    enum: type[IntEnum] | None = None
    domain: frozenset[int] | None = None
    none_raw: int | None = None
    flag: tuple[int, int] | None = None

    def to_value(self, raw: int) -> Any:
        """Python value of ``raw``; ValueError when it is outside the field's domain."""
        if self.none_raw is not None and raw == self.none_raw:
            return None
        if self.flag is not None:
            if raw == self.flag[1]:
                return True
            if raw == self.flag[0]:
                return False
            raise ValueError(f"{self.name}: 0x{raw:02X} is neither 0x{self.flag[0]:02X} nor 0x{self.flag[1]:02X}")
        if self.domain is not None and raw not in self.domain:
            raise ValueError(f"{self.name}: {raw} (0x{raw:X}) not in {sorted(self.domain)}")
        if self.scale is not None:
            return raw / self.scale[0] * self.scale[1]
        if self.enum is not None and raw in self.enum._value2member_map_:
            return self.enum(raw)
        return raw

    def to_raw(self, value: Any) -> int:
        """Raw integer of ``value``; ValueError naming the field when it does not fit."""
        if value is None:
            if self.none_raw is None:
                raise ValueError(f"{self.name}: None is not allowed")
            return self.none_raw
        if self.flag is not None:
            if not isinstance(value, (bool, int)) or value not in (0, 1):
                raise ValueError(f"{self.name}: expected a bool, got {value!r}")
            return self.flag[1] if value else self.flag[0]
        if self.scale is not None:
            try:
                x = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{self.name}: expected a number, got {value!r}") from None
            if not math.isfinite(x):
                raise ValueError(f"{self.name}: {x} is not finite")
            raw = round(x / self.scale[1] * self.scale[0])
        else:
            try:
                raw = operator.index(value)
            except TypeError:
                raise ValueError(f"{self.name}: expected an int, got {value!r}") from None
        lo, hi = _RANGES[self.code]
        if not lo <= raw <= hi:
            unit = f" (raw {raw})" if self.scale is not None else ""
            raise ValueError(f"{self.name}: {value!r}{unit} does not fit {self.code!r} [{lo}, {hi}]")
        if self.domain is not None and raw not in self.domain:
            raise ValueError(f"{self.name}: {raw} (0x{raw:X}) not in {sorted(self.domain)}")
        if self.none_raw is not None and raw == self.none_raw:
            raise ValueError(f"{self.name}: raw {raw} is reserved for 'not set' (pass None)")
        return raw



# ----------------------------------------------------------------------------------------------
# frame base classes


class Frame:
    """Base of every decoded frame. ``can_id`` and ``pack()`` give the wire form."""

    @property
    def can_id(self) -> int:
        raise NotImplementedError

    def pack(self) -> bytes:
        raise NotImplementedError


@dataclass(frozen=True)
class RawFrame(Frame):
    """A frame kept as its raw bytes (base of the frames that have no typed layout)."""

    id: int
    data: bytes

    @property
    def can_id(self) -> int:
        return self.id

    def pack(self) -> bytes:
        return bytes(self.data)


@dataclass(frozen=True)
class UnknownFrame(RawFrame):
    """A frame with an ID this protocol does not define (or a non-PiPER device on the bus)."""


@dataclass(frozen=True)
class InvalidFrame(RawFrame):
    """A frame with a known ID that does not fit its layout; ``reason`` says why."""

    reason: str


@dataclass(frozen=True)
class UndocumentedFrame(RawFrame):
    """A known ID whose layout the protocol tables do not give (0x121 light, 0x422 silent mode)."""


class LayoutFrame(Frame):
    """A frame described by a :class:`Field` list (most of the protocol).

    Class attributes (set by subclasses, not dataclass fields):
        BASE_ID: the family's first CAN ID.
        INDEX: ``(field name, first value, count)`` when the family spans ``count`` IDs and the
            ID gives a field (joint pair, motor number); None for a single ID.
        FIELDS: the wire fields, in byte order.
        COMMAND: True for host -> arm frames.
    """

    BASE_ID: ClassVar[int]
    INDEX: ClassVar[tuple[str, int, int] | None] = None
    FIELDS: ClassVar[tuple[Field, ...]]
    COMMAND: ClassVar[bool] = False
    FORMAT: ClassVar[struct.Struct]
    SIZE: ClassVar[int]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "FIELDS" in cls.__dict__:
            cls.FORMAT = struct.Struct(">" + "".join(f.code for f in cls.FIELDS))
            cls.SIZE = cls.FORMAT.size

    @classmethod
    def ids(cls) -> range:
        """The CAN IDs of this family."""
        return range(cls.BASE_ID, cls.BASE_ID + (cls.INDEX[2] if cls.INDEX else 1))

    def __post_init__(self) -> None:
        self.can_id  # noqa: B018  (validates the index)
        self.pack()

    @property
    def can_id(self) -> int:
        if self.INDEX is None:
            return self.BASE_ID
        name, first, count = self.INDEX
        value = getattr(self, name)
        if isinstance(value, bool) or not isinstance(value, int) or not first <= value < first + count:
            raise ValueError(f"{type(self).__name__}.{name}: {value!r} not in {first}..{first + count - 1}")
        return self.BASE_ID + value - first

    def pack(self) -> bytes:
        raw = [f.to_raw(getattr(self, f.name)) for f in self.FIELDS]
        return self.FORMAT.pack(*raw).ljust(8, b"\0")

    @classmethod
    def unpack(cls, can_id: int, data: bytes) -> Frame:
        """Decode ``data`` (len >= SIZE checked by the caller) of ``can_id`` in ``ids()``."""
        values: dict[str, Any] = {}
        if cls.INDEX is not None:
            values[cls.INDEX[0]] = can_id - cls.BASE_ID + cls.INDEX[1]
        try:
            for f, raw in zip(cls.FIELDS, cls.FORMAT.unpack_from(data)):
                values[f.name] = f.to_value(raw)
        except ValueError as exc:
            return InvalidFrame(can_id, bytes(data), f"{cls.__name__}: {exc}")
        frame = object.__new__(cls)  # fields are valid by construction: skip __post_init__
        frame.__dict__.update(values)
        return frame
