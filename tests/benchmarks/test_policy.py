"""The policy benchmark's own parts (benchmarks/policy): action chunks, temporal ensembling,
failure phases, the success interval, and a policy that learns from image positions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.policy.data import Demonstrations, Viewport
from benchmarks.policy.rollout import _Ensemble, executor, failed_phase, wilson_interval
from benchmarks.policy.train import Budget, image_input, random_shift, train


def _demos(images: torch.Tensor, actions: torch.Tensor, lengths: list[int]) -> Demonstrations:
    ends = torch.tensor(np.cumsum(lengths))
    episode = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    h, w = images.shape[-2:]
    return Demonstrations(images, torch.zeros(len(actions), 7), actions, episode, ends, [f"e{i}" for i in lengths],
                          Viewport(0, 0, h, w, (w, h)))


def test_chunks_stop_at_their_own_episodes_end():
    actions = torch.arange(7, dtype=torch.float32)[:, None].repeat(1, 7)  # frame i's action is i
    demos = _demos(torch.zeros(7, 3, 4, 4, dtype=torch.uint8), actions, [3, 4])
    chunks = demos.chunks(torch.tensor([1, 2, 3, 5]), 4)[..., 0]
    assert chunks.tolist() == [[1, 2, 2, 2], [2, 2, 2, 2], [3, 4, 5, 6], [5, 6, 6, 6]]


def test_temporal_ensembling_weights_the_oldest_prediction_most():
    ensemble = _Ensemble()
    first = ensemble.add(0, np.array([[0.0], [0.0], [0.0]]))
    second = ensemble.add(1, np.array([[1.0], [1.0], [1.0]]))  # step 1: the old 0.0 and the new 1.0
    assert first[0] == 0.0
    w = np.exp(-0.01)
    assert second[0] == pytest.approx(w / (1 + w)) and second[0] < 0.5


def test_open_loop_chunks_run_k_actions_of_each_chunk_then_ask_again():
    run = executor(3)
    chunks = {0: np.arange(16.0)[:, None], 3: 100 + np.arange(16.0)[:, None]}
    actions, asked = [], []
    for step in range(6):
        if run.wants(step):
            asked.append(step)
            actions.append(run.add(step, chunks[step])[0])
        else:
            actions.append(run.action(step)[0])
    assert asked == [0, 3]
    assert actions == [0.0, 1.0, 2.0, 100.0, 101.0, 102.0]
    assert executor(None).wants(5) and isinstance(executor(None), _Ensemble)
    with pytest.raises(ValueError, match="cannot run 3 steps"):
        executor(3).add(0, np.zeros((2, 7)))


def test_wilson_interval():
    assert wilson_interval(0, 50) == pytest.approx((0.0, 0.0713), abs=1e-4)
    assert wilson_interval(25, 50) == pytest.approx((0.3664, 0.6336), abs=1e-4)
    assert wilson_interval(50, 50)[1] == pytest.approx(1.0)


@pytest.mark.parametrize("result, touched, phase", [
    ({"success": True, "lifted_m": 0.1, "failed": []}, True, "success"),
    ({"success": False, "lifted_m": 0.0, "failed": ["not over the mat"]}, False, "reach"),
    ({"success": False, "lifted_m": 0.005, "failed": ["not over the mat"]}, True, "grasp"),
    ({"success": False, "lifted_m": 0.1, "failed": ["not over the mat"]}, True, "transfer"),
    ({"success": False, "lifted_m": 0.1, "failed": ["tilted"]}, True, "place"),
])
def test_failed_phase(result, touched, phase):
    assert failed_phase(result, touched) == phase


def test_random_shift_moves_whole_images_by_at_most_the_pad():
    image = torch.zeros(1, 3, 16, 16)
    image[..., 8, 8] = 1.0
    shifted = random_shift(image.repeat(64, 1, 1, 1), torch.Generator().manual_seed(0), pad=2)
    rows, cols = torch.nonzero(shifted[:, 0] == 1.0, as_tuple=True)[1:]
    assert len(rows) == 64 and (rows - 8).abs().max() <= 2 and (cols - 8).abs().max() <= 2
    assert len(set(zip(rows.tolist(), cols.tolist()))) > 5  # not the same shift every time


@pytest.mark.parametrize("image_transforms", [False, True])
def test_the_policy_learns_where_a_bright_spot_is(image_transforms):
    """With or without LeRobot's colour and sharpness jitter on the training images."""
    torch.manual_seed(0)
    n, h, w = 64, 24, 32
    xy = torch.rand(n, 2)
    images = torch.zeros(n, 3, h, w, dtype=torch.uint8)
    for i, (x, y) in enumerate(xy):
        r, c = int(y * (h - 6)) + 3, int(x * (w - 6)) + 3
        images[i, :, r - 2:r + 3, c - 2:c + 3] = 255
    actions = torch.cat([xy, torch.zeros(n, 5)], 1)  # the action says where the spot is
    demos = _demos(images, actions, [1] * n)
    policy = train(demos, Budget(steps=150, batch=16, chunk=2, lr=3e-3, image_transforms=image_transforms),
                   progress=False)
    with torch.no_grad():
        out = policy.normaliser.unaction(policy.model(image_input(images), policy.normaliser.state(demos.state)))
    error = (out[:, 0, :2] - xy).abs().mean()
    assert error < 0.08, error  # the mean of the targets would be off by 0.25


