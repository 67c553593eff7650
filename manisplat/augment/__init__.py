"""Demonstration augmentation (``manisplat-augment``): new object poses, skills moved with their
objects, motions re-planned collision-free and timed, validated, rendered from the twin, written
as episodes.

    >>> from manisplat.twin import Twin
    >>> from manisplat.augment import AugmentConfig, augment_trajectory, sample_targets, write_demonstration
    >>> twin = Twin.load("demo_twin")
    >>> targets = sample_targets(twin, np.random.default_rng(0))
    >>> traj = augment_trajectory(twin, targets, AugmentConfig())   # raises Rejected(reason)
    >>> write_demonstration(twin, traj, Path("aug/episode_0000"), seed=0)
"""

from manisplat._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "trajectory": ("AugmentConfig", "NewTrajectory", "ObjectTarget", "Rejected", "augment_trajectory",
                   "sample_targets"),
    "writer": ("augmentation_record", "write_demonstration"),
})
