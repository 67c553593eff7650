"""The twin is controllable: reconstruct the built-in sample, then render it in a state it never
saw, with joint 1 turned and the box moved (what augmentation builds on).

    python examples/twin_new_poses.py OUT_DIR [ITERS]

OUT_DIR must be new or empty; it gets the sample (episode/) and new_poses.png: the recorded frame |
the twin at that frame | the twin with joint 1 turned by 15 deg and the box moved 6 cm along the base's y.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from manisplat.episode.synthetic import write_sample_episode
from manisplat.output_folder import new_or_empty_folder
from manisplat.reconstruct.data import load_episode_data
from manisplat.reconstruct.pipeline import build
from manisplat.reconstruct.plan import make_plan
from manisplat.reconstruct.trainer import TrainConfig

FRAME = 4  # before the grasp: the box rests on the table
JOINT1_TURN = math.radians(15.0)
BOX_SHIFT = (0.0, 0.06, 0.0)  # m, base frame


def main(out_dir: str, iters: int = 1000, frames: int = 64, width: int = 160, height: int = 120) -> dict:
    """Returns the three images [H, W, 3] float in [0, 1] ("recorded", "twin", "new"), the box's
    pose before and after (``T_base_box``, ``T_base_box_new`` [4, 4]) and its rendered alpha [H, W]
    in the twin and in the new state (``box_alpha``, ``box_alpha_new``)."""
    out = new_or_empty_folder(out_dir)  # never written into an existing episode or earlier results
    episode = write_sample_episode(out / "episode", frames=frames, width=width, height=height)
    data = load_episode_data(episode)
    rec, _ = build(data, make_plan(data), TrainConfig(iters=iters))
    rec.train(progress=True)

    q = data.q[FRAME].clone()
    q[0] += JOINT1_TURN
    link_poses = data.robot.forward_kinematics(q, data.gripper[FRAME]).float()
    T_box = rec.object_poses(FRAME)["box"].detach()
    T_box_new = T_box.clone()
    T_box_new[:3, 3] += torch.tensor(BOX_SHIFT)
    box = 2 + rec.graph.object_names.index("box")  # its group in the rendered group alphas
    with torch.no_grad():
        twin, _, _, meta, _ = rec.render(FRAME)
        new, _, _, meta_new, _ = rec.render_state(link_poses, {"box": T_box_new})
    images = {"recorded": data.rgb[FRAME].float() / 255, "twin": twin.clamp(0, 1), "new": new.clamp(0, 1)}
    sheet = np.concatenate([(im.numpy() * 255).round().astype(np.uint8) for im in images.values()], axis=1)
    cv2.imwrite(str(out / "new_poses.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return {**images, "T_base_box": T_box.double(), "T_base_box_new": T_box_new.double(),
            "box_alpha": meta["group_alphas"][0, ..., box], "box_alpha_new": meta_new["group_alphas"][0, ..., box]}


if __name__ == "__main__":
    try:
        main(sys.argv[1], *(int(a) for a in sys.argv[2:3]))
    except ValueError as exc:  # a used OUT_DIR
        sys.exit(f"error: {exc}")
    print(f"wrote {Path(sys.argv[1]) / 'new_poses.png'}")