def test_the_workspace_viewport_holds_the_object_where_it_starts_and_ends(tmp_path):
    from manisplat.episode import Episode
    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.data import workspace_viewport

    episode = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)
    view = workspace_viewport(episode, 0.05, size=(64, 48))
    assert view.width * 48 == view.height * 64 and view.width >= 64
    assert 0 <= view.left and view.left + view.width <= 160 and 0 <= view.top and view.top + view.height <= 120
    ep = Episode.open(episode)
    box = [int(k) for k, name in ep.meta.labels.items() if name == "object/box"]
    for i in (0, len(ep) - 1):
        rows, cols = np.nonzero(np.isin(ep.mask(i), box))
        assert view.top <= rows.min() and rows.max() < view.top + view.height
        assert view.left <= cols.min() and cols.max() < view.left + view.width
    assert view.width < 160, "the whole image: no closer look at the workspace"
    assert view.view(ep.rgb(0)).shape == (48, 64, 3)


def test_rollouts_of_earlier_runs_are_found_by_seed_for_their_own_policy_only(tmp_path):
    """A longer evaluation reuses the rollouts an earlier, shorter one saved, seed by seed, and
    never those of another policy whose name begins the same way."""
    from benchmarks.policy.rollout import Rollout
    from benchmarks.policy.stages import ENV_TAG, _cached_rollouts

    def save(name: str, seeds: range, tag: str = ENV_TAG) -> None:
        runs = [Rollout(seed, {"success": True}, "success", True) for seed in seeds]
        np.savez(tmp_path / f"{name}_{seeds[0]}_{len(seeds)}_{tag}.npz", rollouts=np.array(runs, dtype=object))

    save("B50_3000_v1", range(1000, 1030))
    save("B50_3000_v1", range(1030, 1040))
    save("B50_3000_v1_other", range(1040, 1050))  # another viewport
    save("B50_3000_v1", range(1040, 1050), f"{ENV_TAG}_steps8")  # the same policy run another way
    found = _cached_rollouts(tmp_path, "B50_3000_v1", ENV_TAG, set(range(1000, 1050)))
    assert sorted(found) == list(range(1000, 1040))
    assert all(found[seed].seed == seed for seed in found)
    assert sorted(_cached_rollouts(tmp_path, "B50_3000_v1", ENV_TAG, {1005, 1031, 1045})) == [1005, 1031]
    assert sorted(_cached_rollouts(tmp_path, "B50_3000_v1", f"{ENV_TAG}_steps8", {1005, 1045})) == [1045]


@pytest.mark.parametrize("text, size", [("80x60", (80, 60)), ("160x120", (160, 120)), ("80", None), ("16x12", None),
                                        ("ax60", None)])
def test_the_policy_view_size_option(text, size):
    import argparse

    from benchmarks.bench_policy_sim import _size

    if size is None:
        with pytest.raises(argparse.ArgumentTypeError, match="WIDTHxHEIGHT"):
            _size(text)
    else:
        assert _size(text) == size


