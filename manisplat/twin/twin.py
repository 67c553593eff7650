"""The trained twin as a self-contained folder: load it and render any state, without the source
episode's images and without unpickling code.

``twin.json`` holds the description (camera, robot, labels, objects, phases, per-frame pose
sources, node list, light); ``twin.pt`` holds only tensors, read with ``torch.load(...,
weights_only=True)``: every node's Gaussian parameters, the light, the background colour, and
the recorded trajectory (``t`` [T] s, ``q`` [T, dof] rad, ``gripper`` [T] m, object poses
``T_base_obj`` [T, 4, 4] float64) and, when the recording had depth, the support height map
(:mod:`manisplat.twin.support`: ``support/heights`` [Ny, Nx], its origin and cell in twin.json).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from manisplat.episode.fsio import atomic_write_bytes
from manisplat.robot import RobotModel, load_robot
from manisplat.scene import GaussianSet, SceneGraph
from manisplat.scene.render import render_graph
from manisplat.scene.shadows import DirectionalShadows
from manisplat.splat import opencv_to_splat_K
from manisplat.twin.support import SupportMap

TWIN_JSON, TWIN_TENSORS = "twin.json", "twin.pt"
FORMAT, VERSION = "manisplat-twin", 1


class TwinFormatError(ValueError):
    """A twin folder that is missing, incomplete or of another format (the file and key named)."""


@dataclass(frozen=True)
class Phase:
    """Frames [start, end) of one Motion ("motion") or Skill ("skill") segment, e.g. "S_pick"."""

    kind: str
    name: str
    start: int
    end: int


@dataclass
class TwinView:
    """One rendered state: ``rgb`` [H, W, 3] uint8, ``depth`` [H, W] float32 z-depth in metres (0 where
    nothing was rendered), ``labels`` [H, W] uint8 mask values of the episode's ``labels``."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray


