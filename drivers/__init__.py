"""ROS-free drivers: the PiPER over CAN, the OAK camera, replay doubles, a simulated arm.

The recorder talks to the :class:`Arm` and :class:`Camera` interfaces (:mod:`.base`);
:mod:`.piper` (``PiperArm``, ``SimulatedPiper``), :mod:`.replay` (``CanLogPlayer``,
``EpisodeArm``, ``EpisodeCamera``) and :mod:`.oak` (``OakCamera``, ``DepthaiReplayCamera``)
implement them. The names below load on first use (PEP 562), so importing the package (as every
command line does before parsing its arguments) costs nothing.
"""

from __future__ import annotations

from manisplat._lazy import lazy_exports

_EXPORTS = {
    "base": ("Arm", "ArmHealth", "Camera", "CameraFrame", "DriverError", "JointState", "SequenceTracker"),
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
