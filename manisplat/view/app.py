"""The browser viewer on viser: every arm's meshes (or the twin's Gaussians) at its base, moved by
forward kinematics, the objects at their poses, every camera's frustum with the frame's image (a
wrist camera riding on its link), TCP paths, the depth as points, and a timeline; for augmentation
outputs, a list of the new demonstrations. Everything is in the content's world frame."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np
import torch
import viser

from manisplat.geometry.rotation import matrix_to_quat
from manisplat.view.content import Demo, ViewContent
from manisplat.view.splats import splat_arrays

log = logging.getLogger(__name__)

MESH_COLOR = (235, 120, 40)
"""The robot's meshes: one flat orange, so they read apart from the Gaussians and the table."""
PATH_COLORS = ((40, 110, 230), (150, 150, 150))
"""TCP path of the chosen demonstration, and of the others."""
DEPTH_POINTS_MAX = 60_000
"""Points shown of a frame's depth (every k-th valid pixel)."""


def _wxyz_xyz(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz [..., 4], xyz [..., 3]) of [..., 4, 4] poses, as viser takes them."""
    quats = matrix_to_quat(torch.as_tensor(np.asarray(T)[..., :3, :3], dtype=torch.float64)).numpy()
    return quats, np.asarray(T)[..., :3, 3]


def depth_points(depth: np.ndarray, rgb: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                 limit: int = DEPTH_POINTS_MAX) -> tuple[np.ndarray, np.ndarray]:
    """(points [N, 3] m in the world frame, colours [N, 3] uint8) of the valid pixels of ``depth``
    [H, W] (z-depth, m; 0 or non-finite = none) seen from ``T_world_cam`` [4, 4], thinned to at most
    ``limit`` points."""
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    step = max(1, int(np.ceil(len(u) / limit)))
    u, v = u[::step], v[::step]
    z = depth[v, u].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(z)], axis=1)
    points = (rays * z[:, None]) @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return points.astype(np.float32), rgb[v, u]


class Viewer:
    """One viewer on one server. ``set_frame`` and ``select`` move it; ``play`` runs the timeline.

    Scene: ``/arms/<arm>`` at the arm's ``T_world_base`` with its links ``/arms/<arm>/<link>``;
    ``/cameras/<camera>`` the frustums; ``/tcp_paths``, ``/tcp/<arm>``, ``/depth/<camera>``, ``/objects``.

    Args:
        content: what to show (:func:`manisplat.view.content.load_content`).
        server: the viser server (the caller owns and stops it).
    """

    def __init__(self, content: ViewContent, server: viser.ViserServer) -> None:
        self.content, self.server = content, server
        self.demo_index, self.frame = 0, 0
        self.frame_changes = 0  # frames shown since start (tests wait on it)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._tcp = [content.tcp_paths(d) for d in content.demos]
        server.scene.set_up_direction("+z")
        self._build_scene()
        self._build_gui()
        self._set_initial_camera()
        self.set_frame(0)
        self._player = threading.Thread(target=self._play_loop, name="manisplat-view-player", daemon=True)
        self._player.start()

    # ------------------------------------------------------------------ scene
    @property
    def demo(self) -> Demo:
        return self.content.demos[self.demo_index]

    def _build_scene(self) -> None:
        scene, content, twin = self.server.scene, self.content, self.content.twin
        self._arm_bases: dict[str, Any] = {}
        self._link_frames: dict[str, dict[str, Any]] = {}
        self._meshes: list[Any] = []
        for name, arm in content.arms.items():
            wxyz, xyz = _wxyz_xyz(arm.T_world_base)
            self._arm_bases[name] = scene.add_frame(f"/arms/{name}", show_axes=False, wxyz=wxyz, position=xyz)
            self._link_frames[name] = {link: scene.add_frame(f"/arms/{name}/{link}", show_axes=False)
                                       for link in arm.robot.link_names}
            self._meshes += [scene.add_mesh_simple(f"/arms/{name}/{link}/mesh_{k}",
                                                   np.asarray(visual.mesh.vertices, np.float32),
                                                   np.asarray(visual.mesh.faces, np.uint32), color=MESH_COLOR,
                                                   visible=twin is None)
                             for link, visuals in arm.robot.visuals.items() if link in self._link_frames[name]
                             for k, visual in enumerate(visuals)]
        self._object_frames: dict[str, Any] = {}
        self._splats: list[Any] = []
        if twin is not None:
            graph = twin.graph
            if graph.background is not None:
                self._splats.append(self._add_splats("/background", graph.background))
            for name, gaussians in graph.links.items():  # "link1" of a one-arm twin, "left/link1" of several
                arm_link = name if "/" in name else f"{next(iter(content.arms))}/{name}"
                self._splats.append(self._add_splats(f"/arms/{arm_link}/gaussians", gaussians))
            for name, gaussians in graph.objects.items():
                self._object_frames[name] = scene.add_frame(f"/objects/{name}", show_axes=False)
                self._splats.append(self._add_splats(f"/objects/{name}/gaussians", gaussians))
        self._frustums = {name: scene.add_camera_frustum(f"/cameras/{name}", fov=2 * np.arctan2(cam.height / 2,
                                                                                                cam.K[1, 1]),
                                                         aspect=cam.width / cam.height, scale=0.08, thickness=2.0,
                                                         thickness_units="screen", color=(20, 20, 20))
                          for name, cam in content.cameras.items()}
        if len(content.cameras) > 1:  # which frustum is which camera
            for name in content.cameras:
                scene.add_label(f"/cameras/{name}/label", name)
        self._paths = [(k, scene.add_line_segments(f"/tcp_paths/{k}/{arm}", np.stack([p[:-1], p[1:]], axis=1),
                                                   PATH_COLORS[0 if k == 0 else 1], thickness=2.0,
                                                   thickness_units="screen"))
                       for k, paths in enumerate(self._tcp) for arm, p in paths.items() if len(p) > 1]
        self._tcp_markers = {arm: scene.add_icosphere(f"/tcp/{arm}", radius=0.008, color=PATH_COLORS[0])
                             for arm in content.arms}
        self._depth_clouds: dict[str, Any] = {}

    def _add_splats(self, name: str, gaussians: Any) -> Any:
        arrays = splat_arrays(gaussians)
        return self.server.scene.add_gaussian_splats(name, centers=arrays.centers, covariances=arrays.covariances,
                                                     rgbs=arrays.rgbs, opacities=arrays.opacities)

    def _set_initial_camera(self) -> None:
        """Start beside and above a recording camera (the first one fixed in the world, else the
        first), turned 40 deg about the target, looking at the middle of the TCP paths, so the arms,
        the scene and the cameras' frustums are all in view."""
        cameras = self.content.cameras
        view = next((name for name, cam in cameras.items() if cam.arm_link is None), next(iter(cameras)))
        T = self.content.camera_pose(view, self.demo, 0)
        target = np.concatenate(list(self._tcp[0].values())).mean(axis=0)
        angle = np.deg2rad(40.0)
        turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
        eye = target + 1.1 * turn @ (T[:3, 3] - target) + np.array([0.0, 0.0, 0.1])
        camera = self.server.initial_camera
        camera.position, camera.look_at, camera.up = tuple(eye), tuple(target), (0.0, 0.0, 1.0)

    # ------------------------------------------------------------------ GUI
    def _build_gui(self) -> None:
        gui, content = self.server.gui, self.content
        if content.kind == "augmentation":
            names = [d.name for d in content.demos]
            self._choice = gui.add_dropdown("demonstration", tuple(names), initial_value=names[0])
            self._choice.on_update(lambda _: self.select(names.index(self._choice.value)))
            self._validation = gui.add_markdown("")
        with gui.add_folder("timeline"):
            self._playing = gui.add_checkbox("play", initial_value=False)
            self._slider = gui.add_slider("frame", min=0, max=max(1, len(self.demo) - 1), step=1, initial_value=0)
            self._speed = gui.add_slider("speed", min=0.1, max=4.0, step=0.1, initial_value=1.0)
        self._slider.on_update(lambda _: self.set_frame(int(self._slider.value)))
        with gui.add_folder("layers"):
            has_twin = content.twin is not None
            self._show_splats = gui.add_checkbox("twin Gaussians", initial_value=has_twin, disabled=not has_twin)
            self._show_meshes = gui.add_checkbox("robot meshes (URDF)", initial_value=not has_twin)
            self._show_paths = gui.add_checkbox("TCP paths", initial_value=True)
            self._show_depth = gui.add_checkbox("depth points", initial_value=content.kind == "episode")
            self._render_twin = gui.add_checkbox("render the twin's view", initial_value=has_twin, disabled=not has_twin)
        self._layers = {"gaussians": (self._show_splats, self._splats), "meshes": (self._show_meshes, self._meshes),
                        "paths": (self._show_paths, [handle for _, handle in self._paths])}
        for name, (box, _) in self._layers.items():
            box.on_update(lambda _, name=name, box=box: self.set_layer(name, box.value))
        self._show_depth.on_update(lambda _: self._refresh())
        self._render_twin.on_update(lambda _: self._refresh())
        with gui.add_folder("images"):
            self._recorded = {name: gui.add_image(np.full((cam.height, cam.width, 3), 255, np.uint8),
                                                  label=f"recorded: {name}")
                              for name, cam in content.cameras.items()}
            if content.twin is not None:
                blank = np.full((content.twin.height, content.twin.width, 3), 255, np.uint8)
                self._rendered = gui.add_image(blank, label="twin (our rasterizer)")
        if content.notes:
            gui.add_markdown("**Not shown:** " + " ".join(content.notes))

    def set_layer(self, name: str, visible: bool) -> None:
        """Show or hide a layer: "gaussians" (the twin), "meshes" (the robots' URDF meshes), "paths"."""
        box, handles = self._layers[name]
        if box.value != visible:
            box.value = visible
        for handle in handles:
            handle.visible = visible

    # ------------------------------------------------------------------ state
    def select(self, index: int) -> None:
        """Show demonstration ``index`` (augmentation folders), from its first frame."""
        with self._lock:
            self.demo_index = index
            for k, path in self._paths:
                path.colors = np.array(PATH_COLORS[0 if k == index else 1], dtype=np.uint8)
            self._slider.max = max(1, len(self.demo) - 1)
            if self.content.kind == "augmentation":
                if self._choice.value != self.demo.name:
                    self._choice.value = self.demo.name
                self._validation.content = self._validation_text(self.demo)
            self.set_frame(0)

    @staticmethod
    def _validation_text(demo: Demo) -> str:
        """The augmentation's validation record as a short list (numbers to 3 significant digits)."""
        if demo.validation is None:
            return "the source demonstration"
        lines = [f"- {k.replace('_', ' ')}: {v:.3g}" if isinstance(v, float) else f"- {k.replace('_', ' ')}: {v}"
                 for k, v in demo.validation.items() if not isinstance(v, (dict, list))]
        return "**validation**\n" + "\n".join(lines) if lines else "**validation** passed"

    def set_frame(self, i: int) -> None:
        """Move everything to frame ``i`` of the current demonstration."""
        with self._lock:
            i = int(np.clip(i, 0, len(self.demo) - 1))
            self.frame = i
            if int(self._slider.value) != i:
                self._slider.value = i
            self._refresh()

    def _refresh(self) -> None:
        demo, content, i = self.demo, self.content, self.frame
        links = {arm: content.link_poses(arm, demo, i) for arm in content.arms}
        T_cams = {name: content.camera_pose(name, demo, i) for name in content.cameras}
        with self.server.atomic():
            for arm, frames in self._link_frames.items():
                wxyz, xyz = _wxyz_xyz(links[arm])
                for k, frame in enumerate(frames.values()):
                    frame.wxyz, frame.position = wxyz[k], xyz[k]
                self._tcp_markers[arm].position = self._tcp[self.demo_index][arm][i]
            objects = content.object_poses_at(demo, i)
            for name, frame in self._object_frames.items():
                frame.wxyz, frame.position = _wxyz_xyz(objects[name])
            rendered = None
            if content.twin is not None and self._render_twin.value:
                rendered = content.twin_render(demo, i)
                self._rendered.image = rendered
            for name, frustum in self._frustums.items():
                frustum.wxyz, frustum.position = _wxyz_xyz(T_cams[name])
                recorded = demo.episode.rgb(i, name) if demo.episode is not None else None
                if recorded is not None:
                    self._recorded[name].image = recorded
                twin_view = rendered if content.twin is not None and name == content.twin.camera_name else None
                shown = recorded if recorded is not None else twin_view  # the twin renders its reference camera
                if shown is not None:
                    frustum.image = shown
                self._update_depth(name, demo, i, T_cams[name], recorded)
        self.frame_changes += 1

    def _update_depth(self, camera: str, demo: Demo, i: int, T_cam: np.ndarray, rgb: np.ndarray | None) -> None:
        """Show ``camera``'s depth of frame ``i`` as points coloured by ``rgb`` (none when off or without depth)."""
        cloud = self._depth_clouds.pop(camera, None)
        if cloud is not None:
            cloud.remove()
        if not self._show_depth.value or rgb is None or not demo.episode.has_images("depth", camera):
            return
        cam = self.content.cameras[camera]
        points, colors = depth_points(demo.episode.depth(i, camera), rgb, cam.K, T_cam)
        self._depth_clouds[camera] = self.server.scene.add_point_cloud(f"/depth/{camera}", points, colors,
                                                                       point_size=0.004)

    # ------------------------------------------------------------------ playback
    def _play_loop(self) -> None:
        last = time.perf_counter()
        while not self._stop.is_set():
            time.sleep(0.01)
            now = time.perf_counter()
            if not self._playing.value:
                last = now
                continue
            step = (now - last) * self._speed.value * self.demo.fps
            if step >= 1.0:
                self.set_frame((self.frame + int(step)) % len(self.demo))
                last = now

    def close(self) -> None:
        """Stop the playback thread (the server is the caller's)."""
        self._stop.set()
        self._player.join(timeout=2.0)
