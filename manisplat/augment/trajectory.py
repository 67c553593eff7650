"""One new demonstration from a twin and new object poses: skills moved with their objects (IK),
motions re-planned (collision-free path, toppra timing), all validated. No rendering, no files.

    >>> targets = sample_targets(twin, np.random.default_rng(3))
    >>> traj = augment_trajectory(twin, targets, AugmentConfig(seed=3))   # raises Rejected

Method (issue 12, DemoGen): the twin's phases give the skills (:mod:`.source`); each skill's TCP
poses are moved by ``D = T_new @ inv(T_src)`` of its object (the pick by the object's new start
pose against its source rest pose, the place by the new place pose against the source's placed
pose, the grasp offset kept) and solved frame by frame (:mod:`.skills`), slowed uniformly only
if the new joints would break a limit. Between skills, and from the source's first joints to the
first skill and from the last skill back to the source's last joints, a Motion is planned in
joint space (:mod:`.planning`: straight line, else OMPL RRT-Connect) in the collision model of
:mod:`.collision` (the object held during it attached to the gripper) and timed by toppra under
``speed`` x the velocity/acceleration limits (x 0.95 headroom for the frame-rate finite
differences), leaving and entering the skills at their own joint velocities (:mod:`.timing`).
Where no spline does that within the limits (a planned path that turns sharply next to a skill),
the arm brakes along the skill's last velocity to rest, the path is planned again from rest to
rest, and it speeds up into the next skill along the mirror of braking (the planner record's
``joined``: "at speed" or "at rest").
A demonstration whose last skill ends moving gets an extra Motion, "M_settle", that brings the
arm to rest along its direction of travel (so the last commanded frame is at rest).

Conventions of :class:`NewTrajectory`:
* frames at ``t = k / fps`` of the parent; ``action_q`` the commands, in the relation the
  source's commands had to its joints (:mod:`.commands`: every frame led by the source's lead,
  skills pressing as the source did; the next frame's joints where it recorded no commands),
  ``action_gripper`` the source's recorded gripper command at the source time a frame plays
  (a motion: the middle of the source's frames it replaces); where none was recorded 0.07 (open)
  or 0.0 (closed) from the source's gripper events (closed from the grasp to the release);
* skill frames carry the source's gripper signal (interpolated when slowed); motions hold the
  gripper of the frame before them (the first motion: the source's frame 0).
"""

from __future__ import annotations

import math
import time
import weakref
from dataclasses import dataclass, field

import numpy as np

from manisplat.augment.collision import BoxObstacle, SceneCollision
from manisplat.augment.commands import SourceCommands
from manisplat.augment.draws import Draws
from manisplat.augment.errors import Rejected
from manisplat.augment.frames import solid_points
from manisplat.augment.kinematics import PinRobot
from manisplat.augment.planning import MAX_CHECKS, RESOLUTION, SAFETY_TIMEOUT_S, path_free, plan_path
from manisplat.augment.sampling import ObjectTarget, sample_start, sample_targets
from manisplat.augment.skills import SkillResult, SourceSpline, solve_skill
from manisplat.augment.source import SourceDemo, SourceError, source_demo
from manisplat.augment.symmetry import Symmetry, axis_point, wrist_keeping_turn, yaw_of
from manisplat.augment.timing import PROFILES, REST, TimedMotion, TimingError, time_motion
from manisplat.augment.validation import check_all, dense_collision, skill_relative_errors, within_limits
from manisplat.twin.support import MAX_STEP

__all__ = ["AugmentConfig", "BoxObstacle", "NewTrajectory", "ObjectTarget", "Rejected", "augment_trajectory",
           "sample_targets", "Augmenter"]

GRIPPER_OPEN, GRIPPER_CLOSED = 0.07, 0.0
REST_SPEED = 0.02  # rad/s: slower than this at the end counts as at rest


