"""The policy benchmark's stages, each kept in a work folder and reused when already complete:
twin, augmented demonstrations, oracle demonstrations, simulator renders of the augmented motions,
then per condition a trained policy and its rollouts."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from benchmarks._simulator import SimJob, run_sim_jobs, sim_env
from benchmarks.policy.data import IMAGE_SIZE, Viewport, episode_folders, load_demonstrations, workspace_viewport
from benchmarks.policy.rollout import Rollout, evaluate, wilson_interval
from benchmarks.policy.sim_env import SimEnv
from benchmarks.policy.train import Budget, TrainedPolicy, load_saved, train


ENV_OPTIONS = {"control": "linear", "terminate_on_collision": True}
"""How the evaluation drives the simulated arm: targets ramped over each step with velocity
feed-forward, as the generator recorded every demonstration and as manisplat-replay streams them
(``"hold"``, a step target held, lags 0.15 s at the wrist: in an ad-hoc check the B policy that
grasps from the source's own start pose under ``"linear"`` missed under ``"hold"``); an arm that
touches the table, mat or mug has failed by the success criterion, so the episode ends there."""
ENV_TAG = "linear_stop"
TWIN_DEMO_SEED = 501  # the twin's extra demonstrations: after the oracle's seeds, before the evaluation's (1000-)


class Stages:
    """Makes (or finds in ``work``) each condition's demonstrations, policy and rollouts.

    Args:
        source: the gen_pick_place.py episode everything starts from.
        work: the folder that keeps every stage's output.
        simenv, tools: the simulator venv's python and shared/tools/sim.
        object_range, place_range: (x m, y m, yaw deg) half-ranges for augmentation and oracle.
        twin_iters: manisplat-reconstruct iterations.
        image_size: (width, height) of the policy's view of the workspace (None: ``data.IMAGE_SIZE``).
        augment_speed: manisplat-augment's --speed (1.0, its default, keeps the folder names of
            earlier runs; another speed gets its own folders, policies and rollouts).
        augment_profile: manisplat-augment's --profile ("time-optimal", its default, keeps the
            folder names of earlier runs; "smooth" gets its own).
        augment_object_range: (x m, y m, yaw deg) half-ranges of the augmented objects' starts
            (None: ``object_range``, the evaluation's; another gets its own folders).
        twin_episodes: demonstrations the twin is reconstructed from: the source, then
            ``gen_demos.py`` demonstrations of its scene (seeds from :data:`TWIN_DEMO_SEED`, full
            renders with depth and masks). Augmentation still starts from the source alone
            (``--sources``): only the twin's appearance changes. Other than 1, it gets its own
            folders, policies and rollouts.
        object_position_rate: manisplat-reconstruct's --object-position-rate for the twin (None:
            the product's default); a value gets its own twin, folders, policies and rollouts.
        augment_start_range: manisplat-augment's --start-range (deg): each augmented demonstration's
            arm starts that far from the source's on every joint; other than 0 gets its own folders.
        augment_sampling: manisplat-augment's --sampling ("random", its default, keeps the folder
            names of earlier runs; "even" gets its own folders, policies and rollouts).
        symmetry: manisplat-augment's --symmetry items ("box=4"): grasps on the face nearest the
            source's wrist; any gets its own folders, policies and rollouts.
        train_seed: the policy's training seed (initial weights, batches); other than 0, its
            policies and rollouts get their own names (the demonstrations are the same).
        state_noise: rad of Gaussian noise on the training frames' joint states
            (:func:`~benchmarks.policy.train.add_state_noise`); other than 0, its policies and
            rollouts get their own names.
        image_transforms: train every policy with LeRobot's image transforms
            (:func:`~benchmarks.policy.train.jitter_images`); on, its policies and rollouts get
            their own names.
        action_steps: how the policy runs (:func:`~benchmarks.policy.rollout.executor`): None,
            temporal ensembling; k, the first k actions of each chunk open loop (its rollouts get
            their own names; the policies are the same).
    """

    def __init__(self, source: Path, work: Path, simenv: Path, tools: Path, object_range: tuple[float, ...],
                 place_range: tuple[float, ...], twin_iters: int, image_size: tuple[int, int] | None = None,
                 augment_speed: float = 1.0, augment_profile: str = "time-optimal",
                 augment_object_range: tuple[float, ...] | None = None, twin_episodes: int = 1,
                 object_position_rate: float | None = None, symmetry: tuple[str, ...] = (), train_seed: int = 0,
                 state_noise: float = 0.0,
                 augment_start_range: float = 0.0, action_steps: int | None = None,
                 image_transforms: bool = False, augment_sampling: str = "random") -> None:
        self.source, self.work, self.simenv, self.tools = source, work, simenv, tools
        self.object_range, self.place_range, self.twin_iters = object_range, place_range, twin_iters
        self.data_report: dict[str, Any] = {}
        #: key -> [N, 3] (x m, y m, yaw rad) of its training demonstrations' object starts
        self.training_starts: dict[str, np.ndarray] = {}
        self.viewport: Viewport = workspace_viewport(source, max(object_range[:2]), image_size or IMAGE_SIZE)
        self.augment_speed = float(augment_speed)
        self.augment_profile = augment_profile
        self.augment_object_range = tuple(object_range if augment_object_range is None else augment_object_range)
        self.twin_episodes = int(twin_episodes)
        self.object_position_rate = object_position_rate
        #: the twin's folder suffix (and part of the variant tag) for another object position rate
        self.twin_tag = "" if object_position_rate is None else f"_objrate{object_position_rate:g}"
        #: B's and D's folders, policies and rollouts of another speed, twin or symmetry: "", "_speed0.6", "_twin5", ...
        self.variant_tag = ("" if self.augment_speed == 1.0 else f"_speed{self.augment_speed:g}") + \
            ("" if augment_profile == "time-optimal" else f"_{augment_profile}") + \
            ("" if self.augment_object_range == tuple(object_range) else
             "_range{:g}x{:g}x{:g}".format(*self.augment_object_range)) + \
            ("" if self.twin_episodes == 1 else f"_twin{self.twin_episodes}") + self.twin_tag + \
            "".join(f"_sym-{item.replace('=', '')}" for item in symmetry) + \
            (f"_start{augment_start_range:g}" if augment_start_range else "") + \
            ("" if augment_sampling == "random" else f"_{augment_sampling}")
        self.augment_sampling = augment_sampling
        self.augment_start_range = float(augment_start_range)
        self.symmetry = tuple(symmetry)
        self.train_seed = int(train_seed)
        self.state_noise = float(state_noise)
        self.image_transforms = bool(image_transforms)
        self.action_steps = action_steps
        #: the rollout files' tag: the environment's options and how the policy ran
        self.rollout_tag = ENV_TAG + ("" if action_steps is None else f"_steps{action_steps}")

    # ------------------------------------------------------------------ demonstrations
    def twin(self) -> Path:
        name = "twin" if self.twin_episodes == 1 else f"twin_{self.twin_episodes}_episodes"
        out = self.work / (name + self.twin_tag)
        if not (out / "twin.json").exists():
            from benchmarks._degraded import robot_of
            from manisplat.reconstruct.cli import main as reconstruct

            episodes = [self.source, *self._twin_demos(self.twin_episodes - 1)]
            _log(f"reconstructing the twin of {', '.join(e.name for e in episodes)} ({self.twin_iters} iterations)")
            start = time.perf_counter()
            rate = [] if self.object_position_rate is None else \
                ["--object-position-rate", str(self.object_position_rate)]
            if reconstruct([*map(str, episodes), "--out", str(out), "--iters", str(self.twin_iters), "-q",
                            "--robot", robot_of(self.source), "--overwrite", *rate]) != 0:
                raise RuntimeError("manisplat-reconstruct failed")
            self.data_report["twin_s"] = round(time.perf_counter() - start, 1)
        metrics = json.loads((out / "metrics.json").read_text())
        self.data_report["twin_held_out_psnr"] = metrics.get("psnr")
        return out

    def _twin_demos(self, n: int) -> list[Path]:
        """``n`` successful gen_demos.py demonstrations with depth and masks for the twin (seeds from
        :data:`TWIN_DEMO_SEED`: no oracle or evaluation start)."""
        if n == 0:
            return []
        root = self.work / "twin_demos"
        if not (root / "demos.json").exists():
            _log(f"gen_demos.py: {n + 2} seeds from {TWIN_DEMO_SEED} for the twin")
            self._sim("gen_demos.py", "--source", str(self.source), "--out", str(root), "--n", str(n + 2),
                      "--seed-start", str(TWIN_DEMO_SEED), "--object-range", *map(str, self._radians(self.object_range)),
                      "--place-range", *map(str, self._radians(self.place_range)), "--jobs", "2")
        made = [root / d["dir"] for d in json.loads((root / "demos.json").read_text())["demos"] if d["ok"]]
        if len(made) < n:
            raise RuntimeError(f"gen_demos.py made {len(made)} of the {n} demonstrations the twin needs ({root})")
        return made[:n]

    def augmented(self, n: int) -> list[Path]:
        """n demonstrations of manisplat-augment (seed 0), made once per n (and speed) and kept in
        ``augmented_<n><variant tag>``."""
        out = self.work / f"augmented_{n}{self.variant_tag}"
        if not (out / "augment_report.json").exists():
            from manisplat.augment.cli import main as augment

            twin = self.twin()
            _log(f"manisplat-augment: {n} demonstrations")
            start = time.perf_counter()
            augment([str(twin), "--n", str(n), "--out", str(out), "--workers", "2", "--seed", "0", "-q", "--overwrite",
                     "--speed", str(self.augment_speed), "--profile", self.augment_profile,
                     "--sources", self.source.name,
                     "--object-range", ",".join(map(str, self.augment_object_range)),
                     "--target-range", ",".join(map(str, self.place_range)),
                     "--start-range", str(self.augment_start_range), "--sampling", self.augment_sampling,
                     *(f"--symmetry={item}" for item in self.symmetry)])
            self.data_report[f"augment_{n}_s"] = round(time.perf_counter() - start, 1)
        report = json.loads((out / "augment_report.json").read_text())
        self.data_report[f"augment_{n}"] = {k: report[k] for k in ("requested", "drawn", "valid", "reasons")}
        folders = episode_folders(out)[:n]
        if len(folders) < n:
            raise RuntimeError(f"manisplat-augment wrote {len(folders)} of {n} demonstrations ({out})")
        return folders

    def fidelity(self, n: int) -> dict[str, Any]:
        """The twin's first frames of B's ``n`` demonstrations against the simulator's renders of
        the same starts (:mod:`benchmarks.policy.fidelity`; the simulator's object placed from the
        source's ground-truth start, read to score only), kept in ``fidelity_<n><variant tag>.json``."""
        from benchmarks.policy.fidelity import by_bin, object_crops, score_start, simulator_start, worst_first

        path = self.work / f"fidelity_{n}{self.variant_tag}.json"
        if not path.exists():
            folders = self.augmented(n)
            meta = json.loads((self.source / "episode.json").read_text())
            name, T0 = _source_start(self.source)
            labels = {v: int(k) for k, v in meta["labels"].items()}
            robot = [value for label, value in labels.items() if label.startswith("robot/")]
            object_label = labels[f"object/{name}"]
            yaw0 = float(np.arctan2(T0[1, 0], T0[0, 0]))
            _log(f"the twin's first frames of {n} augmented demonstrations against the simulator's")
            scores, crops = [], []
            with SimEnv(self.simenv, self.tools, self.source, mask=True) as env:
                for folder in folders:
                    x, y, yaw = simulator_start(folder, T0, name)
                    obs = env.call("reset", None, (x, y, yaw))
                    twin_rgb = cv2.cvtColor(cv2.imread(str(folder / "rgb" / "000000.png")), cv2.COLOR_BGR2RGB)
                    twin_mask = cv2.imread(str(folder / "masks" / "000000.png"), cv2.IMREAD_UNCHANGED)
                    turn = float(np.degrees((yaw - yaw0 + np.pi) % (2 * np.pi) - np.pi))
                    scores.append(score_start(folder.name, twin_rgb, twin_mask, obs["rgb"], obs["mask"],
                                              object_label, robot, turn, float(np.hypot(x, y))))
                    crops.append(object_crops(twin_rgb, obs["rgb"], obs["mask"] == object_label))
            worst_first(scores, crops, path.with_suffix(".png"))
            path.write_text(json.dumps({"object": name, "starts": [s.__dict__ for s in scores],
                                        "bins": by_bin(scores), "sheet": path.with_suffix(".png").name},
                                       indent=1) + "\n")
        return json.loads(path.read_text())

    def oracle(self, n: int) -> list[Path]:
        """n successful gen_demos.py demonstrations, seeds 1, 2, ... (failed seeds skipped)."""
        root = self.work / "oracle"
        start_seed = 1
        while True:
            made = self._oracle_made(root)
            if len(made) >= n:
                return made[:n]
            batch = root / f"seeds_{start_seed:04d}"
            want = n - len(made) + 2
            if not (batch / "demos.json").exists():
                _log(f"gen_demos.py: {want} seeds from {start_seed}")
                start = time.perf_counter()
                self._sim("gen_demos.py", "--source", str(self.source), "--out", str(batch), "--n", str(want),
                          "--seed-start", str(start_seed), "--object-range", *map(str, self._radians(self.object_range)),
                          "--place-range", *map(str, self._radians(self.place_range)), "--rgb-only", "--jobs", "2")
                self.data_report.setdefault("oracle_s", 0.0)
                self.data_report["oracle_s"] += round(time.perf_counter() - start, 1)
            start_seed = json.loads((batch / "demos.json").read_text())["summary"]["seeds"][1] + 1  # after its last

    def _oracle_made(self, root: Path) -> list[Path]:
        made, skipped = [], []
        for batch in sorted(root.glob("seeds_*")) if root.exists() else []:
            demos = json.loads((batch / "demos.json").read_text())["demos"] if (batch / "demos.json").exists() else []
            made += [batch / d["dir"] for d in demos if d["ok"]]
            skipped += [d["seed"] for d in demos if not d["ok"]]
        self.data_report["oracle_skipped_seeds"] = skipped
        return made

    def sim_rendered(self, augmented: list[Path]) -> list[Path]:
        """The augmented demonstrations executed in the simulator with contact physics; each gets the
        simulator's renders of its own motion as rgb/ (everything else linked from the original)."""
        renders, out = self.work / f"sim_render{self.variant_tag}", self.work / f"sim_rendered{self.variant_tag}"
        jobs = [SimJob("execute_episode.py", (str(path), "--parent", str(self.source), "--render", str(renders / path.name)),
                       renders / f"{path.name}.json") for path in augmented]
        if todo := sum(not job.report.exists() for job in jobs):
            _log(f"execute_episode.py --render: {todo} augmented demonstrations")
        run_sim_jobs(self.simenv, jobs, tools=self.tools)
        results, folders = [], []
        for path in augmented:
            results.append(json.loads((renders / f"{path.name}.json").read_text()))
            target = out / path.name
            if not target.exists():
                target.mkdir(parents=True)
                for item in path.iterdir():
                    (target / item.name).symlink_to(renders / path.name / "rgb" if item.name == "rgb" else item)
            folders.append(target)
        self.data_report[f"augmented_{len(augmented)}_in_physics"] = {
            "n": len(results), "success": sum(r["success"] for r in results),
            "success_clean": sum(r["success_clean"] for r in results),
            "final_pos_err_cm_max": max(r["final_pos_err_cm"] for r in results),
            "failures": {r["episode"]: {k: r[k] for k in ("final_pos_err_cm", "final_rot_err_deg", "upright",
                                                         "collisions")} for r in results if not r["success_clean"]}}
        return folders

    def folders(self, condition: str, n: int) -> list[Path]:
        if condition == "A":
            return [self.source]
        if condition == "B":
            return [self.source, *self.augmented(n)]
        if condition == "C":
            return self.oracle(n)
        return [self.source, *self.sim_rendered(self.augmented(n))]

    # ------------------------------------------------------------------ policies
    def budget_of(self, steps: int) -> Budget:
        return Budget(steps=steps, seed=self.train_seed, state_noise=self.state_noise,
                      image_transforms=self.image_transforms)

    def key(self, condition: str, n: int) -> str:
        """The name of a condition's policy and rollouts: A, C50, B50, B50_speed0.6, B50_twin5,
        C50_trainseed1, ..."""
        return self.key_over_seeds(condition, n) + (f"_trainseed{self.train_seed}" if self.train_seed else "")

    def key_over_seeds(self, condition: str, n: int) -> str:
        """The name its policies of every training seed share: :meth:`key` without the seed."""
        name = condition if condition == "A" else f"{condition}{n}" + (self.variant_tag if condition in "BD" else "")
        return name + (f"_statenoise{self.state_noise:g}" if self.state_noise else "") + \
            ("_imagetransforms" if self.image_transforms else "")

    def condition(self, condition: str, n: int, steps: int, seeds: list[int], envs: int
                  ) -> tuple[dict[str, Any], list[Rollout]]:
        """Train the policy on the condition's demonstrations and evaluate it from ``seeds``."""
        key = self.key(condition, n)
        folders = self.folders(condition, n)
        source_start = _source_start(self.source)
        self.training_starts[key] = np.array([_start_pose(f, source_start) for f in folders])
        budget = self.budget_of(steps)
        policy = self._policy(key, folders, budget)
        rollouts = self._rollouts(key, policy, seeds, envs)
        successes = sum(r.result["success"] for r in rollouts)
        phases = {p: sum(r.phase == p for r in rollouts) for p in ("reach", "grasp", "transfer", "place")}
        row = {"condition": key, "data": self.key_over_seeds(condition, n), "train_seed": self.train_seed,
               "demonstrations": len(folders), "frames": policy.frames,
               "successes": successes, "rollouts": len(rollouts), "success_rate": successes / len(rollouts),
               "ci95": wilson_interval(successes, len(rollouts)), "train_s": round(policy.seconds, 1),
               "train_loss_end": round(policy.final_loss, 4), "failed_in": phases,
               "action_steps": self.action_steps,
               "arm_hit_scene": sum(any(f.startswith("arm hit") for f in r.result["failed"]) for r in rollouts),
               "mean_steps": float(np.mean([r.result["steps"] for r in rollouts])),
               "coverage": self.coverage(key, rollouts)}
        return row, rollouts

    def coverage(self, key: str, rollouts: list[Rollout]) -> dict[str, Any]:
        """Success by each evaluation start's distance to the nearest of ``key``'s training starts
        (:mod:`benchmarks.policy.coverage`, in the evaluation's half-ranges)."""
        from benchmarks.policy.coverage import nearest_distances, success_by_distance

        x, y, yaw = self.object_range
        eval_starts = np.array([r.result["object_start"] for r in rollouts])
        distances = nearest_distances(eval_starts, self.training_starts[key], (x, y, np.radians(yaw)))
        return success_by_distance(distances, np.array([r.result["success"] for r in rollouts]))

    def _policy(self, key: str, folders: list[Path], budget: Budget) -> TrainedPolicy:
        path = self.work / "policies" / f"{key}_{budget.steps}_{self.viewport.tag}.pt"
        if path.exists():
            model, normaliser, saved = load_saved(path, budget.chunk)
            return TrainedPolicy(model, normaliser, budget, saved["seconds"], saved["loss"], saved["frames"],
                                 self.viewport)
        demos = load_demonstrations(folders, self.viewport)
        _log(f"training {key}: {len(folders)} demonstrations, {len(demos)} frames, {budget.steps} steps")
        policy = train(demos, budget)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"model": policy.model.state_dict(), "normaliser": policy.normaliser.__dict__,
                    "seconds": policy.seconds, "loss": policy.final_loss, "frames": len(demos)}, path)
        return policy

    def _rollouts(self, key: str, policy: TrainedPolicy, seeds: list[int], envs: int) -> list[Rollout]:
        """The policy's rollouts from ``seeds``: those of earlier runs of the same policy and
        environment taken from the work folder (by seed), the rest run and saved as one more file."""
        stem = f"{key}_{policy.budget.steps}_{policy.viewport.tag}"
        done = _cached_rollouts(self.work / "rollouts", stem, self.rollout_tag, set(seeds))
        missing = [seed for seed in seeds if seed not in done]
        if missing:
            _log(f"evaluating {key} on {len(missing)} start poses ({len(done)} from earlier runs)")
            torch.set_num_threads(1)  # the environments render on the other cores
            pool: list[SimEnv] = []
            try:
                pool += [SimEnv(self.simenv, self.tools, self.source, **ENV_OPTIONS) for _ in range(envs)]
                rollouts = evaluate(policy, pool, missing, keep_frames=2, progress=_print_rollout,
                                    action_steps=self.action_steps)
            finally:
                for env in pool:
                    env.close()
                torch.set_num_threads(max(1, os.cpu_count() or 1))
            path = self.work / "rollouts" / f"{stem}_{missing[0]}_{len(missing)}_{self.rollout_tag}.npz"
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, rollouts=np.array(rollouts, dtype=object))
            done.update((r.seed, r) for r in rollouts)
        return [done[seed] for seed in seeds]

    # ------------------------------------------------------------------ the simulator venv
    @staticmethod
    def _radians(ranges: tuple[float, ...]) -> tuple[float, ...]:
        return ranges[0], ranges[1], float(np.radians(ranges[2]))

    def _sim_process(self, script: str, *args: str) -> subprocess.Popen:
        return subprocess.Popen([str(self.simenv), script, *args], cwd=self.tools, env=sim_env(),
                                stdout=subprocess.DEVNULL, stderr=sys.stderr)

    def _sim(self, script: str, *args: str) -> None:
        if self._sim_process(script, *args).wait() != 0:
            raise RuntimeError(f"{script} failed")