class Twin:
    """A reconstructed scene: Gaussians of the background, the robot's links and the objects, the
    light that casts the moving parts' shadows, the camera, and the source demonstration.

    Attributes:
        graph: the scene graph (links in link frames, objects in canonical frames).
        robot: the robot model (kinematics only) that ``robot_description`` names.
        K: [3, 3] OpenCV intrinsics (integer pixel centres); width, height: pixels.
        T_base_cam: [4, 4] float64 camera-to-base, including any refinement made in training.
        labels: mask value -> name ("background", "robot/<link>", "object/<name>", ...).
        t, q, gripper: the source demonstration per frame: [T] s, [T, dof] rad, [T] m.
        object_poses: name -> [T, 4, 4] float64 ``T_base_obj`` per frame (trained poses).
        pose_sources: name -> per frame "static", "attached" or "tracked".
        phases: name -> the Motion/Skill segments of the demonstration for that object.
        robot_info: the episode's ``robot.model`` and ``robot.joint_names``; camera_name, task,
            episode (folder name), fps: the source episode's.
        support: the support surfaces' height map, measured from the recording's depth (None
            without depth): where objects can be set down.
    """

    def __init__(self, *, graph: SceneGraph, background_rgb: torch.Tensor, robot: RobotModel, robot_description: str,
                 K: np.ndarray, width: int, height: int, T_base_cam: np.ndarray, labels: dict[int, str],
                 t: np.ndarray, q: np.ndarray, gripper: np.ndarray, object_poses: dict[str, np.ndarray],
                 pose_sources: dict[str, list[str]], phases: dict[str, list[Phase]], fps: float, episode: str,
                 robot_info: dict | None = None, camera_name: str = "camera", task: str | None = None,
                 backend: str = "auto", support: SupportMap | None = None) -> None:
        self.graph, self.background_rgb, self.robot = graph, background_rgb.float(), robot
        self.robot_description = robot_description
        self.K, self.width, self.height = np.asarray(K, np.float64), int(width), int(height)
        self.T_base_cam = np.asarray(T_base_cam, np.float64)
        self.labels = dict(labels)
        self.t, self.q, self.gripper = np.asarray(t, np.float64), np.asarray(q, np.float64), np.asarray(gripper, np.float64)
        self.object_poses = {k: np.asarray(v, np.float64) for k, v in object_poses.items()}
        self.pose_sources, self.phases = pose_sources, phases
        self.fps, self.episode, self.backend = float(fps), episode, backend
        self.robot_info = dict(robot_info or {"model": robot.name, "joint_names": list(robot.arm_joint_names)})
        self.camera_name, self.task, self.support = camera_name, task, support
        self.device = graph.device  # where it renders: the Gaussians' device
        self.background_rgb = self.background_rgb.to(self.device)
        self._viewmat = torch.as_tensor(np.linalg.inv(self.T_base_cam)).float().to(self.device)
        self._K_splat = opencv_to_splat_K(torch.as_tensor(self.K)).float().to(self.device)
        self._node_labels = self._label_of_nodes()

    # ------------------------------------------------------------------ rendering
    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def objects(self) -> list[str]:
        return list(self.graph.objects)

    @torch.no_grad()
    def render(self, q: np.ndarray, gripper: float, object_poses: dict[str, np.ndarray], *,
               T_base_cam: np.ndarray | None = None) -> TwinView:
        """The twin with the arm at joints ``q`` [dof] (rad) and gripper opening ``gripper`` (m), each
        object at ``object_poses[name]`` [4, 4] ``T_base_obj``, seen from the episode's camera (or
        from ``T_base_cam`` [4, 4], camera-to-base, with the episode's intrinsics)."""
        missing = set(self.graph.objects) - set(object_poses)
        if missing:
            raise ValueError(f"render: no pose for objects {sorted(missing)}")
        q = torch.as_tensor(np.asarray(q, np.float64))
        link_poses = self.robot.forward_kinematics(q, torch.as_tensor(float(gripper), dtype=torch.float64)).to(self.device)
        poses = {k: torch.as_tensor(np.asarray(v, np.float64)).to(self.device) for k, v in object_poses.items()
                 if k in self.graph.objects}
        viewmat = self._viewmat if T_base_cam is None else \
            torch.as_tensor(np.linalg.inv(np.asarray(T_base_cam, np.float64))).float().to(self.device)
        view = render_graph(self.graph, link_poses, poses, viewmat=viewmat, K=self._K_splat, width=self.width,
                            height=self.height, background=self.background_rgb, backend=self.backend, depth=True,
                            groups_per_node=True)
        rgb = (view.rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        strongest, node = view.group_alphas.cpu().max(-1)
        labels = self._node_labels[node]
        labels[strongest < 0.5] = self._node_labels[0] if self.graph.background is not None else 0
        return TwinView(rgb=rgb, depth=view.depth.cpu().numpy().astype(np.float32), labels=labels.numpy().astype(np.uint8))

    def render_frame(self, i: int) -> TwinView:
        """The twin in the source demonstration's state at frame ``i``."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} outside 0..{self.n_frames - 1}")
        return self.render(self.q[i], self.gripper[i], {k: v[i] for k, v in self.object_poses.items()})

    def _label_of_nodes(self) -> torch.Tensor:
        """[nodes] the mask value of each node of :meth:`SceneGraph.nodes` (static nodes: "background")."""
        by_name = {name: value for value, name in self.labels.items()}
        static = by_name.get("background", 0)
        values = []
        for node in self.graph.nodes():
            kind, _, name = node.name.partition("/")
            values.append(static if kind == "background" else by_name.get(node.name, static))
        return torch.tensor(values, dtype=torch.long)

    # ------------------------------------------------------------------ files
    def save(self, folder: str | Path) -> None:
        """Write ``twin.json`` and ``twin.pt`` into ``folder`` (each to a temporary name, then renamed)."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        # host copies: a twin trained on a GPU loads anywhere with torch.load(..., weights_only=True)
        tensors = {"background_rgb": self.background_rgb.detach().cpu().clone(),
                   "t": torch.as_tensor(self.t), "q": torch.as_tensor(self.q), "gripper": torch.as_tensor(self.gripper)}
        nodes = []
        for node in self.graph.nodes():
            params = node.gaussians.params
            nodes.append({"name": node.name, "count": len(node.gaussians), "params": sorted(params)})
            tensors.update({f"node/{node.name}/{k}": v.detach().cpu().clone() for k, v in params.items()})
        for name, poses in self.object_poses.items():
            tensors[f"object_poses/{name}"] = torch.as_tensor(poses)
        light = None
        if self.graph.shadows is not None:
            sh = self.graph.shadows
            light = {"extent": sh.extent, "resolution": sh.resolution, "softness": sh.softness}
            tensors.update({f"shadows/{k}": v.detach().cpu().clone() for k, v in sh.state_dict().items()})
        support = None
        if self.support is not None:
            support = {"origin": list(self.support.origin), "cell": self.support.cell}
            tensors["support/heights"] = torch.as_tensor(self.support.heights)
        meta = {
            "format": FORMAT, "version": VERSION, "episode": self.episode, "fps": self.fps, "task": self.task,
            "robot": {"description": self.robot_description, "link_order": list(self.graph.link_index),
                      "model": self.robot_info["model"], "joint_names": list(self.robot_info["joint_names"])},
            "camera": {"name": self.camera_name, "width": self.width, "height": self.height, "K": self.K.tolist(),
                       "T_base_cam": self.T_base_cam.tolist()},
            "labels": {str(k): v for k, v in sorted(self.labels.items())},
            "nodes": nodes, "shadows": light, "support": support,
            "objects": {name: {"pose_source": self.pose_sources.get(name, []),
                               "phases": [vars(p) for p in self.phases.get(name, [])]}
                        for name in self.graph.objects},
        }
        buffer = io.BytesIO()
        torch.save(tensors, buffer)
        atomic_write_bytes(folder / TWIN_TENSORS, buffer.getvalue())
        atomic_write_bytes(folder / TWIN_JSON, (json.dumps(meta, indent=1) + "\n").encode())

    @classmethod
    def load(cls, folder: str | Path, *, backend: str = "auto", device: torch.device | str = "cpu") -> "Twin":
        """The twin a reconstruction folder holds (``manisplat-reconstruct --out``), its Gaussians on
        ``device`` ("cpu", "cuda"; where it renders, with ``backend`` "auto" picking gsplat on CUDA),
        whichever device it was trained on.

        Raises:
            TwinFormatError: ``twin.json`` or ``twin.pt`` missing, unreadable, or inconsistent.
            RobotModelError, FileNotFoundError: the robot description cannot be loaded.
        """
        folder = Path(folder)
        meta = _read_meta(folder / TWIN_JSON)
        tensors_path = folder / TWIN_TENSORS
        if not tensors_path.is_file():
            raise TwinFormatError(f"{tensors_path}: missing (the folder is not a complete reconstruction)")
        try:
            tensors = torch.load(tensors_path, weights_only=True, map_location="cpu")
        except Exception as exc:  # torch raises several types for damaged files
            first = (str(exc).strip().splitlines() or [""])[0]  # torch's messages run over many lines
            raise TwinFormatError(f"{tensors_path}: unreadable, damaged or not written by manisplat-reconstruct "
                                  f"({type(exc).__name__}: {first})") from exc

        def tensor(key: str) -> torch.Tensor:
            if key not in tensors:
                raise TwinFormatError(f"{tensors_path}: no tensor {key!r}")
            return tensors[key]

        robot = load_robot(meta["robot"]["description"], load_meshes=False)
        if list(meta["robot"]["link_order"]) != list(robot.link_names):
            raise TwinFormatError(f"{folder / TWIN_JSON}: link order {meta['robot']['link_order']} does not match "
                                  f"the robot {meta['robot']['description']!r} ({robot.link_names})")
        background, links, objects = None, {}, {}
        for node in meta["nodes"]:
            g = GaussianSet({k: tensor(f"node/{node['name']}/{k}") for k in node["params"]}, device=device)
            if len(g) != node["count"]:
                raise TwinFormatError(f"{tensors_path}: node {node['name']} has {len(g)} Gaussians, "
                                      f"twin.json says {node['count']}")
            g.active_degree = g.sh_degree
            kind, _, name = node["name"].partition("/")
            if kind == "background":
                background = g
            elif kind == "robot":
                links[name] = g
            else:
                objects[name] = g
        graph = SceneGraph(background, links, list(meta["robot"]["link_order"]), objects)
        if meta["shadows"] is not None:
            light = meta["shadows"]
            sh = DirectionalShadows(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3), light["extent"],
                                    resolution=light["resolution"], softness=light["softness"])
            sh.load_state_dict({k: tensor(f"shadows/{k}") for k in sh.state_dict()})
            graph.shadows = sh.to(device)
        camera = meta["camera"]
        objects_meta = meta["objects"]
        support = None
        if meta.get("support") is not None:  # twins written before support maps have none
            support = SupportMap(tensor("support/heights").numpy(), tuple(meta["support"]["origin"]),
                                 float(meta["support"]["cell"]))
        return cls(
            graph=graph, background_rgb=tensor("background_rgb"), robot=robot,
            robot_description=meta["robot"]["description"], K=np.array(camera["K"]), width=camera["width"],
            height=camera["height"], T_base_cam=np.array(camera["T_base_cam"]),
            labels={int(k): v for k, v in meta["labels"].items()},
            t=tensor("t").numpy(), q=tensor("q").numpy(), gripper=tensor("gripper").numpy(),
            object_poses={name: tensor(f"object_poses/{name}").numpy() for name in objects_meta},
            pose_sources={name: o["pose_source"] for name, o in objects_meta.items()},
            phases={name: [Phase(**p) for p in o["phases"]] for name, o in objects_meta.items()},
            fps=meta["fps"], episode=meta["episode"], backend=backend, task=meta.get("task"),
            robot_info={k: meta["robot"][k] for k in ("model", "joint_names")}, camera_name=camera["name"],
            support=support,
        )


def resolve_description(description: str, episode_dir: Path) -> str:
    """``robot.description`` made independent of the episode folder: a built-in name as it is, a
    relative URDF path made absolute against the episode folder."""
    if description.startswith("builtin:"):
        return description
    path = Path(description)
    return str(path if path.is_absolute() else (episode_dir / path).resolve())


def _read_meta(path: Path) -> dict:
    if not path.is_file():
        raise TwinFormatError(f"{path}: missing (not a reconstruction folder, or written before twins were saved)")
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise TwinFormatError(f"{path}: unreadable ({exc})") from exc
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise TwinFormatError(f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}; "
                              f"expected {FORMAT!r} version {VERSION}")
    required = {"": ("robot", "camera", "labels", "nodes", "shadows", "objects", "fps", "episode"),
                "robot": ("description", "link_order", "model", "joint_names"),
                "camera": ("name", "width", "height", "K", "T_base_cam")}
    for section, keys in required.items():
        content = meta if not section else meta.get(section)
        for key in keys:
            if not isinstance(content, dict) or key not in content:
                raise TwinFormatError(f"{path}: no key {'.'.join(filter(None, (section, key)))!r}")
    return meta
