"""ROS-free drivers: the PiPER over CAN, the OAK camera, replay doubles, a simulated arm.

The recorder talks to the :class:`Arm` and :class:`Camera` interfaces (:mod:`.base`);
:mod:`.piper` (``PiperArm``, ``SimulatedPiper``), :mod:`.replay` (``CanLogPlayer``,
``EpisodeArm``, ``EpisodeCamera``) and :mod:`.oak` (``OakCamera``, ``DepthaiReplayCamera``)
implement them.
"""

from manisplat.drivers.base import Arm, ArmHealth, Camera, CameraFrame, DriverError, JointState, SequenceTracker

__all__ = ["Arm", "ArmHealth", "Camera", "CameraFrame", "DriverError", "JointState", "SequenceTracker"]
