"""The AgileX PiPER over CAN: protocol (pure encode/decode), PiperArm (bus I/O), SimulatedPiper.

    >>> from manisplat.drivers.piper import PiperArm, SimulatedPiper, protocol
"""

from manisplat.drivers.piper import protocol
from manisplat.drivers.piper.arm import CommandError, PiperArm, PiperError
from manisplat.drivers.piper.assembler import JointAssembler, assemble_joint_samples
from manisplat.drivers.piper.feedback import BusStats, FeedbackTracker, IdStats, Received
from manisplat.drivers.piper.sim_model import PiperModel, SimConfig
from manisplat.drivers.piper.simulated import SimulatedPiper

__all__ = [
    "BusStats", "CommandError", "FeedbackTracker", "IdStats", "JointAssembler", "PiperArm", "PiperError",
    "PiperModel", "Received", "SimConfig", "SimulatedPiper", "assemble_joint_samples", "protocol",
]
