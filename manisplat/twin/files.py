"""The twin as a self-contained folder, loadable without the source episode and without
unpickling code.

``twin.json`` (format ``manisplat-twin`` version 2) holds the description: the frame (``"base"``
for one arm, ``"world"`` for several), the arms (robot description, model, joint names,
``T_world_base``), the link order, the cameras (intrinsics, mount, ``T_mount_cam``; the reference
camera first), labels, objects, phases, per-frame pose sources, node list, light. ``twin.pt``
holds only tensors, read with ``torch.load(..., weights_only=True)``: every node's Gaussian
parameters, the light, the background colour, the recorded trajectory (``t`` [T] s, ``q``
[T, dof] rad, ``gripper`` [T] or [T, A] m, object poses ``T_<frame>_obj`` [T, 4, 4] float64),
when the recording had depth the support height map (:mod:`manisplat.twin.support`), and when
it had commands their press ``command_press`` [T, dof] rad (``twin.json``'s ``command_lead``, the
lead: :mod:`manisplat.twin.commands`) and the gripper commands ``command_gripper`` [T, arms] m.
A twin fused from several episodes keeps the first demonstration there and each other one in
``twin.json``'s ``demonstrations`` (episode, fps, task, command lead, per-object pose sources and
phases) and ``twin.pt``'s ``demonstration/<k>/...`` (k from 1: the same tensors).
Version 1 folders (one arm, one camera, written before 2026-11-27) still load.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import torch

from manisplat.episode.fsio import atomic_write_bytes
from manisplat.robot import RobotModel, load_robot
from manisplat.robot.arms import ArmSet
from manisplat.scene import GaussianSet, SceneGraph
from manisplat.scene.shadows import DirectionalShadows
from manisplat.splat import GSPLAT_EPS2D, RASTERIZE_MODES, is_dilation
from manisplat.twin.commands import CommandRelation
from manisplat.twin.rig import BASE_FRAME, TwinArm, TwinCamera, one_arm
from manisplat.twin.support import SupportMap
from manisplat.twin.twin import Demonstration, Phase, Twin, TwinFormatError

TWIN_JSON, TWIN_TENSORS = "twin.json", "twin.pt"
FORMAT, VERSION = "manisplat-twin", 2
READABLE_VERSIONS = (1, 2)


def save_twin(twin: Twin, folder: Path) -> None:
    """Write ``twin.json`` and ``twin.pt`` into ``folder`` (each to a temporary name, then renamed)."""
    folder.mkdir(parents=True, exist_ok=True)
    # host copies: a twin trained on a GPU loads anywhere with torch.load(..., weights_only=True)
    demos = list(twin.demonstrations.values())
    tensors = {"background_rgb": twin.background_rgb.detach().cpu().clone(), **_demonstration_tensors(demos[0])}
    for k, demo in enumerate(demos[1:], start=1):
        tensors.update({f"demonstration/{k}/{key}": v for key, v in _demonstration_tensors(demo).items()})
    nodes = []
    for node in twin.graph.nodes():
        params = node.gaussians.params
        nodes.append({"name": node.name, "count": len(node.gaussians), "params": sorted(params)})
        tensors.update({f"node/{node.name}/{k}": v.detach().cpu().clone() for k, v in params.items()})
    light = None
    if twin.graph.shadows is not None:
        sh = twin.graph.shadows
        light = {"extent": sh.extent, "resolution": sh.resolution, "softness": sh.softness, "receivers": sh.receivers,
                 "casters": "meshes" if sh.has_casters else "gaussians"}
        tensors.update({f"shadows/{k}": v.detach().cpu().clone() for k, v in sh.state_dict().items()})
    support = None
    if twin.support is not None:
        support = {"origin": list(twin.support.origin), "cell": twin.support.cell,
                   "resolution": twin.support.resolution}
        tensors["support/heights"] = torch.as_tensor(twin.support.heights)
    meta = {
        "format": FORMAT, "version": VERSION, **_demonstration_meta(demos[0], twin.graph.objects),
        "frame": twin.frame, "arms": [arm.to_dict() for arm in twin.arms], "link_order": list(twin.graph.link_index),
        "cameras": [cam.to_dict() for cam in twin.cameras.values()],
        "labels": {str(k): v for k, v in sorted(twin.labels.items())},
        "nodes": nodes, "shadows": light, "support": support, "rasterize_mode": twin.graph.rasterize_mode,
        "eps2d": twin.graph.eps2d,
    }
    if len(demos) > 1:
        meta["demonstrations"] = [_demonstration_meta(d, twin.graph.objects) for d in demos[1:]]
    buffer = io.BytesIO()
    torch.save(tensors, buffer)
    atomic_write_bytes(folder / TWIN_TENSORS, buffer.getvalue())
    atomic_write_bytes(folder / TWIN_JSON, (json.dumps(meta, indent=1) + "\n").encode())


def _demonstration_tensors(demo: Demonstration) -> dict[str, torch.Tensor]:
    out = {"t": torch.as_tensor(demo.t), "q": torch.as_tensor(demo.q), "gripper": torch.as_tensor(demo.gripper)}
    if demo.commands is not None:
        out["command_press"] = torch.as_tensor(demo.commands.press)
        if demo.commands.gripper is not None:
            out["command_gripper"] = torch.as_tensor(demo.commands.gripper)
    out.update({f"object_poses/{name}": torch.as_tensor(poses) for name, poses in demo.object_poses.items()})
    return out


def _demonstration_meta(demo: Demonstration, objects) -> dict:
    return {"episode": demo.episode, "fps": demo.fps, "task": demo.task,
            "command_lead": None if demo.commands is None else demo.commands.lead,
            "objects": {name: {"pose_source": demo.pose_sources.get(name, []),
                               "phases": [vars(p) for p in demo.phases.get(name, [])]} for name in objects}}


def _demonstration(meta: dict, tensor, prefix: str = "") -> Demonstration:
    """A demonstration from its ``twin.json`` entry and its tensors (under ``prefix``)."""
    objects = meta["objects"]
    commands = None
    if meta.get("command_lead") is not None:  # twins of recordings without commands, or written before, have none
        gripper = tensor(f"{prefix}command_gripper", required=False)  # twins written before 2026-11-28 have none
        commands = CommandRelation(meta["command_lead"], tensor(f"{prefix}command_press").numpy(),
                                   None if gripper is None else gripper.numpy())
    return Demonstration(
        episode=meta["episode"], fps=meta["fps"], task=meta.get("task"),
        t=tensor(f"{prefix}t").numpy(), q=tensor(f"{prefix}q").numpy(), gripper=tensor(f"{prefix}gripper").numpy(),
        object_poses={name: tensor(f"{prefix}object_poses/{name}").numpy() for name in objects},
        pose_sources={name: o["pose_source"] for name, o in objects.items()},
        phases={name: [Phase(**p) for p in o["phases"]] for name, o in objects.items()}, commands=commands)


def load_twin(folder: Path, *, backend: str = "auto", device: torch.device | str = "cpu") -> Twin:
    """The twin ``folder`` holds, its Gaussians on ``device`` (see :meth:`Twin.load`)."""
    meta = read_meta(folder / TWIN_JSON)
    tensors_path = folder / TWIN_TENSORS
    if not tensors_path.is_file():
        raise TwinFormatError(f"{tensors_path}: missing (the folder is not a complete reconstruction)")
    try:
        tensors = torch.load(tensors_path, weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises several types for damaged files
        first = (str(exc).strip().splitlines() or [""])[0]  # torch's messages run over many lines
        raise TwinFormatError(f"{tensors_path}: unreadable, damaged or not written by manisplat-reconstruct "
                              f"({type(exc).__name__}: {first})") from exc

    def tensor(key: str, required: bool = True) -> torch.Tensor | None:
        """The tensor ``key``; without it None where it is not ``required``, else a TwinFormatError."""
        if key not in tensors:
            if not required:
                return None
            raise TwinFormatError(f"{tensors_path}: no tensor {key!r}")
        return tensors[key]

    arms = [TwinArm.from_dict(a) for a in meta["arms"]]
    robot = _robot_of(arms, meta["frame"])
    if list(meta["link_order"]) != list(robot.link_names):
        raise TwinFormatError(f"{folder / TWIN_JSON}: link order {meta['link_order']} does not match the robot "
                              f"{robot.name!r} ({list(robot.link_names)})")
    background, links, objects = _nodes(meta, tensor, tensors_path, device)
    graph = SceneGraph(background, links, list(meta["link_order"]), objects)
    graph.rasterize_mode = meta.get("rasterize_mode", "classic")  # twins before the option: classic
    if graph.rasterize_mode not in RASTERIZE_MODES:
        raise TwinFormatError(f"{folder / TWIN_JSON}: rasterize_mode {graph.rasterize_mode!r} is not one of {RASTERIZE_MODES}")
    graph.eps2d = meta.get("eps2d", GSPLAT_EPS2D)  # twins before the modes' own dilations: gsplat's in both
    if not is_dilation(graph.eps2d):
        raise TwinFormatError(f"{folder / TWIN_JSON}: eps2d {graph.eps2d!r} is not a finite dilation >= 0 px^2")
    if meta["shadows"] is not None:
        light = meta["shadows"]
        casters = None
        if light.get("casters", "gaussians") == "meshes":  # twins before mesh casters: the links' Gaussians cast
            casters = tensor("shadows/caster_points"), tensor("shadows/caster_links")
        sh = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), light["extent"],
                                resolution=light["resolution"], softness=light["softness"],
                                receivers=light.get("receivers", "background"),  # twins before receivers: background
                                casters=casters)
        stored = [k for k in sh.state_dict() if "receivers" in light or k != "moving_strength_logit"]
        sh.load_state_dict({k: tensor(f"shadows/{k}") for k in stored}, strict="receivers" in light)
        graph.shadows = sh.to(device)
    support = None
    if meta.get("support") is not None:  # twins written before support maps have none
        support = SupportMap(tensor("support/heights").numpy(), tuple(meta["support"]["origin"]),
                             float(meta["support"]["cell"]), float(meta["support"].get("resolution", 0.0)))
    try:
        demonstrations = [_demonstration(meta, tensor)] + [_demonstration(d, tensor, f"demonstration/{k}/")
                                                           for k, d in enumerate(meta.get("demonstrations", []), start=1)]
        return Twin(
            graph=graph, background_rgb=tensor("background_rgb"), robot=robot, arms=arms,
            cameras=[TwinCamera.from_dict(c) for c in meta["cameras"]],
            labels={int(k): v for k, v in meta["labels"].items()},
            demonstrations=demonstrations, backend=backend, support=support,
        )
    except ValueError as exc:  # arms, cameras or mounts that do not fit together
        raise TwinFormatError(f"{folder / TWIN_JSON}: {exc}") from exc


def _robot_of(arms: list[TwinArm], frame: str) -> RobotModel | ArmSet:
    """The kinematics of the twin's arms: one arm's model in its base frame, else an arm set."""
    if frame == BASE_FRAME:
        return load_robot(arms[0].description, load_meshes=False)
    return ArmSet({a.name: load_robot(a.description, load_meshes=False) for a in arms},
                  {a.name: a.T_world_base for a in arms})


def _nodes(meta: dict, tensor, tensors_path: Path, device
           ) -> tuple[GaussianSet | None, dict[str, GaussianSet], dict[str, GaussianSet]]:
    """The Gaussians of ``twin.json``'s nodes: (background or None, link -> set, object -> set)."""
    background, links, objects = None, {}, {}
    for node in meta["nodes"]:
        g = GaussianSet({k: tensor(f"node/{node['name']}/{k}") for k in node["params"]}, device=device)
        if len(g) != node["count"]:
            raise TwinFormatError(f"{tensors_path}: node {node['name']} has {len(g)} Gaussians, "
                                  f"twin.json says {node['count']}")
        g.active_degree = g.sh_degree
        kind, _, name = node["name"].partition("/")  # "robot/left/link1" -> ("robot", "left/link1")
        if kind == "background":
            background = g
        elif kind == "robot":
            links[name] = g
        else:
            objects[name] = g
    return background, links, objects


