"""manisplat-record: synchronised, crash-safe recording of camera frames and joint states."""
