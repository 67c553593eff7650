"""manisplat-calibrate: camera-to-base (hand-eye), intrinsics and camera latency."""