def test_another_augmentation_speed_gets_its_own_folders_and_policies(tmp_path):
    """B and D at --augment-speed 0.6 never reuse the demonstrations, policies or rollouts of the
    default speed (kept in the same work folder); A and C do."""
    import json

    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.stages import Stages

    source = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)
    made = {speed: Stages(source, tmp_path / "work", tmp_path / "python", tmp_path / "tools", (0.05, 0.05, 30.0),
                          (0.02, 0.02, 30.0), 10, augment_speed=speed) for speed in (1.0, 0.6)}
    for folder in ("augmented_2", "augmented_2_speed0.6"):  # as manisplat-augment left them
        for k in range(2):
            (tmp_path / "work" / folder / f"episode_{k:04d}").mkdir(parents=True)
            (tmp_path / "work" / folder / f"episode_{k:04d}" / "episode.json").write_text("{}")
        (tmp_path / "work" / folder / "augment_report.json").write_text(json.dumps(
            {"requested": 2, "drawn": 2, "valid": 2, "reasons": {}}))
    assert made[1.0].augmented(2)[0].parent.name == "augmented_2"
    assert made[0.6].augmented(2)[0].parent.name == "augmented_2_speed0.6"
    assert [made[1.0].key(c, 50) for c in "ABCD"] == ["A", "B50", "C50", "D50"]
    assert [made[0.6].key(c, 50) for c in "ABCD"] == ["A", "B50_speed0.6", "C50", "D50_speed0.6"]


def test_a_declared_symmetry_another_range_and_another_training_seed_get_their_own_names(tmp_path):
    """--symmetry and --augment-object-range change B's and D's demonstrations (their own folders
    and policies); --train-seed changes every condition's policy (trained with that seed) but no
    demonstrations."""
    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.stages import Stages

    source = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)

    def stages(**kw) -> Stages:
        return Stages(source, tmp_path / "work", tmp_path / "python", tmp_path / "tools", (0.05, 0.05, 30.0),
                      (0.02, 0.02, 30.0), 10, **kw)

    symmetric, seeded = stages(symmetry=("box=4",)), stages(train_seed=1)
    assert [symmetric.key(c, 50) for c in "ABCD"] == ["A", "B50_sym-box4", "C50", "D50_sym-box4"]
    wider, same = stages(augment_object_range=[0.1, 0.1, 55.0]), stages(augment_object_range=[0.05, 0.05, 30.0])
    assert [wider.key(c, 50) for c in "ABCD"] == ["A", "B50_range0.1x0.1x55", "C50", "D50_range0.1x0.1x55"]
    assert [same.key(c, 50) for c in "ABCD"] == ["A", "B50", "C50", "D50"]
    assert wider.viewport == same.viewport  # the policy sees the evaluation's workspace either way
    assert [seeded.key(c, 50) for c in "ABCD"] == ["A_trainseed1", "B50_trainseed1", "C50_trainseed1",
                                                   "D50_trainseed1"]
    assert seeded.budget_of(9000).seed == 1 and symmetric.budget_of(9000).seed == 0
    assert [seeded.key_over_seeds(c, 50) for c in "ABCD"] == [symmetric.key_over_seeds(c, 50).replace("_sym-box4", "")
                                                             for c in "ABCD"] == ["A", "B50", "C50", "D50"]


def test_another_start_range_sampling_and_state_noise_get_their_own_names(tmp_path):
    """--augment-start-range and --augment-sampling change B's and D's demonstrations (their own
    folders and policies); --state-noise changes every condition's policy (trained with it) but no
    demonstrations."""
    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.stages import Stages

    source = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)

    def stages(**kw) -> Stages:
        return Stages(source, tmp_path / "work", tmp_path / "python", tmp_path / "tools", (0.05, 0.05, 30.0),
                      (0.02, 0.02, 30.0), 10, **kw)

    started, noisy = stages(augment_start_range=10.0), stages(state_noise=0.1)
    assert [started.key(c, 50) for c in "ABCD"] == ["A", "B50_start10", "C50", "D50_start10"]
    even = stages(augment_sampling="even", augment_start_range=10.0)
    assert [even.key(c, 50) for c in "ABCD"] == ["A", "B50_start10_even", "C50", "D50_start10_even"]
    assert [noisy.key(c, 50) for c in "ABCD"] == ["A_statenoise0.1", "B50_statenoise0.1", "C50_statenoise0.1",
                                                  "D50_statenoise0.1"]
    assert noisy.budget_of(9000).state_noise == 0.1 and started.budget_of(9000).state_noise == 0.0
    open_loop = stages(action_steps=8)  # the same policies, run otherwise: rollouts of their own
    assert [open_loop.key(c, 50) for c in "ABCD"] == ["A", "B50", "C50", "D50"]
    assert (open_loop.rollout_tag, started.rollout_tag) == ("linear_stop_steps8", "linear_stop")


