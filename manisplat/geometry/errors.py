"""Errors raised by geometry functions on inputs that have no meaningful answer."""


class GeometryError(ValueError):
    """Degenerate or invalid geometric input (zero quaternion, collinear points, ...)."""
