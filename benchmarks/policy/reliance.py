"""Does a trained policy look at the image, or follow its own joints?

    python -m benchmarks.policy.reliance POLICY.pt [POLICY.pt ...] --probe DIR [--source EP]
        [--episodes 20] [--frames 0,6,10,14,18,22] [--out JSON]

On probe demonstrations (``--probe``: episode folders, e.g. the benchmark's ``oracle/`` ones), at
frame k of each, the policy's last action of its chunk (where it means the arm to be one chunk
later) is predicted three times: with the frame's own image and joint state, with the image of
another probe demonstration at the same frame (its object elsewhere) and the own state, and with
the own image and the other demonstration's state. If swapping the image barely moves the action
while swapping the state moves it as far as the two demonstrations' targets differ, the policy
reads its target off its joints: a misjudgement made while the arm was still is never corrected
by what the camera shows. Reported per frame: the mean absolute change (deg) of joints 1, 4 and
6 for each swap, and how far the two demonstrations' own targets differ.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch and the policy load in the functions: --help answers at once
    from benchmarks.policy.data import Demonstrations
    from benchmarks.policy.model import ChunkPolicy
    from benchmarks.policy.train import Normaliser

JOINTS = (0, 3, 5)  # joints 1, 4 and 6: the arm's heading and the wrist's turn
PARTNER_SHIFT = 7  # demonstration i is paired with demonstration i - 7 (mod n): an object elsewhere


def reliance(model: ChunkPolicy, norm: Normaliser, demos: Demonstrations, frames: list[int]) -> list[dict]:
    """Per frame k: how far (deg, mean over demonstrations, joints 1/4/6) the chunk's last action
    moves when the image or the state is another demonstration's, against how far the two
    demonstrations' own targets differ."""
    import numpy as np
    import torch

    from benchmarks.policy.train import image_input

    starts = torch.cat([torch.zeros(1, dtype=torch.long), demos.ends[:-1]])
    partner = torch.roll(torch.arange(len(starts)), PARTNER_SHIFT)

    def last_action(img: torch.Tensor, st: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return norm.unaction(model(img, st))[:, -1, :6].double()

    def moved(other: torch.Tensor, base: torch.Tensor) -> list[float]:
        return [round(float(v), 2) for v in np.degrees((other - base).abs().mean(0).numpy())[list(JOINTS)]]

    rows = []
    for k in frames:
        index = torch.minimum(starts + k, demos.ends - 1)
        images, state = image_input(demos.images[index]), norm.state(demos.state[index])
        own = last_action(images, state)
        target = demos.actions[torch.minimum(index + model.chunk - 1, demos.ends - 1)][:, :6].double()
        rows.append({"frame": k, "image_swapped_deg": moved(last_action(images[partner], state), own),
                     "state_swapped_deg": moved(last_action(images, state[partner]), own),
                     "targets_differ_deg": moved(target[partner], target),
                     "error_to_target_deg": moved(own, target)})
    return rows


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.policy.reliance", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("policies", type=Path, nargs="+", help="policies saved by policy_sim (WORK/policies/*.pt)")
    p.add_argument("--probe", type=Path, required=True, help="a folder of probe episodes (searched for episode_*)")
    p.add_argument("--source", type=Path, help="the benchmark's source episode, for the policy's view "
                                               "(default shared/data/sim_pick_place_small)")
    p.add_argument("--episodes", type=int, default=20, help="probe demonstrations used (default 20)")
    p.add_argument("--frames", default="0,6,10,14,18,22", help="frames probed (default 0,6,10,14,18,22)")
    p.add_argument("--out", type=Path, help="write the JSON here too")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    import torch

    from benchmarks._harness import shared_dir
    from benchmarks.bench_policy_sim import OBJECT_RANGE
    from benchmarks.policy.data import episode_folders, load_demonstrations, workspace_viewport
    from benchmarks.policy.train import Budget, load_saved

    source = args.source or shared_dir() / "data" / "sim_pick_place_small"
    folders = sorted(p for p in args.probe.rglob("episode_*") if (p / "episode.json").exists())
    folders = folders[: args.episodes] if folders else episode_folders(args.probe)
    if len(folders) <= PARTNER_SHIFT:
        raise SystemExit(f"--probe {args.probe}: {len(folders)} episodes; more than {PARTNER_SHIFT} are needed")
    frames = [int(f) for f in args.frames.split(",")]
    torch.set_num_threads(1)
    demos = load_demonstrations(folders, workspace_viewport(source, max(OBJECT_RANGE[:2])))
    result = {"command": "python -m benchmarks.policy.reliance " + " ".join(argv if argv is not None else sys.argv[1:]),
              "probe": [f.name for f in folders], "joints": [j + 1 for j in JOINTS], "policies": {}}
    for path in args.policies:
        model, norm, _ = load_saved(path, Budget().chunk)
        rows = reliance(model, norm, demos, frames)
        result["policies"][path.stem] = rows
        print(path.stem)
        for r in rows:
            print(f"  frame {r['frame']:2d}: image swapped {r['image_swapped_deg']}, state swapped "
                  f"{r['state_swapped_deg']}, targets differ {r['targets_differ_deg']} (deg, joints 1/4/6)")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