def read_meta(path: Path) -> dict:
    """``twin.json``, checked for the keys loading needs; a version 1 file in version 2's terms."""
    if not path.is_file():
        raise TwinFormatError(f"{path}: missing (not a reconstruction folder, or written before twins were saved)")
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise TwinFormatError(f"{path}: unreadable ({exc})") from exc
    if meta.get("format") != FORMAT or meta.get("version") not in READABLE_VERSIONS:
        raise TwinFormatError(f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}; "
                              f"expected {FORMAT!r} version {' or '.join(map(str, READABLE_VERSIONS))}")
    if meta["version"] == 1:
        _require(path, meta, {"": ("robot", "camera"), "robot": ("description", "link_order", "model", "joint_names"),
                              "camera": ("name", "width", "height", "K", "T_base_cam")})
        meta = _from_version_1(meta)
    _require(path, meta, {"": ("frame", "arms", "link_order", "cameras", "labels", "nodes", "shadows", "objects",
                               "fps", "episode")})
    for k, arm in enumerate(meta["arms"]):
        _require(path, arm, {"": ("name", "description", "model", "joint_names", "T_world_base")}, f"arms[{k}]")
    for k, cam in enumerate(meta["cameras"]):
        _require(path, cam, {"": ("name", "width", "height", "K", "mount", "T_mount_cam")}, f"cameras[{k}]")
    for k, demo in enumerate(meta.get("demonstrations", [])):
        _require(path, demo, {"": ("episode", "fps", "objects")}, f"demonstrations[{k}]")
    if not meta["arms"] or not meta["cameras"]:
        raise TwinFormatError(f"{path}: a twin needs at least one arm and one camera")
    return meta


def _from_version_1(meta: dict) -> dict:
    """A version 1 ``twin.json`` (one arm, one camera fixed in its base frame) as version 2."""
    robot, camera = meta.pop("robot"), meta.pop("camera")
    meta["frame"] = BASE_FRAME
    meta["arms"] = [one_arm(robot["description"], robot["model"], robot["joint_names"]).to_dict()]
    meta["link_order"] = robot["link_order"]
    meta["cameras"] = [{"name": camera["name"], "width": camera["width"], "height": camera["height"],
                        "K": camera["K"], "mount": BASE_FRAME, "T_mount_cam": camera["T_base_cam"]}]
    return meta


def _require(path: Path, meta: dict, required: dict[str, tuple[str, ...]], prefix: str = "") -> None:
    for section, keys in required.items():
        content = meta if not section else meta.get(section)
        for key in keys:
            if not isinstance(content, dict) or key not in content:
                name = ".".join(filter(None, (prefix, section, key)))
                raise TwinFormatError(f"{path}: no key {name!r}")
