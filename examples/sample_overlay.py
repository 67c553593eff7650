"""First steps: make the built-in sample episode, read it back, and check the robot model
against the images by drawing the TCP (from forward kinematics) over every 8th frame.

    python examples/sample_overlay.py OUT_DIR

OUT_DIR must be new or empty; it gets the sample (episode/) and overlay.png (a contact sheet).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from manisplat.episode import Episode
from manisplat.episode.synthetic import write_sample_episode
from manisplat.output_folder import new_or_empty_folder
from manisplat.robot import load_robot


def main(out_dir: str) -> Path:
    out = new_or_empty_folder(out_dir)  # never written into an existing episode or earlier results
    episode = Episode.open(write_sample_episode(out / "episode"))
    robot = load_robot(episode.meta.robot.description, base_dir=episode.path)
    T_base_tcp = robot.tcp_pose(episode.frames.q).numpy()  # [T, 4, 4]
    T_cam_base = np.linalg.inv(episode.camera.T_mount_cam)  # camera mount is the base
    K = episode.camera.K
    tiles = []
    for i in range(0, len(episode), 8):
        image = cv2.cvtColor(episode.rgb(i), cv2.COLOR_RGB2BGR)
        tcp_cam = T_cam_base @ T_base_tcp[i]
        origin = K @ tcp_cam[:3, 3]
        u, v = origin[:2] / origin[2]
        for axis, color in ((0, (0, 0, 255)), (1, (0, 255, 0)), (2, (255, 0, 0))):  # x red, y green, z blue
            tip = K @ (tcp_cam[:3, 3] + 0.04 * tcp_cam[:3, axis])
            cv2.line(image, (round(u), round(v)), (round(tip[0] / tip[2]), round(tip[1] / tip[2])), color, 1, cv2.LINE_AA)
        cv2.putText(image, f"{episode.frames.t[i]:.2f}s", (3, 12), cv2.FONT_HERSHEY_PLAIN, 0.8, (0, 0, 0), 1)
        tiles.append(image)
    sheet = cv2.resize(np.hstack(tiles), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    path = out / "overlay.png"
    cv2.imwrite(str(path), sheet)
    print(f"{len(episode)} frames, {episode.frames.t[-1]:.2f} s; TCP overlay written to {path}")
    return path


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    try:
        main(sys.argv[1])
    except ValueError as exc:  # a used OUT_DIR
        sys.exit(f"error: {exc}")
