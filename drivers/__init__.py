"""ROS-free drivers: the PiPER over CAN, the OAK camera, replay doubles, a simulated arm."""
