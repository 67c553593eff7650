"""From one recorded demonstration to a LeRobot dataset a policy trains on: reconstruct the twin,
write N new demonstrations over the start poses the policy must handle, export them with the
recording as one LeRobot v3.0 dataset, and print the command that trains LeRobot's ACT on it.

    python examples/augment_for_lerobot.py OUT_DIR [--episode EP] [--n 50] [--iters 1000]
        [--object-range 0.1,0.1,55] [--target-range 0.025,0.025,45] [--start-range 10] [--task TEXT]

Without --episode it uses the built-in sample. OUT_DIR must be new or empty; it gets twin/ (the
reconstruction), augmented/ (episode_0000 ...) and lerobot/ (the dataset). The choices behind the
defaults (how many demonstrations, which ranges, why the arm's start is scattered) are in
docs/training-policies.md.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from manisplat.augment.cli import main as augment
from manisplat.episode.cli import main as episode_cli
from manisplat.episode.synthetic import write_sample_episode
from manisplat.output_folder import new_or_empty_folder
from manisplat.reconstruct.cli import main as reconstruct


def main(out_dir: str, episode: str | None = None, n: int = 50, iters: int = 1000, object_range: str = "0.1,0.1,55",
         target_range: str = "0.025,0.025,45", start_range: float = 10.0,
         task: str = "pick up the object and place it on the mat") -> dict:
    out = new_or_empty_folder(out_dir)
    source = Path(episode) if episode else write_sample_episode(out / "sample")
    steps = [
        ("reconstruct", reconstruct, [str(source), "--out", str(out / "twin"), "--iters", str(iters)]),
        ("augment", augment, [str(out / "twin"), "--n", str(n), "--out", str(out / "augmented"),
                              "--object-range", object_range, "--target-range", target_range,
                              "--start-range", str(start_range)]),
    ]
    for name, command, args in steps:
        if command(args) != 0:
            raise RuntimeError(f"{name} failed (its message is above)")
    augmented = sorted(p for p in (out / "augmented").iterdir() if p.name.startswith("episode_"))
    dataset = out / "lerobot"
    if episode_cli(["export", str(source), *map(str, augmented), "--format", "lerobot", "--out", str(dataset),
                    "--task", task]) != 0:
        raise RuntimeError("export failed (its message is above)")
    train = ["lerobot-train", f"--dataset.repo_id=local/{dataset.parent.name}", f"--dataset.root={dataset}",
             "--policy.type=act", "--policy.device=cuda", "--policy.push_to_hub=false",
             f"--output_dir={out / 'act'}"]
    print(f"{len(augmented) + 1} demonstrations in {dataset}; train LeRobot's ACT on them with\n  "
          + " ".join(map(shlex.quote, train)))
    return {"dataset": dataset, "episodes": len(augmented) + 1, "train_command": train}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir")
    parser.add_argument("--episode", help="a recorded episode folder (default: the built-in sample)")
    parser.add_argument("--n", type=int, default=50, help="new demonstrations (default 50)")
    parser.add_argument("--iters", type=int, default=1000, help="reconstruction iterations (default 1000)")
    parser.add_argument("--object-range", default="0.1,0.1,55", help="X,Y m and YAW deg of the object's start")
    parser.add_argument("--target-range", default="0.025,0.025,45", help="X,Y m and YAW deg of the place pose")
    parser.add_argument("--start-range", type=float, default=10.0,
                        help="deg each joint of the arm's start is scattered by (default 10)")
    parser.add_argument("--task", default="pick up the object and place it on the mat")
    args = parser.parse_args()
    try:
        main(args.out_dir, args.episode, args.n, args.iters, args.object_range, args.target_range, args.start_range,
             args.task)
    except (ValueError, RuntimeError) as exc:
        sys.exit(f"error: {exc}")