def test_another_object_position_rate_gets_its_own_twin_trained_at_that_rate(tmp_path):
    """--object-position-rate changes the twin, so B's and D's demonstrations, policies and rollouts
    (their own names); the twin is reconstructed with that rate (its metrics.json says so)."""
    import json

    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.policy.stages import Stages

    source = write_sample_episode(tmp_path / "sample", frames=8, width=80, height=60)

    def stages(**kw) -> Stages:
        return Stages(source, tmp_path / "work", tmp_path / "python", tmp_path / "tools", (0.05, 0.05, 30.0),
                      (0.02, 0.02, 30.0), 4, **kw)

    slower, default = stages(object_position_rate=0.5), stages()
    assert [slower.key(c, 50) for c in "ABCD"] == ["A", "B50_objrate0.5", "C50", "D50_objrate0.5"]
    assert [default.key(c, 50) for c in "ABCD"] == ["A", "B50", "C50", "D50"]
    twin = slower.twin()
    assert twin.name == "twin_objrate0.5"
    assert json.loads((twin / "metrics.json").read_text())["object_position_rate"] == 0.5


def test_the_chunk_length_the_options_allow_is_the_policys():
    from benchmarks.bench_policy_sim import CHUNK, _parser

    assert CHUNK == Budget().chunk
    assert _parser().parse_args(["--n-action-steps", "8"]).n_action_steps == 8
    for bad in ("0", "17", "2.5"):
        with pytest.raises(SystemExit):
            _parser().parse_args(["--n-action-steps", bad])


def test_the_benchmarks_augmentation_is_the_documented_recipe():
    """B's default --augment-object-range, --augment-start-range and --augment-sampling are the ones
    docs/training-policies.md tells users to pass to manisplat-augment."""
    import re
    import shlex

    from benchmarks.bench_policy_sim import _parser

    recipe = (Path(__file__).parents[2] / "docs" / "training-policies.md").read_text()
    line = next(line for line in recipe.splitlines() if line.startswith("manisplat-augment "))
    words = shlex.split(line)
    option = {words[i]: words[i + 1] for i in range(len(words) - 1) if re.fullmatch(r"--[a-z-]+", words[i])}
    defaults = _parser().parse_args([])
    assert [float(v) for v in option["--object-range"].split(",")] == list(defaults.augment_object_range)
    assert float(option["--start-range"]) == defaults.augment_start_range
    from manisplat.augment.cli import build_parser

    assert defaults.augment_sampling == option.get("--sampling", build_parser().get_default("sampling")) == "even"
    assert defaults.state_noise == 0.1 and defaults.train_seed == [0]


def test_training_seeds_are_parsed_and_totalled_per_condition():
    from benchmarks.bench_policy_sim import _parser, over_seeds

    assert _parser().parse_args(["--train-seed", "0,1"]).train_seed == [0, 1]
    for bad in ("", "0,0", "-1", "a"):
        with pytest.raises(SystemExit):
            _parser().parse_args(["--train-seed", bad])
    rows = [{"data": "C50", "train_seed": 0, "successes": 45, "rollouts": 50},
            {"data": "C50", "train_seed": 1, "successes": 46, "rollouts": 50},
            {"data": "B50", "train_seed": 0, "successes": 34, "rollouts": 50}]
    totals = {t["data"]: t for t in over_seeds(rows)}
    assert totals["C50"]["per_seed"] == [45, 46] and totals["C50"]["train_seeds"] == [0, 1]
    assert (totals["C50"]["successes"], totals["C50"]["rollouts"], totals["C50"]["success_rate"]) == (91, 100, 0.91)
    assert (totals["B50"]["successes"], totals["B50"]["rollouts"]) == (34, 50)


def test_state_noise_jitters_the_joints_only_and_none_leaves_the_state_as_it_is():
    from benchmarks.policy.train import add_state_noise

    state = torch.zeros(4000, 7)
    generator = torch.Generator().manual_seed(0)
    noisy = add_state_noise(state, 0.1, generator)
    assert torch.all(noisy[:, 6] == 0)
    assert abs(float(noisy[:, :6].std()) - 0.1) < 0.005 and abs(float(noisy[:, :6].mean())) < 0.005
    assert add_state_noise(state, 0.0, generator) is state


