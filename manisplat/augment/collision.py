"""The collision model of a twin's scene, checked with Pinocchio's geometry layer on coal (ex
hpp-fcl): one ``pin.computeCollisions`` call per configuration runs every active pair in C++.

Library choice: the reference (shared/reference/augmentation.md section 4) measured pin + coal at
0.13 ms per all-pairs check with convex link hulls, python-fcl via trimesh at 0.03 ms per single
pair query (plus Python per pair); Pinocchio is already the kinematics here
(:mod:`.kinematics`), so its ``GeometryModel`` on coal gives one C++ call per configuration, and
coal brings convex-convex GJK/EPA, half-spaces and octrees (for the background's points).

What is modelled:
* robot links: the convex hull of each link's geometry (the built-in PiPER's primitives, or a
  URDF's meshes, loaded when the twin's model came without them), moving with the gripper width;
* the table: a half-space below the estimated table height, lowered by ``table_margin``: the
  surface the twin's support map (the recording's depth) measures under the manipulated objects
  where they rest; without a map, the lowest 2 % of their Gaussians there (an object's underside
  is never seen, so its lowest Gaussians sit millimetres above the table: 7.7 and 14 mm on the
  Cobot Magic sample, where the map measures it within 0.1 mm); else the background's densest
  height;
* objects: boxes fitted to their Gaussians' means (2nd..98th percentile in their canonical frame,
  plus ``object_margin``), at their poses; a held object is attached to the TCP at its grasp;
* the background above the table: an octree (``voxel`` m) of the background Gaussians' means more
  than ``background_min_height`` above the table, without isolated points (fewer than 3
  neighbours within 2 voxels), without points that the source robot (links inflated by
  ``swept_margin``) or the source objects passed through (they cannot be obstacles: the source
  demonstration went there), and within 1.2 m of the base;
* extra obstacles (boxes) given by the caller.

Pairs: robot link vs link for non-adjacent links, minus pairs that touch in any source frame (the
source was executed, so such contacts are artefacts of the primitive geometry: the usual
"allowed collision matrix" from sampled states); every link vs the table, background, objects and
obstacles, minus pairs in contact in every source frame (the base on the table); a held object
vs everything except the links that hold it. Inside a skill, the fingers may touch the object it
acts on, and pairs the source touched during that skill are allowed (its relative motion is the
source's; see :meth:`SceneCollision.skill_allowances`).
"""

from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin
from scipy.spatial import cKDTree

from manisplat.augment.kinematics import PinRobot
from manisplat.robot.hulls import convex, link_hulls
from manisplat.twin.support import MIN_KNOWN


@dataclass(frozen=True)
class BoxObstacle:
    """An extra obstacle: a box of ``extents`` (3,) m centred at pose ``T`` (4, 4), base frame."""

    extents: tuple[float, float, float]
    T: np.ndarray


@dataclass
class CollisionSettings:
    table_margin: float = 0.003
    object_margin: float = 0.002
    voxel: float = 0.01
    background_min_height: float = 0.015
    swept_margin: float = 0.02
    workspace_radius: float = 1.2


