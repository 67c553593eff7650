"""manisplat-reconstruct: the scene graph trained on one episode, with task-oriented alignment."""
