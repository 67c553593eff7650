"""The AgileX PiPER over CAN: protocol (pure encode/decode), PiperArm (bus I/O), SimulatedPiper."""