def _cached_rollouts(folder: Path, stem: str, tag: str, seeds: set[int]) -> dict[int, Rollout]:
    """seed -> rollout of the files ``{stem}_{first seed}_{count}_{tag}.npz`` in ``folder``
    (one policy, one environment, one way of running it), for ``seeds``."""
    found: dict[int, Rollout] = {}
    for path in sorted(folder.glob(f"{stem}_*_*_{tag}.npz")):
        first, _, count = path.name[len(stem) + 1: -len(f"_{tag}.npz")].partition("_")
        if not (first.isdigit() and count.isdigit()):  # another policy whose key begins with this one's
            continue
        for rollout in np.load(path, allow_pickle=True)["rollouts"]:
            if rollout.seed in seeds:
                found[rollout.seed] = rollout
    return found


def _source_start(source: Path) -> tuple[str, np.ndarray]:
    """The source's manipulated object and its first-frame pose [4, 4] (base frame, gt.npz: the
    simulator's; read to score and to place the simulator's object only)."""
    name = json.loads((source / "episode.json").read_text())["objects"][0]
    return name, np.load(source / "gt.npz", allow_pickle=True)[f"T_base_{name}"][0]


def _start_pose(folder: Path, source_start: tuple[str, np.ndarray]) -> tuple[float, float, float]:
    """The object's start (x m, y m, yaw rad; the simulator's frame) of a training demonstration:
    an augmented one's first skill applied to the source's start (``source_start``:
    :func:`_source_start`; ``fidelity.simulator_start``), gen_demos' record, or the source's own."""
    name, T0 = source_start
    if (folder / "augmentation.json").exists():
        from benchmarks.policy.fidelity import simulator_start

        return simulator_start(folder, T0, name)
    demos = folder.parent / "demos.json"
    if demos.exists():
        record = next(d for d in json.loads(demos.read_text())["demos"] if d["dir"] == folder.name)
        return float(record["object_pose"][0]), float(record["object_pose"][1]), float(record["object_pose"][2])
    return float(T0[0, 3]), float(T0[1, 3]), float(np.arctan2(T0[1, 0], T0[0, 0]))


def _print_rollout(rollout: Rollout) -> None:
    print(f"    seed {rollout.seed}: {rollout.phase} ({rollout.result['steps']} steps)", flush=True)


def _log(text: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)