@dataclass
class AugmentConfig:
    """Settings of :func:`augment_trajectory`.

    Attributes:
        speed: fraction of the joint velocity/acceleration limits for re-planned motions (0, 1].
        profile: how re-planned motions are timed (:data:`~manisplat.augment.timing.PROFILES`):
            "time-optimal" (toppra) or "smooth" (a quintic, bell-shaped speed); braking to rest
            along a skill's velocity and speeding up into the next (a motion joined at rest,
            ``M_settle``) stay time-optimal: a quintic with zero acceleration at the skill needs
            a longer way to stop than the braking point leaves.
        planner_checks: RRT-Connect's budget per motion, in collision checks (the same paths on
            any machine, however busy; the default about 1 s on one idle core).
        planner_timeout_s: its time limit per motion, a safety net behind the budget.
        ik_position_tol, ik_rotation_tol: the largest IK residual accepted (m, rad).
        seed: seeds the planner (with the segment index).
        obstacles: extra boxes in the base frame, besides what the twin holds.
        headroom: the fraction of the limits actually planned for (finite differences at the
            frame rate overshoot a continuous profile slightly).
        max_support_step: an object set down (start or place) where the surface near its centre
            falls more than this (m) below the highest surface under it is discarded: it would
            rest on an edge and tip (:mod:`manisplat.twin.support`; not checked when the twin has
            no support map).
        min_slow: skill name -> the least uniform slow-down it is solved at (1: its recorded
            pace); a handover skill is played by both arms at one pace.
        symmetries: object name -> its shape's symmetry about the vertical: its skills grasp
            the face that keeps the wrist nearest the source's (:mod:`.symmetry`).
    """

    speed: float = 1.0
    profile: str = "time-optimal"
    planner_checks: int = MAX_CHECKS
    planner_timeout_s: float = SAFETY_TIMEOUT_S
    ik_position_tol: float = 1e-4
    ik_rotation_tol: float = 1.75e-4
    seed: int = 0
    obstacles: tuple[BoxObstacle, ...] = ()
    headroom: float = 0.95
    max_support_step: float = MAX_STEP
    min_slow: dict[str, float] = field(default_factory=dict)
    symmetries: dict[str, Symmetry] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (0 < self.speed <= 1):
            raise ValueError(f"speed must be in (0, 1], got {self.speed}")
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {PROFILES}, got {self.profile!r}")
        if not self.planner_timeout_s > 0:
            raise ValueError(f"planner_timeout_s must be > 0, got {self.planner_timeout_s}")
        if not self.planner_checks >= 1:
            raise ValueError(f"planner_checks must be >= 1, got {self.planner_checks}")
        if not (self.ik_position_tol > 0 and self.ik_rotation_tol > 0):
            raise ValueError("IK tolerances must be > 0")


@dataclass
class NewTrajectory:
    """A new demonstration (see the module docstring for the conventions)."""

    t: np.ndarray
    q: np.ndarray
    gripper: np.ndarray
    action_q: np.ndarray
    action_gripper: np.ndarray
    object_poses: dict[str, np.ndarray]
    segments: list[dict]
    objects: dict[str, dict]
    validation: dict
    planner: dict = field(default_factory=dict)


@dataclass(eq=False)
class _State:
    """Collision state of a stretch of frames."""

    world: dict
    held: str | None
    G: np.ndarray | None
    allowed: frozenset = frozenset()
    skill_object: str | None = None

    def apply(self, scene: SceneCollision) -> None:
        if getattr(scene, "_applied", None) is not self:
            scene.set_state(self.world, self.held, self.G, set(self.allowed), self.skill_object)
            scene._applied = self