def _probe(n: int = 10, frames: int = 12):
    """Random probe demonstrations: n episodes of ``frames`` frames, 32 x 24 images."""
    from benchmarks.policy.data import Demonstrations, Viewport

    generator = torch.Generator().manual_seed(0)
    total = n * frames
    return Demonstrations(images=torch.randint(0, 255, (total, 3, 24, 32), generator=generator, dtype=torch.uint8),
                          state=torch.randn(total, 7, generator=generator), actions=torch.randn(total, 7, generator=generator),
                          episode=torch.arange(n).repeat_interleave(frames), ends=torch.arange(1, n + 1) * frames,
                          names=[f"episode_{i:04d}" for i in range(n)], viewport=Viewport(0, 0, 24, 32, (32, 24)))


@pytest.mark.parametrize("blind", ["image", "state"])
def test_reliance_shows_which_input_a_policy_follows(blind):
    """A policy whose head ignores the image does not move when the image is swapped but does when
    the state is, and the other way round: the measure can show either."""
    from benchmarks.policy.model import ChunkPolicy
    from benchmarks.policy.reliance import reliance
    from benchmarks.policy.train import Normaliser

    torch.manual_seed(0)
    model = ChunkPolicy(chunk=4).eval()
    with torch.no_grad():
        first = model.head[0].weight
        if blind == "image":
            first[:, :128] = 0.0
        else:
            first[:, 128:] = 0.0
    norm = Normaliser(torch.zeros(7), torch.ones(7), torch.zeros(7), torch.ones(7))
    rows = reliance(model, norm, _probe(), [0, 5])
    for row in rows:
        image, state = np.array(row["image_swapped_deg"]), np.array(row["state_swapped_deg"])
        assert (image == 0).all() and (state > 0.01).all() if blind == "image" else (state == 0).all() and (image > 0.01).all()
        assert (np.array(row["targets_differ_deg"]) > 0).all()


class _Adds(torch.nn.Module):
    def __init__(self, amount: float) -> None:
        super().__init__()
        self.amount = amount

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return images + self.amount


def test_each_training_image_goes_through_three_of_the_transforms():
    """LeRobot's max_num_transforms: three of the five per image, drawn per image."""
    from benchmarks.policy.train import jitter_images

    transforms = tuple(_Adds(2.0 ** k) for k in range(5))  # the sum names the subset
    images = torch.zeros(200, 3, 4, 4)
    out = jitter_images(images, torch.Generator().manual_seed(0), transforms)
    sums = out[:, 0, 0, 0].long()
    assert all(bin(int(s)).count("1") == 3 for s in sums)
    assert len(set(sums.tolist())) == 10  # every one of the C(5, 3) subsets occurs
    assert torch.all(images == 0), "the input is left as it was"


def test_lerobots_transforms_jitter_colour_and_sharpness_within_the_image_range():
    from benchmarks.policy.train import jitter_images, lerobot_image_transforms

    torch.manual_seed(0)
    images = torch.rand(16, 3, 24, 32)
    out = jitter_images(images, torch.Generator().manual_seed(0), lerobot_image_transforms())
    assert out.shape == images.shape and float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    changed = (out - images).abs().flatten(1).amax(1)
    assert bool((changed > 0.01).all()), "every image is jittered"


def test_image_transforms_get_their_own_policies(tmp_path):
    from manisplat.episode.synthetic import write_sample_episode

    from benchmarks.bench_policy_sim import _parser
    from benchmarks.policy.stages import Stages

    source = write_sample_episode(tmp_path / "sample", frames=8, width=160, height=120)
    jittered = Stages(source, tmp_path / "work", tmp_path / "python", tmp_path / "tools", (0.05, 0.05, 30.0),
                      (0.02, 0.02, 30.0), 10, state_noise=0.1, image_transforms=True)
    assert jittered.key("B", 50) == "B50_statenoise0.1_imagetransforms"
    assert jittered.budget_of(9000).image_transforms
    assert _parser().parse_args(["--image-transforms"]).image_transforms
    assert not _parser().parse_args([]).image_transforms
