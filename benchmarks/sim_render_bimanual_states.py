"""The Cobot Magic simulator's images of given states, without physics: run by the simulator's venv.

    MUJOCO_GL=osmesa SIMENV/bin/python sim_render_bimanual_states.py STATES.npz --calib CALIB.json \\
        --task handover|dual_pick_place --render DIR --json REPORT [--shadow-map-px N] [--supersample N]

STATES.npz holds ``q`` [T, 14] in ``/observations/qpos``'s layout ([left q1..q6, left gap, right
q1..q6, right gap]; rad in the AgileX URDF convention, gaps in m) and ``T_world_<object>`` [T, 4, 4]
for the objects that move, in the simulator's object frames; the others stand where the task's
layout puts them. CALIB.json is the recording's calibration sidecar (the head camera's pose and
the image size), as ``execute_bimanual.py`` reads it. Every frame is posed exactly and drawn from
the three cameras: ``DIR/<camera>/rgb/NNNNNN.png`` and ``DIR/<camera>/masks/NNNNNN.png``
(``gen_bimanual.py``'s labels). ``execute_bimanual.py --render`` draws what contact physics made
of a demonstration's commands (the arms lag their targets: a wrist camera's whole image moves
with its link); this draws the states the demonstration's own images show. Run with the working
directory ``shared/tools/sim`` (``benchmarks._simulator.run_sim_jobs`` does). ``--shadow-map-px``
draws the key light's shadows from a map of that many pixels a side instead of the scene's
(MuJoCo's ``visual/quality/shadowsize``, 2048 in the samples). ``--supersample N`` draws every
image N times wider and higher and averages each N x N block, as a camera's pixel integrates its
area (the simulator filters its textures by mipmap level, which changes with a surface's distance
and slant, so the head camera a metre away draws the objects' prints blurrier than a camera
integrating its pixels would); the masks are the fine drawing's sample at each pixel's centre (N
odd), where the image-sized drawing samples them."""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.getcwd())
os.environ.setdefault("MUJOCO_GL", "osmesa")
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import gen_bimanual as gb  # noqa: E402
import piper_convention as pc  # noqa: E402


def posed_states(m, states: dict, task: str) -> np.ndarray:
    """qpos [T, nq] of every frame: both arms and their fingers at ``states["q"]``, each object at
    its ``T_world_<object>`` or, without one, where ``task``'s layout starts it."""
    q = np.asarray(states["q"], float)
    if q.ndim != 2 or q.shape[1] != 14 or not np.isfinite(q).all():
        raise SystemExit(f"q must be a finite [T, 14] array, got {q.shape}")
    poses = {name: np.asarray(states[f"T_world_{name}"], float) if f"T_world_{name}" in states
             else np.broadcast_to(gb.start_pose(name, *gb.LAYOUT[task][name]), (len(q), 4, 4))
             for name in gb.OBJECTS}
    for name, T in poses.items():
        if T.shape != (len(q), 4, 4) or not np.isfinite(T).all():
            raise SystemExit(f"T_world_{name} must be a finite [{len(q)}, 4, 4] array, got {T.shape}")
    d = mujoco.MjData(m)
    arms = {n: gb.Arm(m, n) for n in gb.ARMS}
    qpos = np.empty((len(q), m.nq))
    for k in range(len(q)):
        for i, name in enumerate(gb.ARMS):
            gb.set_arm(d, arms[name], pc.urdf_to_menagerie(q[k, 7 * i:7 * i + 6]),
                       float(np.clip(q[k, 7 * i + 6], 0.0, 2 * gb.GRIPPER_OPEN)))
        for name, T in poses.items():
            gb.set_object_pose(m, d, name, T[k])
        qpos[k] = d.qpos
    return qpos


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("states", help="npz with q [T, 14] and T_world_<object> [T, 4, 4]")
    ap.add_argument("--calib", required=True, help="the recording's calibration sidecar")
    ap.add_argument("--task", required=True, choices=gb.TASKS)
    ap.add_argument("--render", required=True, help="write <camera>/rgb/ and <camera>/masks/ here")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--shadow-map-px", type=int, help="the shadow map's size (default: the scene's)")
    ap.add_argument("--supersample", type=int, default=1, metavar="N",
                    help="draw N times finer and average N x N blocks (N odd; default 1)")
    ap.add_argument("--json", required=True, help="write the report here")
    a = ap.parse_args(argv)
    if a.supersample < 1 or a.supersample % 2 == 0:
        ap.error(f"--supersample must be an odd number of at least 1, not {a.supersample}")
    t_wall = time.time()

    with open(a.calib) as fh:
        head = json.load(fh)["cameras"]["cam_high"]
    T = np.array(head["T_mount_cam"], float)
    m, _, _ = gb.build_model(gb.DEFAULT_SCENE, gb.DEFAULT_ROBOT, None, T[:3, 3].tolist(), (T[:3, 3] + T[:3, 2]).tolist(),
                             head.get("fovy_deg", gb.CAM_HIGH_FOVY))
    if a.shadow_map_px is not None:
        if a.shadow_map_px < 1:
            raise SystemExit(f"--shadow-map-px must be positive, got {a.shadow_map_px}")
        m.vis.quality.shadowsize = a.shadow_map_px
    W, H, N = int(head["width"]), int(head["height"]), a.supersample
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, N * W)  # the offscreen buffer holds the finer images
    m.vis.global_.offheight = max(m.vis.global_.offheight, N * H)
    qpos = posed_states(m, dict(np.load(a.states)), a.task)
    for camera in gb.CAMERAS:
        for sub in ("rgb", "masks"):
            os.makedirs(os.path.join(a.render, camera, sub), exist_ok=True)

    def save(result):
        for i, camera in enumerate(gb.CAMERAS):
            rgb = result["rgb"][i].reshape(H, N, W, N, 3).mean(axis=(1, 3))
            mask = result["mask"][i][N // 2::N, N // 2::N]
            Image.fromarray(np.rint(rgb).astype(np.uint8)).save(os.path.join(a.render, camera, "rgb", "%06d.png" % result["k"]))
            Image.fromarray(mask).save(os.path.join(a.render, camera, "masks", "%06d.png" % result["k"]))

    gb.render_all(m, qpos, N * W, N * H, shadows=True, jpeg_quality=0, checks=False, workers=a.workers, consume=save)
    with open(a.json, "w") as fh:
        fh.write(json.dumps({"states": os.path.basename(a.states), "frames": len(qpos),
                             "shadow_map_px": int(m.vis.quality.shadowsize), "supersample": N,
                             "wall_s": round(time.time() - t_wall, 2)}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