class Augmenter:
    """Everything about one twin that does not depend on the sample: the source, the Pinocchio
    model, the collision scene and the limits. :func:`augment_trajectory` keeps one per twin."""

    def __init__(self, twin, obstacles: tuple[BoxObstacle, ...] = ()) -> None:
        try:
            self.src: SourceDemo = source_demo(twin)
        except SourceError as exc:
            raise Rejected("source", str(exc)) from exc
        self.twin = twin
        self.kin = PinRobot(twin.robot)
        self.convention, self.convention_note = _convention(twin)
        self._limit_positions()
        self.spline = SourceSpline(self.kin, self.src.q, self.src.gripper, self.src.tcp)
        self.commands = SourceCommands(self.src.commands, self.kin.dof, self.src.fps)
        self.scene = SceneCollision(twin, self.kin, self.src, obstacles=tuple(obstacles))
        self.skill_allowed = [frozenset(self.scene.skill_allowances(s)) for s in self.src.skills]
        self.footprints = {name: solid_points(twin, name) for name in twin.objects}  # seen from above
        robot = twin.robot
        self.dt = 1.0 / self.src.fps
        # the replay also refuses a step above max_step_deg between two frames: at the parent's fps
        # that is a speed limit too
        from manisplat.drivers.piper.trajectory import ReplayLimits
        step_speed = math.radians(ReplayLimits().max_step_deg) / self.dt
        self.vlim = np.minimum(robot.velocity_limits.astype(float), step_speed)
        self.alim = robot.acceleration_limits.astype(float)
        lo, hi = robot.gripper.width_range if robot.gripper else (0.0, GRIPPER_OPEN)
        self.gripper_range = (float(lo), float(hi))

    def _limit_positions(self) -> None:
        """Joint limits = the model's, intersected with the arm's own (built-in PiPER) limits mapped
        into the episode's convention, which is what the replay checks."""
        lo, hi = self.kin.lower.copy(), self.kin.upper.copy()
        if self.convention is not None:
            from manisplat.augment.validation import _arm
            arm = _arm()
            a = self.convention.from_arm(arm.lower)
            b = self.convention.from_arm(arm.upper)
            lo, hi = np.maximum(lo, np.minimum(a, b)), np.minimum(hi, np.maximum(a, b))
        self.kin.lower, self.kin.upper = lo, hi

    # ------------------------------------------------------------------ objects over source time
    def _object_plan(self, targets: dict[str, ObjectTarget],
                     symmetries: dict[str, Symmetry] | None = None) -> dict[str, dict]:
        """Per object: where it starts and is left ("T_start", "T_place"), the source poses its
        skills move from ("T_src_start", "T_src_place") and its grasp offset "G", the last three
        turned by the symmetry turn of its pick ("turn_deg"); "T_place" by the place's turn too.
        Symmetries of objects this arm's source does not hold are ignored (another arm's)."""
        unknown = set(targets) - set(self.src.objects)
        if unknown:
            raise ValueError(f"targets for unknown objects {sorted(unknown)}; the twin's objects are "
                             f"{list(self.src.objects)}")
        plan = {}
        for name, obj in self.src.objects.items():
            tgt = targets.get(name)
            T_start = tgt.T_start if tgt is not None else obj.T_rest
            if obj.T_placed is None:
                T_place = None
            elif tgt is not None and tgt.T_place is not None:
                T_place = tgt.T_place
            else:
                T_place = obj.T_placed
            S = place_turn = np.eye(4)
            symmetry = (symmetries or {}).get(name)
            if symmetry is not None and obj.G is not None:
                axis = self.symmetry_axis(name)
                S = wrist_keeping_turn(symmetry, obj.T_rest, T_start, axis)
                if T_place is not None:
                    place_turn = wrist_keeping_turn(symmetry, obj.T_placed, T_place, axis)
                    T_place = T_place @ place_turn @ np.linalg.inv(S)
            unturn = np.linalg.inv(S)
            plan[name] = {"T_start": T_start, "T_place": T_place, "src": obj,
                          "T_src_start": obj.T_rest @ unturn,
                          "T_src_place": None if obj.T_placed is None else obj.T_placed @ unturn,
                          "G": None if obj.G is None else obj.G @ unturn,
                          "turn_deg": (_turn_deg(T_start, S), _turn_deg(T_place, place_turn))
                          if symmetry is not None else None}
        return plan

    def symmetry_axis(self, name: str) -> np.ndarray:
        """A point [3] (object frame, m) of the vertical axis a symmetric ``name`` turns about
        (:func:`~manisplat.augment.symmetry.axis_point`; its source start pose says where up is)."""
        obj = self.src.objects[name]
        up = obj.T_rest[2, :3]  # the base's z in the object frame
        return axis_point(np.linalg.inv(obj.G), self.scene.object_box[name][1], up)

    def _world_at(self, plan: dict, s: float) -> tuple[dict, str | None]:
        """Objects on the table at source time ``s`` (name -> pose) and the one held, if any."""
        world, held = {}, None
        for name, p in plan.items():
            obj = p["src"]
            if obj.grasp is None or s < obj.grasp:
                world[name] = p["T_start"]
            elif obj.release is None or s < obj.release:
                held = name
            else:
                world[name] = p["T_place"]
        return world, held

    # ------------------------------------------------------------------ the whole demonstration
    def run(self, targets: dict[str, ObjectTarget], config: AugmentConfig,
            start_q: np.ndarray | None = None) -> NewTrajectory:
        """The new demonstration with the objects at ``targets``, its first motion planned from
        ``start_q`` [dof] (rad; None: the source's first joints). Raises :class:`Rejected`."""
        timings = {"ik_s": 0.0, "planning_s": 0.0, "timing_s": 0.0, "validation_s": 0.0}
        src, kin = self.src, self.kin
        q_first = src.q[0] if start_q is None else self._start(start_q)
        plan = self._object_plan(targets, config.symmetries)
        tol_pos, tol_rot = config.ik_position_tol, config.ik_rotation_tol

        # objects placed where other things are
        t0 = time.perf_counter()
        self._check_placements(plan)
        self._check_support(plan, config.max_support_step)

        # 1. skills
        skills: list[SkillResult] = []
        transforms = []
        for i, spec in enumerate(src.skills):
            p = plan[spec.object]
            if spec.relative_to == "place":
                T_new, T_src = p["T_place"], p["T_src_place"]
            else:
                T_new, T_src = p["T_start"], p["T_src_start"]
            D = T_new @ np.linalg.inv(T_src)
            transforms.append((D, T_new, T_src))
            skills.append(solve_skill(kin, self.spline, spec.first, spec.last, D, dt=self.dt, vlim=self.vlim,
                                      alim=self.alim, tol_pos=tol_pos, tol_rot=tol_rot, commands=self.commands,
                                      margin=config.headroom,
                                      seed=config.seed, name=f"{spec.name} ({spec.object})",
                                      min_slow=config.min_slow.get(spec.name, 1.0)))
        timings["ik_s"] += time.perf_counter() - t0

        # 2. the timeline: motion, skill, motion, ..., motion
        pieces: list[dict] = []
        vl = self.vlim * config.speed * config.headroom
        al = self.alim * config.speed * config.headroom
        attempts = []
        n = len(src.skills)
        for i in range(n + 1):
            prev = skills[i - 1] if i > 0 else None
            nxt = skills[i] if i < n else None
            if prev is None and not self.plans_first_motion:
                pass
            elif nxt is None and src.skills[-1].last == src.n_frames - 1:
                pass
            else:
                q_a = prev.q[-1] if prev is not None else q_first
                q_b = nxt.q[0] if nxt is not None else src.q[-1]
                v_a = _end_velocity(prev.q, self.dt) if prev is not None else np.zeros(kin.dof)
                v_b = _start_velocity(nxt.q, self.dt) if nxt is not None else np.zeros(kin.dof)
                s_a = src.skills[i - 1].last if prev is not None else 0.0
                s_b = src.skills[i].first if nxt is not None else float(src.n_frames - 1)
                width = float(prev.gripper[-1]) if prev is not None else float(src.gripper[0])
                name = _motion_name(i, n, src)
                piece = self._motion(name, q_a, q_b, v_a, v_b, width, plan, 0.5 * (s_a + s_b), vl, al, config,
                                     seed=config.seed * 1009 + i, timings=timings, attempts=attempts)
                piece["source_gap"] = (s_a, s_b)
                pieces.append(piece)
            if nxt is not None:
                pieces.append({"kind": "skill", "index": i, "result": nxt})
        # settle at the end when the last frame is still moving
        last_q = pieces[-1]["result"].q if pieces[-1]["kind"] == "skill" else pieces[-1]["q"]
        v_end = _end_velocity(last_q, self.dt) if len(last_q) >= 2 else np.zeros(kin.dof)
        if pieces[-1]["kind"] == "skill" and np.abs(v_end).max() > REST_SPEED:  # a motion ends at rest
            width = float(pieces[-1]["result"].gripper[-1])
            pieces.append(self._settle(last_q[-1], v_end, width, plan, float(src.n_frames - 1), config, timings, attempts))

        # 3. assemble frames
        trajectory = self._assemble(pieces, skills, transforms, plan, config, timings, attempts)
        trajectory.planner["start_offset_deg"] = np.degrees(q_first - src.q[0]).round(3).tolist()
        return trajectory

    @property
    def plans_first_motion(self) -> bool:
        """Whether a motion leads into the source's first skill (or the arm has none), so that a new
        start can be planned from."""
        return not self.src.skills or self.src.skills[0].first > 0

    def sample_start(self, rng: Draws, half_range: float) -> np.ndarray:
        """First joints (rad) for a new demonstration: the source's moved by up to +-``half_range``
        rad each, within the limits the augmentation plans in."""
        return sample_start(rng, self.src.q[0], half_range, self.kin.lower, self.kin.upper)

    def _start(self, start_q: np.ndarray) -> np.ndarray:
        """``start_q`` checked: finite, one value per joint, and a first motion there is to plan."""
        start_q = np.asarray(start_q, np.float64)
        if start_q.shape != (self.kin.dof,) or not np.isfinite(start_q).all():
            raise ValueError(f"start_q must be {self.kin.dof} finite joint positions, got shape {start_q.shape}")
        if not self.plans_first_motion:
            raise ValueError("the source's first skill begins at its first frame: there is no first motion to "
                             "plan from another start")
        return start_q

    def _check_placements(self, plan: dict) -> None:
        """A moved object must not overlap other objects, obstacles or the background."""
        import coal
        import pinocchio as pin
        scene = self.scene
        for name, p in plan.items():
            if name not in scene.object_geom or not p["src"].manipulated:
                continue
            extents, centre = scene.object_box[name]
            box = coal.Box(*extents)
            for which in ("T_start", "T_place"):
                T = p[which]
                if T is None:
                    continue
                M = pin.SE3(T[:3, :3], T[:3, 3]) * pin.SE3(np.eye(3), centre)
                tf = coal.Transform3s(M.rotation, M.translation)
                others = [(f"object:{o}", scene.object_box[o], plan[o]["T_start"]) for o in plan
                          if o != name and o in scene.object_box]
                for label, (ext, cen), T2 in others:
                    M2 = pin.SE3(T2[:3, :3], T2[:3, 3]) * pin.SE3(np.eye(3), cen)
                    if coal.collide(box, tf, coal.Box(*ext), coal.Transform3s(M2.rotation, M2.translation),
                                    coal.CollisionRequest(), coal.CollisionResult()):
                        raise Rejected("object_collision", f"{name} at its new {which[2:]} pose overlaps {label}")
                for gid in [*scene.obstacle_geoms] + ([scene.background_geom] if scene.background_geom is not None else []):
                    go = scene.gm.geometryObjects[gid]
                    Mo = go.placement
                    if coal.collide(box, tf, go.geometry, coal.Transform3s(Mo.rotation, Mo.translation),
                                    coal.CollisionRequest(), coal.CollisionResult()):
                        raise Rejected("object_collision", f"{name} at its new {which[2:]} pose overlaps {go.name}")

    def _check_support(self, plan: dict, max_step: float) -> None:
        """A moved object must rest with its centre well inside the surface it is set down on
        (:meth:`manisplat.twin.support.SupportMap.edge_drop`)."""
        support = self.twin.support
        if support is None:
            return
        for name, p in plan.items():
            if not p["src"].manipulated:
                continue
            footprint = self.footprints[name]
            for which in ("T_start", "T_place"):
                T = p[which]
                if T is None:
                    continue
                drop = support.edge_drop(footprint @ T[:2, :3].T + T[:2, 3])
                if drop is not None and drop > support.smallest_edge(max_step):
                    raise Rejected("unstable_support", f"{name} at its new {which[2:]} pose would rest on the edge of a "
                                                       f"surface: it falls away {drop * 1e3:.1f} mm (more than "
                                                       f"{support.smallest_edge(max_step) * 1e3:g} mm) near the "
                                                       "object's centre")

    def _motion(self, name, q_a, q_b, v_a, v_b, width, plan, s_mid, vl, al, config, *, seed, timings, attempts) -> dict:
        world, held = self._world_at(plan, s_mid)
        G = plan[held]["G"] if held is not None else None
        state = _State(world, held, G)
        state.apply(self.scene)
        t0 = time.perf_counter()
        path = plan_path(self.scene, q_a, q_b, width, lower=self.kin.lower, upper=self.kin.upper,
                         timeout=config.planner_timeout_s, max_checks=config.planner_checks, seed=seed, name=name)
        timings["planning_s"] += time.perf_counter() - t0
        record = {"segment": name, "method": path.method, "plan_s": round(path.seconds, 4), "checks": path.checks,
                  "waypoints": len(path.waypoints)}
        waypoints = path.waypoints
        for attempt in range(3):
            t0 = time.perf_counter()
            timed, err = self._time_path(waypoints, v_a, v_b, vl, al, config)
            timings["timing_s"] += time.perf_counter() - t0
            record["joined"] = "at speed"
            if timed is None:
                # the path turns too sharply to be joined at the skills' speeds: stop at the ends
                timed, method = self._through_rest(name, q_a, q_b, v_a, v_b, width, vl, al, config,
                                                   seed + 7 * attempt, err, timings)
                record.update(joined="at rest", method=method)
            # the commanded path is linear between frames: check exactly that, and the limits
            t0 = time.perf_counter()
            problem = self._departure(timed.q, width)
            timings["planning_s"] += time.perf_counter() - t0
            if problem is None:
                record.update(frames=len(timed.q) - 1, duration_s=round(timed.duration, 4),
                              optimal_s=round(timed.optimal, 4), timing_attempts=attempt + 1)
                attempts.append(record)
                return {"kind": "motion", "name": name, "q": timed.q, "width": width, "state": state}
            # the timed spline left the checked polyline (or the limits): follow it more closely, or plan around
            t0 = time.perf_counter()
            if attempt == 0:
                waypoints = _densify(waypoints, 0.05)
            else:
                replanned = plan_path(self.scene, q_a, q_b, width, lower=self.kin.lower, upper=self.kin.upper,
                                      timeout=config.planner_timeout_s, max_checks=config.planner_checks, seed=seed + 7,
                                      name=name, straight=False)
                waypoints = _densify(replanned.waypoints, 0.05)
                record["method"] = replanned.method
            timings["planning_s"] += time.perf_counter() - t0
        what = "collides" if problem == "collision" else "leaves the joint limits"
        raise Rejected(problem, f"{name}: the timed motion {what} after re-planning")

    def _departure(self, q: np.ndarray, width: float) -> str | None:
        """Why the timed motion ``q`` [n, dof] cannot be commanded: "limits" (a frame outside the
        joint limits, as the validation judges it), "collision" (the frames' joint-linear path
        collides), or None."""
        if not within_limits(q, self.kin.lower, self.kin.upper):
            return "limits"
        return None if path_free(self.scene, q, width) else "collision"

    def _time_path(self, waypoints, v_a, v_b, vl, al, config) -> tuple[TimedMotion | None, str]:
        """Timed along ``waypoints`` within ``speed`` x the limits, else the full limits, else
        (a planner's polyline) densified knots; ``(None, last error)`` when none can be timed."""
        options = [(waypoints, vl, al), (waypoints, self.vlim * config.headroom, self.alim * config.headroom)]
        if len(waypoints) > 2:  # a planner's polyline: more knots give the spline local control
            options.append((_densify(waypoints, 0.05), self.vlim * config.headroom, self.alim * config.headroom))
        err = ""
        for wps, lim_v, lim_a in options:
            try:
                return time_motion(wps, v_a, v_b, vlim=lim_v, alim=lim_a, dt=self.dt, profile=config.profile), ""
            except TimingError as exc:
                err = str(exc)
        return None, err

    def _stop_point(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Where the arm comes to rest from ``q`` moving at ``v`` (rad/s) when braking along ``v``
        at half the acceleration limit (clipped to the joint limits)."""
        stop_t = float((np.abs(v) / (0.5 * self.alim)).max())
        return np.clip(q + v * stop_t / 2, self.kin.lower, self.kin.upper)

    def _through_rest(self, name, q_a, q_b, v_a, v_b, width, vl, al, config, seed, why,
                      timings) -> tuple[TimedMotion, str]:
        """The fallback when no spline joins the skills at their own speeds (a planner's path that
        turns sharply near an end): brake along the last skill's velocity to rest, the path
        re-planned from rest to rest, and speed up into the next skill along its first velocity
        (the mirror of braking). Returns the timed motion and how its rest-to-rest path was
        planned ("straight" or "rrtconnect"). Raises :class:`Rejected`."""
        lim_v, lim_a = self.vlim * config.headroom, self.alim * config.headroom
        moving_a, moving_b = np.abs(v_a).max() >= REST, np.abs(v_b).max() >= REST
        rest_a = self._stop_point(q_a, v_a) if moving_a else q_a
        rest_b = self._stop_point(q_b, -v_b) if moving_b else q_b
        t0 = time.perf_counter()
        path = plan_path(self.scene, rest_a, rest_b, width, lower=self.kin.lower, upper=self.kin.upper,
                         timeout=config.planner_timeout_s, max_checks=config.planner_checks, seed=seed, name=name)
        timings["planning_s"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        zero = np.zeros_like(v_a)
        middle, err = self._time_path(path.waypoints, zero, zero, vl, al, config)
        try:
            if middle is None:
                raise TimingError(err)
            parts = [middle.q]
            if moving_a:
                parts.insert(0, time_motion(np.stack([q_a, rest_a]), v_a, zero, vlim=lim_v, alim=lim_a, dt=self.dt).q[:-1])
            if moving_b:
                parts.append(time_motion(np.stack([rest_b, q_b]), zero, v_b, vlim=lim_v, alim=lim_a, dt=self.dt).q[1:])
        except TimingError as exc:
            raise Rejected("timing", f"{name}: no time-parametrization within the limits ({why}; and through rest: "
                                     f"{exc})") from exc
        finally:
            timings["timing_s"] += time.perf_counter() - t0
        q = np.concatenate(parts)
        return TimedMotion(q, (len(q) - 1) * self.dt, middle.optimal, middle.sample), path.method

    def _settle(self, q_end, v_end, width, plan, s, config, timings, attempts) -> dict:
        q_stop = self._stop_point(q_end, v_end)
        world, held = self._world_at(plan, s)
        state = _State(world, held, plan[held]["G"] if held else None)
        state.apply(self.scene)
        t0 = time.perf_counter()
        try:
            timed = time_motion(np.stack([q_end, q_stop]), v_end, np.zeros_like(v_end),
                                vlim=self.vlim * config.headroom, alim=self.alim * config.headroom, dt=self.dt)
        except TimingError as exc:
            raise Rejected("timing", f"M_settle: {exc}") from exc
        timings["timing_s"] += time.perf_counter() - t0
        attempts.append({"segment": "M_settle", "method": "stop along the last velocity", "frames": len(timed.q) - 1,
                         "duration_s": round(timed.duration, 4)})
        return {"kind": "motion", "name": "M_settle", "q": timed.q, "width": width, "state": state,
                "source_gap": (s, s)}

    def _assemble(self, pieces, skills, transforms, plan, config, timings, attempts) -> NewTrajectory:
        src, kin = self.src, self.kin
        qs, grip, cmd, press, svals, states, segments = [], [], [], [], [], [], []
        skill_errors, ik_errors = [], []
        frame = 0
        for k, piece in enumerate(pieces):
            if piece["kind"] == "motion":
                q = piece["q"]
                # interior frames only: the ends are the neighbouring skills' frames (or the
                # source's first/last joints when nothing is there)
                begin = 0 if k == 0 else 1
                end = len(q) if k == len(pieces) - 1 else len(q) - 1
                body = q[begin:end]
                if not len(body):
                    continue
                s_a, s_b = piece["source_gap"]
                s_mid = 0.5 * (s_a + s_b)
                for row in body:
                    qs.append(row)
                    grip.append(piece["width"])
                    cmd.append(_command(src, s_mid))
                    press.append(np.zeros(kin.dof))
                    svals.append(s_mid)
                    states.append(piece["state"])
                segments.append({"kind": "motion", "name": piece["name"], "object": None,
                                 "frames": [frame, frame + len(body) - 1], "source_frames": None, "T": None})
                frame += len(body)
            else:
                i = piece["index"]
                spec, res = src.skills[i], piece["result"]
                D, T_new, T_src = transforms[i]
                first = frame
                tcp_new = kin.tcp_batch(res.q)
                # collision states inside the skill: split where the object is grasped / released
                prev_key = None
                for j, s in enumerate(res.s):
                    world, held = self._world_at(plan, s)
                    key = (tuple(sorted(world)), held)
                    if key != prev_key:
                        allowed = set(self.skill_allowed[i])
                        if held is not None:
                            allowed |= {self.scene.pair_index[_pair(self.scene, f"held:{held}", "table")]}
                        st = _State(world, held, plan[held]["G"] if held else None, frozenset(allowed),
                                    spec.object)
                        prev_key = key
                    qs.append(res.q[j])
                    grip.append(res.gripper[j])
                    cmd.append(_command(src, s))
                    press.append(res.press[j])
                    svals.append(s)
                    states.append(st)
                frame += len(res.q)
                ik_errors.append((res.pos_err, res.rot_err))
                skill_errors.append(skill_relative_errors(tcp_new, np.broadcast_to(T_new, tcp_new.shape),
                                                          res.tcp_source, np.broadcast_to(T_src, tcp_new.shape)))
                segments.append({"kind": "skill", "name": spec.name, "object": spec.object,
                                 "frames": [first, frame - 1], "source_frames": [spec.first, spec.last],
                                 "T": D.tolist(), "slowed": round(float(res.slow), 4)})
        q = np.asarray(qs)
        # the source's signal, clipped into the gripper's range (recordings overshoot by ~1e-7 m)
        gripper = np.clip(np.asarray(grip, np.float64), *self.gripper_range)
        action_gripper = np.asarray(cmd, np.float64)
        T = len(q)
        t = np.arange(T) / src.fps
        action_q = self.commands.commanded(q, np.asarray(press))

        # objects per frame
        tcp_all = kin.tcp_batch(q)
        object_poses = {}
        for name in self.twin.object_poses:
            p = plan.get(name)
            rows = np.empty((T, 4, 4))
            for f in range(T):
                world, held = self._world_at(plan, svals[f]) if p is not None else ({}, None)
                if held == name:
                    rows[f] = tcp_all[f] @ p["G"]
                elif p is not None and name in world:
                    rows[f] = world[name]
                else:
                    rows[f] = self.twin.object_poses[name][0]
            object_poses[name] = rows

        # validation
        t0 = time.perf_counter()
        hit = dense_collision(self.scene, q, gripper, states, 0, T - 1)
        if hit is not None:
            f, pair = hit
            seg = next((s for s in segments if s["frames"][0] <= f <= s["frames"][1]), {"name": "?"})
            raise Rejected("collision", f"{seg.get('name')}: frames {f}-{f + 1} collide"
                                        + (f" ({pair[0]} with {pair[1]})" if pair else ""))
        validation = check_all(t=t, q=q, action_q=action_q, gripper=gripper, action_gripper=action_gripper,
                               convention=self.convention, lower=kin.lower, upper=kin.upper, tol_pos=config.ik_position_tol,
                               tol_rot=config.ik_rotation_tol, skill_errors=skill_errors, ik_errors=ik_errors)
        clear = np.inf
        for seg in segments:
            if seg["kind"] != "motion":
                continue
            for f in range(seg["frames"][0], seg["frames"][1] + 1, 2):
                states[f].apply(self.scene)
                clear = min(clear, self.scene.clearance(q[f], gripper[f]))
        validation["collision_free"] = True
        validation["collision_resolution_rad"] = RESOLUTION
        validation["min_clearance_motions_m"] = None if math.isinf(clear) else round(float(clear), 5)
        validation["table_z_m"] = round(float(self.scene.table_z), 5)
        validation["table_z_estimates_m"] = {k: round(v, 5) for k, v in self.scene.table_estimates.items()}
        validation["background_points"] = int(len(self.scene.background_points))
        timings["validation_s"] += time.perf_counter() - t0

        objects = {name: {"T_start": object_poses[name][0].tolist(), "T_end": object_poses[name][-1].tolist()}
                   for name in object_poses}
        planner = {"libraries": {"kinematics_ik": "pinocchio (pin) Levenberg-Marquardt, warm-started",
                                 "collision": "coal via pinocchio GeometryModel",
                                 "planner": "straight joint line, else OMPL RRTConnect + PathSimplifier.simplifyMax",
                                 "timing": "toppra (TOPPRA, ParametrizeConstAccel)" if config.profile == "time-optimal"
                                 else "quintic time scaling within the limits (toppra's spline path)"},
                   "speed": config.speed, "profile": config.profile, "seed": config.seed, "segments": attempts,
                   "skills": [{"name": s.name, "object": s.object, "slowed": round(float(r.slow), 4),
                               "ik_iterations": r.ik_iterations, "ik_restarts": r.ik_restarts}
                              for s, r in zip(self.src.skills, skills)],
                   "times_s": {k: round(v, 5) for k, v in timings.items()},
                   "commands": {"lead_frames": round(self.commands.lead, 4), "press": self.commands.recorded},
                   "symmetry_turns_deg": {name: {"pick": p["turn_deg"][0], "place": p["turn_deg"][1]}
                                          for name, p in plan.items() if p["turn_deg"] is not None},
                   "convention": self.convention_note}
        return NewTrajectory(t=t, q=q, gripper=gripper, action_q=action_q, action_gripper=action_gripper,
                             object_poses=object_poses, segments=segments, objects=objects, validation=validation,
                             planner=planner)


# ---------------------------------------------------------------------- helpers
def _turn_deg(T: np.ndarray | None, S: np.ndarray) -> float:
    """The turn about the vertical (deg, rounded) of the object-frame turn ``S`` [4, 4] of an object at ``T``."""
    if T is None:
        return 0.0
    return round(math.degrees(yaw_of(T[:3, :3] @ S[:3, :3] @ T[:3, :3].T)), 3)


def _pair(scene: SceneCollision, a: str, b: str) -> tuple[int, int]:
    ids = {scene.gm.geometryObjects[i].name: i for i in range(len(scene.gm.geometryObjects))}
    x, y = ids[a], ids[b]
    return (min(x, y), max(x, y))


def _command(src: SourceDemo, s: float) -> float:
    """The gripper command at source time ``s`` (frames): what the source commanded there
    (interpolated) where it was recorded, else open or closed by its grasp and release events."""
    recorded = src.commands.gripper if src.commands is not None else None
    if recorded is not None:
        return float(np.interp(s, np.arange(len(recorded), dtype=np.float64), recorded[:, 0]))
    for obj in src.objects.values():
        if obj.grasp is not None and s >= obj.grasp and (obj.release is None or s < obj.release):
            return GRIPPER_CLOSED
    return GRIPPER_OPEN


def _start_velocity(q: np.ndarray, dt: float) -> np.ndarray:
    if len(q) >= 3:
        return (-3 * q[0] + 4 * q[1] - q[2]) / (2 * dt)
    return (q[1] - q[0]) / dt if len(q) == 2 else np.zeros(q.shape[1])


def _end_velocity(q: np.ndarray, dt: float) -> np.ndarray:
    if len(q) >= 3:
        return (3 * q[-1] - 4 * q[-2] + q[-3]) / (2 * dt)
    return (q[-1] - q[-2]) / dt if len(q) == 2 else np.zeros(q.shape[1])


def _densify(waypoints: np.ndarray, step: float) -> np.ndarray:
    out = [waypoints[0]]
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        n = max(1, int(np.ceil(np.abs(b - a).max() / step)))
        out += [a + (b - a) * u for u in np.linspace(0, 1, n + 1)[1:]]
    return np.asarray(out)


def _motion_name(i: int, n: int, src: SourceDemo) -> str:
    if i == 0:
        return "M_approach"
    if i == n:
        return "M_return"
    return "M_transfer" if any(o.grasp is not None and src.skills[i - 1].last >= o.grasp and
                               (o.release is None or src.skills[i].first <= o.release)
                               for o in src.objects.values()) else f"M_{i}"


def _convention(twin):
    try:
        from manisplat.drivers.piper.convention import convention_for
        conv = convention_for(twin.robot_description)
        return conv, conv.name
    except Exception as exc:  # an unknown description: validated in its own convention
        return None, f"unknown to manisplat-replay ({type(exc).__name__}: {exc}); limits checked as given"


_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def augmenter_for(twin, obstacles: tuple[BoxObstacle, ...] = ()) -> Augmenter:
    """The :class:`Augmenter` of ``twin`` (built once per twin and obstacle set)."""
    key = tuple((tuple(map(float, o.extents)), np.asarray(o.T, np.float64).tobytes()) for o in obstacles)
    per_twin = _CACHE.setdefault(twin, {})
    if key not in per_twin:
        per_twin[key] = Augmenter(twin, obstacles)
    return per_twin[key]


def augment_trajectory(twin, targets: dict[str, ObjectTarget], config: AugmentConfig | None = None,
                       start_q: np.ndarray | None = None) -> NewTrajectory:
    """A new, validated demonstration with the objects at ``targets``, starting from the arm's
    ``start_q`` [dof] (rad; None: the source's first joints); raises :class:`Rejected`."""
    config = config or AugmentConfig()
    return augmenter_for(twin, tuple(config.obstacles)).run(targets, config, start_q)
