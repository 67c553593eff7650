"""Shared test settings: deterministic hypothesis runs, so CI failures reproduce."""

from hypothesis import HealthCheck, settings

settings.register_profile(
    "manisplat",
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("manisplat")
