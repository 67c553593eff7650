"""Fixtures of the driver tests: a simulated PiPER and a PiperArm on a private virtual bus."""

from __future__ import annotations

import uuid
from typing import Iterator

import can
import pytest

from manisplat.drivers.piper import PiperArm, SimulatedPiper


@pytest.fixture
def channel() -> str:
    """A fresh virtual channel; its name ends in digits, which a BLF log cannot take as a channel
    number (the PiperArm tee must cope)."""
    return f"test-{uuid.uuid4().hex}-4294967296"


@pytest.fixture
def sim_bus(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    yield bus
    bus.shutdown()


@pytest.fixture
def host_bus(channel: str) -> Iterator[can.BusABC]:
    """A plain bus on the channel, standing for any other host (e.g. the vendor SDK)."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


@pytest.fixture
def sim(sim_bus: can.BusABC) -> Iterator[SimulatedPiper]:
    sim = SimulatedPiper(sim_bus)
    yield sim
    sim.stop()


@pytest.fixture
def arm_on_sim(channel: str, sim: SimulatedPiper) -> Iterator[tuple[PiperArm, SimulatedPiper]]:
    """A running simulator and a PiperArm on the same virtual channel."""
    arm = PiperArm(can.Bus(interface="virtual", channel=channel), own_bus=True)
    sim.start()
    try:
        arm.wait_for_joint_state(timeout=5.0)
        yield arm, sim
    finally:
        arm.close()
        sim.stop()
