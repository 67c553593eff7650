"""Closed-loop evaluation: the policy drives simulated environments from given start seeds.

Two ways to run a chunking policy: by default it is queried every step and, as in ACT, the actions
that the chunks predicted for the current step are averaged with weights exp(-0.01 i), the oldest
first (temporal ensembling); or it is queried every k steps and the first k actions of its chunk
run open loop (LeRobot's ``n_action_steps``; diffusion policy runs 8 of 16). Several environments
run side by side (each renders in its own process); the policy takes their observations as one
batch."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from benchmarks.policy.sim_env import SimEnv
from benchmarks.policy.train import TrainedPolicy, image_input

ENSEMBLE_DECAY = 0.01
LIFTED_M = 0.02  # the object counts as lifted above this


@dataclass
class Rollout:
    """One evaluation episode: its seed, the env's summary, the failed phase, a few policy views."""

    seed: int
    result: dict[str, Any]
    phase: str
    touched: bool
    frames: list[np.ndarray] = field(default_factory=list)


def failed_phase(result: dict[str, Any], touched: bool) -> str:
    """'success', or where it went wrong: 'reach' (never held the object), 'grasp' (held, not lifted),
    'transfer' (lifted, did not end over the mat), 'place' (over the mat, not left there properly)."""
    if result["success"]:
        return "success"
    if result["lifted_m"] < LIFTED_M:
        return "grasp" if touched else "reach"
    return "transfer" if "not over the mat" in result["failed"] else "place"


class _Ensemble:
    """Temporal ensembling of one episode: a chunk every step, per-step action buffers."""

    def __init__(self) -> None:
        self.pending: dict[int, list[np.ndarray]] = defaultdict(list)

    def wants(self, step: int) -> bool:
        return True

    def add(self, step: int, chunk: np.ndarray) -> np.ndarray:
        """Take the chunk predicted at ``step``; the action to run at ``step``."""
        for i, action in enumerate(chunk):
            self.pending[step + i].append(action)
        return self.action(step)

    def action(self, step: int) -> np.ndarray:
        actions = np.stack(self.pending.pop(step))
        weights = np.exp(-ENSEMBLE_DECAY * np.arange(len(actions)))
        return (weights[:, None] * actions).sum(0) / weights.sum()


class _ChunkSteps:
    """Open-loop chunks of one episode: a chunk every ``k`` steps, its first ``k`` actions run."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.plan: np.ndarray | None = None

    def wants(self, step: int) -> bool:
        return step % self.k == 0

    def add(self, step: int, chunk: np.ndarray) -> np.ndarray:
        if len(chunk) < self.k:
            raise ValueError(f"a chunk of {len(chunk)} actions cannot run {self.k} steps")
        self.plan = chunk[: self.k]
        return self.action(step)

    def action(self, step: int) -> np.ndarray:
        return self.plan[step % self.k]


def executor(action_steps: int | None) -> _Ensemble | _ChunkSteps:
    """None: temporal ensembling; k: the first k actions of every k-th step's chunk."""
    return _Ensemble() if action_steps is None else _ChunkSteps(action_steps)


@torch.no_grad()
def _act(policy: TrainedPolicy, observations: list[dict[str, Any]]) -> np.ndarray:
    """(E,) observations -> (E, chunk, 7) float64 actions."""
    images = torch.from_numpy(np.stack([policy.viewport.view(o["rgb"]) for o in observations])).permute(0, 3, 1, 2)
    state = torch.tensor(np.array([[*o["q"], o["gripper"]] for o in observations]), dtype=torch.float32)
    out = policy.model(image_input(images), policy.normaliser.state(state))
    return policy.normaliser.unaction(out).double().numpy()


def evaluate(policy: TrainedPolicy, envs: list[SimEnv], seeds: list[int], keep_frames: int = 0,
             frame_every: int = 8, progress: Any = None, action_steps: int | None = None) -> list[Rollout]:
    """Run one episode per seed, ``len(envs)`` at a time; the first ``keep_frames`` seeds keep their
    policy view every ``frame_every`` steps; ``action_steps`` as :func:`executor`."""
    results: list[Rollout] = []
    queue = list(seeds)
    while queue:
        batch, queue = queue[: len(envs)], queue[len(envs):]
        active = envs[: len(batch)]
        for env, seed in zip(active, batch):
            env.send("reset", seed)
        observations = [env.receive() for env in active]
        executors = [executor(action_steps) for _ in active]
        touched = [False] * len(active)
        keep = [seed in seeds[:keep_frames] for seed in batch]
        frames: list[list[np.ndarray]] = [[] for _ in active]
        running = list(range(len(active)))
        step = 0
        while running:
            asking = [i for i in running if executors[i].wants(step)]
            chunks = dict(zip(asking, _act(policy, [observations[i] for i in asking]))) if asking else {}
            for i in running:
                if keep[i] and step % frame_every == 0:
                    frames[i].append(policy.viewport.view(observations[i]["rgb"]))
                action = executors[i].add(step, chunks[i]) if i in chunks else executors[i].action(step)
                active[i].send("step", action)
            still = []
            for i in running:
                observations[i], done, info = active[i].receive()
                touched[i] |= all(info["finger_contact"])
                if not done:
                    still.append(i)
            running, step = still, step + 1
        for i, (env, seed) in enumerate(zip(active, batch)):
            result = env.call("evaluate")
            if keep[i]:
                frames[i].append(policy.viewport.view(observations[i]["rgb"]))
            results.append(Rollout(seed, result, failed_phase(result, touched[i]), touched[i], frames[i]))
            if progress is not None:
                progress(results[-1])
    return results


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))