def _object_box(means: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    lo = np.percentile(means, 2, axis=0) - margin
    hi = np.percentile(means, 98, axis=0) + margin
    return (hi - lo), (hi + lo) / 2


def _se3(T: np.ndarray) -> pin.SE3:
    T = np.asarray(T, np.float64)
    R = T[:3, :3]
    U, _, Vt = np.linalg.svd(R)  # re-orthonormalise (trained poses drift by ~1e-7)
    R = U @ Vt
    return pin.SE3(R, T[:3, 3].copy())


class SceneCollision:
    """Robot, table, objects, background and obstacles of one twin, and the pair lists.

    Use :meth:`set_state` (which objects are where, which is held, which pairs a skill allows),
    then :meth:`collides` / :meth:`first_collision` per configuration.
    """

    def __init__(self, twin, kin: PinRobot, source, *, obstacles: tuple[BoxObstacle, ...] = (),
                 settings: CollisionSettings | None = None) -> None:
        self.kin, self.src = kin, source
        self.settings = s = settings or CollisionSettings()
        robot = twin.robot
        self.gm = pin.GeometryModel()
        self.link_geom: dict[str, int] = {}
        hulls = link_hulls(robot, getattr(twin, "robot_description", None))
        self.link_points = {}
        for link, hull in hulls.items():
            jid, place = kin.link_joint[link]
            go = pin.GeometryObject(f"link:{link}", jid, place, convex(hull.vertices))
            self.link_geom[link] = self.gm.addGeometryObject(go)
            self.link_points[link] = np.asarray(hull.sample(150, seed=0) if hasattr(hull, "sample") else hull.vertices)
        # object boxes
        self.object_geom: dict[str, int] = {}
        self.held_geom: dict[str, int] = {}
        self.object_box: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        tcp_jid, tcp_place = kin.link_joint[robot.tcp_link]
        self._tcp_place = tcp_place * pin.SE3(np.asarray(robot.T_link_tcp, np.float64))
        self._tcp_jid = tcp_jid
        for name, g in twin.graph.objects.items():
            means = g.params["means"].detach().double().numpy()
            extents, centre = _object_box(means, s.object_margin)
            self.object_box[name] = (extents, centre)
            self.object_geom[name] = self.gm.addGeometryObject(
                pin.GeometryObject(f"object:{name}", 0, pin.SE3.Identity(), coal.Box(*extents)))
            self.held_geom[name] = self.gm.addGeometryObject(
                pin.GeometryObject(f"held:{name}", tcp_jid, pin.SE3.Identity(), coal.Box(*extents)))
        # table
        self.table_z, self.table_estimates = self._table_height(twin)
        self.table_geom = self.gm.addGeometryObject(pin.GeometryObject(
            "table", 0, pin.SE3(np.eye(3), np.array([0.0, 0.0, self.table_z - s.table_margin])),
            coal.Halfspace(np.array([0.0, 0.0, 1.0]), 0.0)))
        # obstacles
        self.obstacle_geoms = []
        for k, ob in enumerate(obstacles):
            self.obstacle_geoms.append(self.gm.addGeometryObject(
                pin.GeometryObject(f"obstacle:{k}", 0, _se3(ob.T), coal.Box(*map(float, ob.extents)))))
        # background
        self.background_points = self._background_points(twin)
        self.background_geom = None
        if len(self.background_points):
            tree = coal.makeOctree(self.background_points, s.voxel)
            self.background_geom = self.gm.addGeometryObject(
                pin.GeometryObject("background", 0, pin.SE3.Identity(), tree))
        self._build_pairs(robot)
        self.gd = pin.GeometryData(self.gm)
        self.active: set[int] = set()
        self.checks = 0

    # ------------------------------------------------------------------ scene estimates
    def _table_height(self, twin) -> tuple[float, dict]:
        """The table's height (m, the twin's frame) and every estimate of it (name -> m), the
        first there is of: ``support``, the measured surface under the manipulated objects where
        they rest (the median of the support map's cells under their Gaussians, median over
        objects); ``objects``, the lowest 2 % of those Gaussians; ``background``, the background's
        densest height. An object's rest is where it starts or where it is left, the lower: one of
        them may be in another gripper (a handover) or on a raised surface."""
        est = {}
        support = twin.support
        surfaces, lows = [], []
        for name, obj in self.src.objects.items():
            if not obj.manipulated or name not in twin.graph.objects:
                continue
            means = twin.graph.objects[name].params["means"].detach().double().numpy()
            resting = [means @ T[:3, :3].T + T[:3, 3] for T in (obj.T_rest, obj.T_placed) if T is not None]
            lows.append(min(float(np.percentile(p[:, 2], 2)) for p in resting))
            if support is not None:
                under = [support.height_at(p[:, :2]) for p in resting]
                seen = [float(np.median(h[np.isfinite(h)])) for h in under if np.isfinite(h).mean() >= MIN_KNOWN]
                if seen:
                    surfaces.append(min(seen))
        if surfaces:
            est["support"] = float(np.median(surfaces))
        if lows:
            est["objects"] = float(np.median(lows))
        bg = twin.graph.background
        if bg is not None and len(bg):
            z = bg.params["means"].detach().double().numpy()
            near = z[np.linalg.norm(z[:, :2], axis=1) < 0.8][:, 2]
            if len(near) > 10:
                hist, edges = np.histogram(near, bins=np.arange(near.min(), near.max() + 0.01, 0.005))
                k = int(np.argmax(hist))
                est["background"] = float((edges[k] + edges[k + 1]) / 2)
        for source in ("support", "objects", "background"):
            if source in est:
                return est[source], est
        return 0.0, est

    def _background_points(self, twin) -> np.ndarray:
        s = self.settings
        bg = twin.graph.background
        if bg is None or not len(bg):
            return np.zeros((0, 3))
        pts = bg.params["means"].detach().double().numpy()
        if "opacities" in bg.params:
            op = bg.params["opacities"].detach().double().numpy().reshape(-1)
            op = 1 / (1 + np.exp(-op)) if (op.min() < 0 or op.max() > 1) else op
            pts = pts[op > 0.2]
        pts = pts[(pts[:, 2] > self.table_z + s.background_min_height) & (np.linalg.norm(pts, axis=1) < s.workspace_radius)]
        if len(pts) == 0:
            return pts
        # isolated points (floaters) are not obstacles
        tree = cKDTree(pts)
        counts = np.array([len(n) for n in tree.query_ball_point(pts, 2 * s.voxel)])
        pts = pts[counts >= 4]
        if len(pts) == 0:
            return pts
        # what the source robot and objects swept through is free space
        swept = []
        step = max(1, len(self.src.q) // 200)
        for i in range(0, len(self.src.q), step):
            poses = self.kin.link_poses(self.src.q[i], self.src.gripper[i])
            for link, p in self.link_points.items():
                T = poses[link]
                swept.append(p @ T[:3, :3].T + T[:3, 3])
        d, _ = cKDTree(np.concatenate(swept)).query(pts)
        pts = pts[d > s.swept_margin]
        for name, poses in self.src.object_poses.items():
            if name not in self.object_box or len(pts) == 0:
                continue
            extents, centre = self.object_box[name]
            half = extents / 2 + 0.015
            inside = np.zeros(len(pts), bool)
            for T in poses[::max(1, len(poses) // 100)]:
                local = (pts - T[:3, 3]) @ T[:3, :3] - centre
                inside |= np.all(np.abs(local) <= half, axis=1)
            pts = pts[~inside]
        return pts

    # ------------------------------------------------------------------ pairs
    def _build_pairs(self, robot) -> None:
        parent = {j.child: j.parent for j in robot.joints}
        links = list(self.link_geom)
        pair_index: dict[tuple[int, int], int] = {}

        def add(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in pair_index:
                self.gm.addCollisionPair(pin.CollisionPair(*key))
                pair_index[key] = len(pair_index)
            return pair_index[key]

        self.pair_index = pair_index
        self.pair_names: dict[int, tuple[str, str]] = {}
        names = {i: self.gm.geometryObjects[i].name for i in range(len(self.gm.geometryObjects))}

        def adjacent(a: str, b: str) -> bool:
            return parent.get(a) == b or parent.get(b) == a or (parent.get(a) is not None and parent.get(a) == parent.get(b))

        self.self_pairs = [add(self.link_geom[a], self.link_geom[b]) for i, a in enumerate(links)
                           for b in links[i + 1:] if not adjacent(a, b)]
        env = [self.table_geom, *self.obstacle_geoms] + ([self.background_geom] if self.background_geom is not None else [])
        self.env_geoms = env
        self.link_env_pairs = {(l, g): add(self.link_geom[l], g) for l in links for g in env}
        self.link_object_pairs = {(l, o): add(self.link_geom[l], g) for l in links for o, g in self.object_geom.items()}
        # links that hold a grasped object: the TCP link and every link below it (fingers)
        holding = {robot.tcp_link} | {l for l in links if self._descends(parent, l, robot.tcp_link)}
        self.holding_links = holding
        self.fingers = {l for l in links if l != robot.tcp_link and self._descends(parent, l, robot.tcp_link)} or {robot.tcp_link}
        self.held_pairs: dict[str, list[int]] = {}
        for o, hg in self.held_geom.items():
            ps = [add(hg, g) for g in env]
            ps += [add(hg, self.link_geom[l]) for l in links if l not in holding]
            ps += [add(hg, og) for o2, og in self.object_geom.items() if o2 != o]
            self.held_pairs[o] = ps
        self.pair_names = {idx: (names[a], names[b]) for (a, b), idx in pair_index.items()}
        self.n_pairs = len(pair_index)

        # what the source shows to be artefacts: self pairs touching in any source frame, link-env
        # pairs touching in every frame
        gd = self._data_with(set(self.self_pairs) | set(self.link_env_pairs.values()))
        touched_any = np.zeros(self.n_pairs, bool)
        touched_all = np.ones(self.n_pairs, bool)
        for i in range(len(self.src.q)):
            hit = self._hits(gd, self.src.q[i], self.src.gripper[i])
            touched_any |= hit
            touched_all &= hit
        self.disabled_self = {k for k in self.self_pairs if touched_any[k]}
        self.disabled_env = {k for k in self.link_env_pairs.values() if touched_all[k]}
        self._touched_source = None

    @staticmethod
    def _descends(parent: dict, link: str, ancestor: str) -> bool:
        while link in parent:
            link = parent[link]
            if link == ancestor:
                return True
        return False

    def _hits(self, gd, q, width) -> np.ndarray:
        pin.computeCollisions(self.kin.model, self.kin.data, self.gm, gd, self.kin.full_q(q, width), False)
        out = np.zeros(self.n_pairs, bool)
        for k in range(self.n_pairs):
            if gd.activeCollisionPairs[k]:
                out[k] = gd.collisionResults[k].isCollision()
        return out

    def skill_allowances(self, skill) -> set[int]:
        """Link-environment pairs (table, background, obstacles excluded) the source touched
        during ``skill``'s frames: allowed again in the moved skill."""
        cand = {k for (l, g), k in self.link_env_pairs.items() if g not in self.obstacle_geoms}
        gd = self._data_with(cand)
        allowed = set()
        for i in range(skill.first, skill.last + 1):
            hit = self._hits(gd, self.src.q[i], self.src.gripper[i])
            allowed |= {k for k in cand if hit[k]}
        return allowed

    # ------------------------------------------------------------------ state
    def set_state(self, world: dict[str, np.ndarray], held: str | None, G: np.ndarray | None,
                  allowed: set[int] = frozenset(), skill_object: str | None = None) -> None:
        """Objects in ``world`` at their poses (name -> T), ``held`` attached at grasp offset ``G``
        (object in the TCP frame), ``allowed`` pairs off, and finger contact with ``skill_object`` off."""
        active = set(self.self_pairs) - self.disabled_self
        active |= set(self.link_env_pairs.values()) - self.disabled_env
        for name, T in world.items():
            if name not in self.object_geom:
                continue
            self.gm.geometryObjects[self.object_geom[name]].placement = _se3(T) * pin.SE3(np.eye(3), self.object_box[name][1])
            for l in self.link_geom:
                if name == skill_object and l in self.fingers:
                    continue
                active.add(self.link_object_pairs[(l, name)])
        if held is not None and held in self.held_geom:
            self.gm.geometryObjects[self.held_geom[held]].placement = (
                self._tcp_place * _se3(G) * pin.SE3(np.eye(3), self.object_box[held][1]))
            for k in self.held_pairs[held]:
                a, b = self.pair_names[k]
                other = a if b == f"held:{held}" else b
                if other.startswith("object:") and other[7:] not in world:
                    continue
                active.add(k)
        active -= set(allowed)
        self.gd = self._data_with(active)
        self.active = active

    def _data_with(self, active: set[int]) -> pin.GeometryData:
        gd = pin.GeometryData(self.gm)
        gd.deactivateAllCollisionPairs()
        for k in active:
            gd.activateCollisionPair(k)
        return gd

    def collides(self, q: np.ndarray, width: float) -> bool:
        self.checks += 1
        return bool(pin.computeCollisions(self.kin.model, self.kin.data, self.gm, self.gd,
                                          self.kin.full_q(q, width), True))

    def first_collision(self, q: np.ndarray, width: float) -> tuple[str, str] | None:
        pin.computeCollisions(self.kin.model, self.kin.data, self.gm, self.gd, self.kin.full_q(q, width), False)
        for k in sorted(self.active):
            if self.gd.collisionResults[k].isCollision():
                return self.pair_names[k]
        return None

    def clearance(self, q: np.ndarray, width: float) -> float:
        """Smallest distance (m) over the active pairs except the background octree (coal gives no
        octree distance); negative inside."""
        pin.updateGeometryPlacements(self.kin.model, self.kin.data, self.gm, self.gd, self.kin.full_q(q, width))
        best = np.inf
        bg = self.background_geom
        for k in self.active:
            cp = self.gm.collisionPairs[k]
            if bg is not None and bg in (cp.first, cp.second):
                continue
            if self.table_geom in (cp.first, cp.second):
                continue  # half-space distances are handled below
            d = pin.computeDistance(self.gm, self.gd, k).min_distance
            best = min(best, d)
        table = self.table_geom
        for l, g in self.link_geom.items():
            k = self.link_env_pairs[(l, table)]
            if k in self.active:
                M = self.gd.oMg[g]
                pts = self.link_points[l] @ M.rotation.T + M.translation
                best = min(best, float(pts[:, 2].min() - (self.table_z - self.settings.table_margin)))
        if bg is not None and len(self.background_points):
            tree = getattr(self, "_bg_tree", None) or cKDTree(self.background_points)
            self._bg_tree = tree
            for l, g in self.link_geom.items():
                if self.link_env_pairs[(l, bg)] in self.active:
                    M = self.gd.oMg[g]
                    d, _ = tree.query(self.link_points[l] @ M.rotation.T + M.translation)
                    best = min(best, float(d.min()))
        return float(best)
