"""The simulator's images of given states, without physics: run by the simulator's venv.

    MUJOCO_GL=osmesa SIMENV/bin/python sim_render_states.py EPISODE --parent PARENT --render DIR --json REPORT
        [--supersample N]

EPISODE holds the states: ``frames.csv`` (``q1..q6`` rad in the AgileX URDF convention, ``gripper``
the pads' gap in m) and ``object_poses.npz`` (the parent's object name -> [T, 4, 4] ``T_base_obj``
in the simulator's object frame), with ``episode.json`` for the image size. PARENT is the
``gen_pick_place.py`` episode whose scene (object, camera) is rebuilt, as ``execute_episode.py``
rebuilds it. Every frame is posed exactly (arm, fingers, object; the rest of the scene where the
scene puts it) and drawn: ``DIR/rgb/NNNNNN.png`` and ``DIR/masks/NNNNNN.png`` with the parent's
labels. ``execute_episode.py --render`` draws what contact physics made of a demonstration's
commands (the arm lags its targets, the object slips); this draws the states the demonstration's
own images show, so the two images differ only in how they are drawn. ``--supersample N`` draws
each colour image N times wider and higher and averages each N x N block, as a camera's pixel
integrates its area (the simulator's own images filter their textures by mipmap level, which
changes with the surface's distance and slant); the masks stay drawn at the image's size. Run
with the working directory ``shared/tools/sim`` (``benchmarks._simulator.run_sim_jobs`` does)."""

import argparse
import csv
import json
import os
import sys
import time

sys.path.insert(0, os.getcwd())
os.environ.setdefault("MUJOCO_GL", "osmesa")
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import gen_pick_place as gp  # noqa: E402
import piper_convention as pc  # noqa: E402


def read_states(episode: str, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joints [T, 6] (URDF convention, rad), gaps [T] (m) and ``name``'s poses [T, 4, 4] of ``episode``."""
    with open(os.path.join(episode, "frames.csv")) as fh:
        rows = list(csv.DictReader(fh))
    q = np.array([[float(r[f"q{i}"]) for i in range(1, 7)] for r in rows])
    gap = np.array([float(r["gripper"]) for r in rows])
    poses = np.load(os.path.join(episode, "object_poses.npz"))
    if name not in poses.files:
        raise SystemExit(f"{episode}/object_poses.npz has no {name!r} (it has {', '.join(poses.files)})")
    T = np.asarray(poses[name], float)
    if T.shape != (len(q), 4, 4) or not (np.isfinite(q).all() and np.isfinite(gap).all() and np.isfinite(T).all()):
        raise SystemExit(f"{episode}: {len(q)} frames in frames.csv, {name!r} poses of shape {T.shape}, "
                         "or values that are not finite")
    return q, gap, T


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("episode")
    ap.add_argument("--parent", required=True, help="the gen_pick_place.py episode whose scene is rebuilt")
    ap.add_argument("--render", required=True, help="write rgb/ and masks/ here")
    ap.add_argument("--json", required=True, help="write the report here")
    ap.add_argument("--supersample", type=int, default=1, metavar="N",
                    help="draw the colour images N times finer and average N x N blocks (default 1)")
    a = ap.parse_args(argv)
    if a.supersample < 1:
        ap.error(f"--supersample must be at least 1, not {a.supersample}")
    t_wall = time.time()

    pargs = json.loads(str(np.load(os.path.join(a.parent, "gt.npz"), allow_pickle=True)["info"]))["args"]
    obj = pargs.get("object", "box")
    q_urdf, gap, T_obj = read_states(a.episode, obj)

    m, _, _ = gp.build_model(gp.DEFAULT_SCENE, gp.DEFAULT_ROBOT, obj, pargs.get("timestep", 0.0005))
    d = mujoco.MjData(m)
    ids = gp.Ids(m, obj)
    cam_id = m.camera(pargs.get("camera", "ego")).id
    if pargs.get("cam_pos") is not None:
        gp.set_camera_lookat(m, cam_id, pargs["cam_pos"], pargs.get("cam_target") or [0.3, 0.0, 0.0])
    if pargs.get("camera_from"):
        pcam = gp.camera_from_episode(a.parent)
        gp.set_camera_pose(m, cam_id, pcam["T_base_cam"], pcam["fovy_deg"])
    with open(os.path.join(a.episode, "episode.json")) as fh:
        cam = json.load(fh)["camera"]
    H, W, N = int(cam["height"]), int(cam["width"]), a.supersample
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, N * W)  # the offscreen buffer holds the finer images
    m.vis.global_.offheight = max(m.vis.global_.offheight, N * H)
    renderer = mujoco.Renderer(m, H, W)
    fine = mujoco.Renderer(m, N * H, N * W) if N > 1 else renderer
    labels = gp.geom_labels(m, obj)
    for sub in ("rgb", "masks"):
        os.makedirs(os.path.join(a.render, sub), exist_ok=True)

    q_men = pc.urdf_to_menagerie(q_urdf)
    half = np.clip(gap / 2.0, 0.0, gp.GRIPPER_OPEN)
    qa = ids.obj_jnt_qadr
    for k in range(len(q_men)):
        d.qpos[ids.arm_qadr] = q_men[k]
        d.qpos[ids.fing_qadr] = [half[k], -half[k]]
        d.qpos[qa:qa + 3] = T_obj[k, :3, 3]
        d.qpos[qa + 3:qa + 7] = gp.mat2quat(T_obj[k, :3, :3])
        mujoco.mj_forward(m, d)
        fine.update_scene(d, camera=cam_id)
        rgb = fine.render()
        if N > 1:  # each pixel the mean of its N x N block (same centre: the fovy fixes the intrinsics' scale)
            rgb = np.round(rgb.reshape(H, N, W, N, 3).astype(np.float64).mean((1, 3))).astype(np.uint8)
        renderer.update_scene(d, camera=cam_id)
        renderer.enable_segmentation_rendering()
        seg = renderer.render()
        renderer.disable_segmentation_rendering()
        is_geom = (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (seg[..., 0] >= 0)
        mask = np.where(is_geom, labels[np.clip(seg[..., 0], 0, m.ngeom - 1)], 0).astype(np.uint8)
        Image.fromarray(rgb).save(os.path.join(a.render, "rgb", f"{k:06d}.png"))
        Image.fromarray(mask).save(os.path.join(a.render, "masks", f"{k:06d}.png"))
    renderer.close()
    if N > 1:
        fine.close()
    report = {"episode": os.path.basename(os.path.normpath(a.episode)), "object": obj, "frames": len(q_men),
              "supersample": N,
              "wall_s": round(time.time() - t_wall, 2)}
    with open(a.json, "w") as fh:
        fh.write(json.dumps(report) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
