"""Geometry ops: error and time per call, ours vs kornia.

For each op of ``manisplat.geometry`` (so3_exp, so3_log, quat_to_matrix, matrix_to_quat,
se3_exp, se3_log, rotation_angle, kabsch, slerp, interpolate_poses) and the kornia equivalent
where one exists, in float64 and float32: the median time per call at batch 1 and 10000 and the
maximum error over an error set of random inputs plus the special angles 0, 1e-12, 1e-8,
pi - 1e-9 and pi (on random and coordinate axes).

Errors are measured against float64 oracles independent of both implementations:
``torch.linalg.matrix_exp`` of the skew (3x3) or twist (4x4) matrix for exp and slerp, the
round trip ``matrix_exp(log(R))`` vs R for log, the half-angle quaternion for matrix_to_quat, the
exact angle of rotations built about a known axis for rotation_angle, and the known R, t for
Kabsch. float32 inputs are rounded copies of the float64 ones; where the oracle is a function of
the input (exp, quat_to_matrix, round trips) it is evaluated on the rounded input, so the error is
the function's own; elsewhere (matrix_to_quat, rotation_angle, kabsch, slerp, interpolate_poses)
it includes the input rounding (~6e-8).

Rows: op, impl, dtype, batch, us_per_call, ours_over_peer (time ratio on our rows; peer = kornia,
or acos for rotation_angle), max_err (whole error set), err_special (special angles only),
err_near0 / err_near_pi (rotation_angle: angles in [0, 1e-4] and [pi - 1e-4, pi]).
"""

from __future__ import annotations

import math
import os
from typing import Callable

import torch
from kornia.geometry import conversions as kc
from kornia.geometry.liegroup import Se3 as KSe3
from kornia.geometry.liegroup import So3 as KSo3
from kornia.geometry.quaternion import Quaternion as KQuaternion

from benchmarks._harness import time_call
from manisplat import geometry as mg

SPECIAL = [0.0, 1e-12, 1e-8, math.pi - 1e-9, math.pi]
NEAR = [0.0, 1e-12, 1e-10, 1e-9, 1e-8, 2e-8, 5e-8, 1e-7, 1e-6, 1e-5, 1e-4]
F64 = torch.float64


# ---------------------------------------------------------------------------------------------
# float64 oracles, written here (no manisplat, no kornia)
def _skew(w: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> [..., 3, 3] cross-product matrix."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z], -1).reshape(
        *w.shape[:-1], 3, 3
    )


def _exp3(w: torch.Tensor) -> torch.Tensor:
    return torch.linalg.matrix_exp(_skew(w.to(F64)))


def _exp4(xi: torch.Tensor) -> torch.Tensor:
    """Twist (v, w) [..., 6] -> matrix_exp of the 4x4 twist matrix."""
    xi = xi.to(F64)
    M = torch.zeros(*xi.shape[:-1], 4, 4, dtype=F64)
    M[..., :3, :3] = _skew(xi[..., 3:])
    M[..., :3, 3] = xi[..., :3]
    return torch.linalg.matrix_exp(M)


def _rodrigues(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation about unit ``axis`` [..., 3] by ``angle`` [...] (float64 closed form)."""
    K = _skew(axis)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=F64) + s * K + (1 - c) * (K @ K)


def _quat_of_axis_angle(w: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) = (cos(theta/2), sin(theta/2) n), float64."""
    w = w.to(F64)
    theta = w.norm(dim=-1, keepdim=True)
    n = torch.where(theta > 0, w / torch.where(theta > 0, theta, torch.ones_like(theta)), torch.zeros_like(w))
    return torch.cat([torch.cos(theta / 2), torch.sin(theta / 2) * n], -1)


def _axis_angle_of_quat(q: torch.Tensor) -> torch.Tensor:
    """Inverse of the above for any (not nec. unit) quaternion, float64, via atan2."""
    q = q.to(F64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    nv = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(nv, q[..., :1])
    return torch.where(nv > 0, angle * v / torch.where(nv > 0, nv, torch.ones_like(nv)), torch.zeros_like(v))


def _quat_to_matrix64(q: torch.Tensor) -> torch.Tensor:
    return _exp3(_axis_angle_of_quat(q))


def _hamilton(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def _maxabs(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-sample max abs difference [B] of [B, ...] tensors (computed in float64)."""
    d = (a.detach().to(F64) - b.detach().to(F64)).abs()
    return d.reshape(d.shape[0], -1).amax(-1)


# ---------------------------------------------------------------------------------------------
# input sets
def _unit(n: int, gen: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, generator=gen, dtype=F64)
    return v / v.norm(dim=-1, keepdim=True)


def _angle_set(n: int, gen: torch.Generator, specials: list[float] = SPECIAL, per_special: int = 16):
    """(axes [M, 3], angles [M], special mask [M]): n random angles in [0, pi] then each special
    angle on the 3 coordinate axes (both signs) and on ``per_special`` random axes."""
    axes = [_unit(n, gen)]
    angles = [torch.rand(n, generator=gen, dtype=F64) * math.pi]
    coord = torch.cat([torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)])
    for a in specials:
        ax = torch.cat([coord, _unit(per_special, gen)])
        axes.append(ax)
        angles.append(torch.full((len(ax),), a, dtype=F64))
    axes_t, angles_t = torch.cat(axes), torch.cat(angles)
    special = torch.zeros(len(angles_t), dtype=torch.bool)
    special[n:] = True
    return axes_t, angles_t, special


# ---------------------------------------------------------------------------------------------
class Case:
    """One op: inputs per dtype, implementations, and an error function."""

    def __init__(self, name: str, make: Callable, impls: dict[str, Callable], error: Callable, peer: str | None):
        self.name, self.make, self.impls, self.error, self.peer = name, make, impls, error, peer


def _cases(n_err: int, gen: torch.Generator) -> list[Case]:
    cases = []

    # so3_exp ----------------------------------------------------------------------------------
    def make_exp(n, dtype, with_special=True):
        ax, an, sp = _angle_set(n, gen) if with_special else (_unit(n, gen), torch.rand(n, generator=gen, dtype=F64) * math.pi, None)
        return ((ax * an[:, None]).to(dtype),), sp

    cases.append(
        Case(
            "so3_exp",
            make_exp,
            {
                "ours": lambda w: mg.so3_exp(w),
                "kornia": lambda w: kc.axis_angle_to_rotation_matrix(w),
                "kornia.So3": lambda w: KSo3.exp(w).matrix(),
            },
            lambda out, w: _maxabs(out, _exp3(w)),
            "kornia",
        )
    )

    # so3_log ----------------------------------------------------------------------------------
    def make_log(n, dtype, with_special=True):
        (w,), sp = make_exp(n, F64, with_special)
        return (_exp3(w).to(dtype),), sp

    cases.append(
        Case(
            "so3_log",
            make_log,
            {
                "ours": lambda R: mg.so3_log(R),
                "kornia": lambda R: kc.rotation_matrix_to_axis_angle(R),
                "kornia.So3": lambda R: KSo3.from_matrix(R).log(),
            },
            lambda out, R: _maxabs(_exp3(out), R),
            "kornia",
        )
    )

    # quat_to_matrix ---------------------------------------------------------------------------
    def make_q(n, dtype, with_special=True):
        (w,), sp = make_exp(n, F64, with_special)
        return (_quat_of_axis_angle(w).to(dtype),), sp

    cases.append(
        Case(
            "quat_to_matrix",
            make_q,
            {"ours": lambda q: mg.quat_to_matrix(q), "kornia": lambda q: kc.quaternion_to_rotation_matrix(q)},
            lambda out, q: _maxabs(out, _quat_to_matrix64(q)),
            "kornia",
        )
    )

    # matrix_to_quat ---------------------------------------------------------------------------
    def make_m2q(n, dtype, with_special=True):
        (w,), sp = make_exp(n, F64, with_special)
        return (_exp3(w).to(dtype), _quat_of_axis_angle(w)), sp

    def err_m2q(out, R, q_true):
        out = out.detach().to(F64)
        return torch.minimum(_maxabs(out, q_true), _maxabs(out, -q_true))

    cases.append(
        Case(
            "matrix_to_quat",
            make_m2q,
            {"ours": lambda R, _q: mg.matrix_to_quat(R), "kornia": lambda R, _q: kc.rotation_matrix_to_quaternion(R)},
            err_m2q,
            "kornia",
        )
    )

    # se3_exp / se3_log ------------------------------------------------------------------------
    def make_xi(n, dtype, with_special=True):
        (w,), sp = make_exp(n, F64, with_special)
        v = 0.5 * torch.randn(len(w), 3, generator=gen, dtype=F64)
        return (torch.cat([v, w], -1).to(dtype),), sp

    cases.append(
        Case(
            "se3_exp",
            make_xi,
            {"ours": lambda xi: mg.se3_exp(xi), "kornia": lambda xi: KSe3.exp(xi).matrix()},
            lambda out, xi: _maxabs(out, _exp4(xi)),
            "kornia",
        )
    )

    def make_T(n, dtype, with_special=True):
        (xi,), sp = make_xi(n, F64, with_special)
        return (_exp4(xi).to(dtype),), sp

    cases.append(
        Case(
            "se3_log",
            make_T,
            {"ours": lambda T: mg.se3_log(T), "kornia": lambda T: KSe3.from_matrix(T).log()},
            lambda out, T: _maxabs(_exp4(out), T),
            "kornia",
        )
    )

    # rotation_angle ---------------------------------------------------------------------------
    def make_angle(n, dtype, with_special=True):
        if with_special:
            near = NEAR + [math.pi - a for a in NEAR]
            ax, an, sp = _angle_set(n, gen, specials=sorted(set(SPECIAL + near)), per_special=8)
        else:
            ax, an, sp = _unit(n, gen), torch.rand(n, generator=gen, dtype=F64) * math.pi, None
        return (_rodrigues(ax, an).to(dtype), an), sp

    def acos_angle(R):
        tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
        return torch.acos(((tr - 1) / 2).clamp(-1.0, 1.0))

    cases.append(
        Case(
            "rotation_angle",
            make_angle,
            {
                "ours": lambda R, _a: mg.rotation_angle(R),
                "acos": lambda R, _a: acos_angle(R),
                "kornia": lambda R, _a: kc.rotation_matrix_to_axis_angle(R).norm(dim=-1),
            },
            lambda out, R, a: (out.detach().to(F64) - a).abs(),
            "acos",
        )
    )

    # kabsch -----------------------------------------------------------------------------------
    N_PTS = 100

    def make_kabsch(n, dtype, with_special=True):
        (w,), sp = make_exp(n, F64, with_special)
        R = _exp3(w)
        t = torch.randn(len(w), 3, generator=gen, dtype=F64)
        P = 0.1 * torch.randn(len(w), N_PTS, 3, generator=gen, dtype=F64)
        Q = P @ R.transpose(-1, -2) + t[:, None, :]
        T = torch.eye(4, dtype=F64).repeat(len(w), 1, 1)
        T[:, :3, :3], T[:, :3, 3] = R, t
        return (P.to(dtype), Q.to(dtype), T), sp

    cases.append(
        Case(
            "kabsch",
            make_kabsch,
            {"ours": lambda P, Q, _T: mg.kabsch(P, Q).T},
            lambda out, P, Q, T: _maxabs(out, T),
            None,
        )
    )

    # slerp --------------------------------------------------------------------------------------
    def make_slerp(n, dtype, with_special=True):
        ax, an, sp = _angle_set(n, gen) if with_special else (_unit(n, gen), torch.rand(n, generator=gen, dtype=F64) * math.pi, None)
        m = len(an)
        w0 = _unit(m, gen) * (torch.rand(m, generator=gen, dtype=F64) * math.pi)[:, None]
        rel = ax * an[:, None]
        s = torch.rand(m, generator=gen, dtype=F64)
        R0 = _exp3(w0)
        R1 = R0 @ _exp3(rel)
        q0 = _quat_of_axis_angle(w0)
        q1 = _hamilton(q0, _quat_of_axis_angle(rel))
        # Both geodesics at a relative angle of exactly pi are correct: keep both oracles.
        s_d = s.to(dtype).to(F64)
        want_a = R0 @ _exp3(s_d[:, None] * rel)
        want_b = R0 @ _exp3(-s_d[:, None] * (2 * math.pi - an)[:, None] * ax)
        return (R0.to(dtype), R1.to(dtype), q0.to(dtype), q1.to(dtype), s.to(dtype), want_a, want_b), sp

    def slerp_kornia(R0, R1, q0, q1, s, *_):
        return KQuaternion(q0).slerp(KQuaternion(q1), s).data

    def err_slerp(out, R0, R1, q0, q1, s, want_a, want_b):
        out = out.detach().to(F64)
        if out.shape[-1] == 4:  # kornia: a quaternion
            out = _quat_to_matrix64(out)
        return torch.minimum(_maxabs(out, want_a), _maxabs(out, want_b))

    cases.append(
        Case(
            "slerp",
            make_slerp,
            {"ours": lambda R0, R1, q0, q1, s, *_: mg.slerp(R0, R1, s), "kornia": slerp_kornia},
            err_slerp,
            "kornia",
        )
    )

    # interpolate_poses ------------------------------------------------------------------------
    def make_interp(n, dtype, with_special=True):
        ax, an, sp = _angle_set(n, gen) if with_special else (_unit(n, gen), torch.rand(n, generator=gen, dtype=F64) * math.pi, None)
        m = len(an)
        w0 = _unit(m, gen) * (torch.rand(m, generator=gen, dtype=F64) * math.pi)[:, None]
        R0 = _exp3(w0)
        R1 = R0 @ _exp3(ax * an[:, None])
        t0, t1 = torch.randn(m, 3, generator=gen, dtype=F64), torch.randn(m, 3, generator=gen, dtype=F64)
        # Pose pairs at times (2j, 2j + 1); query j lies inside that interval.
        poses = torch.eye(4, dtype=F64).repeat(2 * m, 1, 1)
        poses[0::2, :3, :3], poses[1::2, :3, :3] = R0, R1
        poses[0::2, :3, 3], poses[1::2, :3, 3] = t0, t1
        times = torch.arange(2 * m, dtype=F64)
        query = (2 * torch.arange(m, dtype=F64) + torch.rand(m, generator=gen, dtype=F64)).to(dtype)
        s = query.to(F64) - 2 * torch.arange(m, dtype=F64)  # the fraction the rounded query asks for
        want = torch.eye(4, dtype=F64).repeat(m, 1, 1)
        want[:, :3, 3] = (1 - s)[:, None] * t0 + s[:, None] * t1
        want_b = want.clone()
        want[:, :3, :3] = R0 @ _exp3(s[:, None] * an[:, None] * ax)
        want_b[:, :3, :3] = R0 @ _exp3(-s[:, None] * (2 * math.pi - an)[:, None] * ax)
        return (times.to(dtype), poses.to(dtype), query, want, want_b), sp

    cases.append(
        Case(
            "interpolate_poses",
            make_interp,
            {"ours": lambda times, poses, query, *_: mg.interpolate_poses(times, poses, query)},
            lambda out, times, poses, query, want, want_b: torch.minimum(_maxabs(out, want), _maxabs(out, want_b)),
            None,
        )
    )
    return cases


def _timing_inputs(case: Case, batch: int, dtype: torch.dtype):
    args, _ = case.make(batch, dtype, with_special=False)
    return args


def _interleaved(calls: dict[str, Callable], batch: int, rounds: int) -> dict[str, float]:
    """Seconds per call of each implementation: the minimum over ``rounds`` interleaved rounds of
    the harness's median (so a burst of load from other processes hits every implementation alike
    and is then discarded)."""
    best = {k: math.inf for k in calls}
    for fn in calls.values():  # warm-up (kornia and torch lazily initialise on first use)
        fn()
    for _ in range(rounds):
        for impl, fn in calls.items():
            if batch == 1:
                t = time_call(fn, repeat=3, warmup=1, min_time=0.002)
            else:
                t = time_call(fn, repeat=3, warmup=1, min_time=0.005)
            best[impl] = min(best[impl], t)
    return best


def run(ctx) -> list[dict]:
    rounds = 2 if ctx.quick else 5
    load_before = os.getloadavg()[0]
    gen = torch.Generator().manual_seed(20261121)
    n_err = 1000 if ctx.quick else 10000
    batches = (1, 1000) if ctx.quick else (1, 10000)
    rows: list[dict] = []
    for case in _cases(n_err, gen):
        for dtype in (F64, torch.float32):
            # Errors: once per (op, dtype, impl) on the error set (independent of the timing batch).
            err_args, special = case.make(n_err, dtype)
            errs: dict[str, dict] = {}
            for impl, fn in case.impls.items():
                e = case.error(fn(*err_args), *err_args)
                info = {"max_err": float(e.max()), "err_special": float(e[special].max())}
                if case.name == "rotation_angle":
                    a = err_args[1]
                    info["err_near0"] = float(e[a <= 1e-4].max())
                    info["err_near_pi"] = float(e[a >= math.pi - 1e-4].max())
                    for label, probe in (("1e-8", 1e-8), ("pi-1e-9", math.pi - 1e-9)):
                        info[f"err_at_{label}"] = float(e[a == probe].max())
                errs[impl] = info
            for batch in batches:
                args = _timing_inputs(case, batch, dtype)
                times = _interleaved({impl: (lambda f=fn: f(*args)) for impl, fn in case.impls.items()}, batch, rounds)
                for impl in case.impls:
                    row = {
                        "op": case.name,
                        "impl": impl,
                        "dtype": str(dtype).removeprefix("torch."),
                        "batch": batch,
                        "us_per_call": times[impl] * 1e6,
                        "ours_over_peer": (times["ours"] / times[case.peer]) if (impl == "ours" and case.peer) else None,
                    }
                    info = errs[impl]
                    row["max_err"] = info["max_err"]
                    row["err_special"] = info["err_special"]
                    for k in ("err_near0", "err_near_pi"):
                        if k in info:
                            row[k] = info[k]
                    rows.append(row)
            if case.name == "rotation_angle":
                for impl, info in errs.items():
                    ctx.notes.append(
                        f"rotation_angle {impl} {str(dtype).removeprefix('torch.')}: error at angle 1e-8 = "
                        f"{info['err_at_1e-8']:.3g} rad, at pi-1e-9 = {info['err_at_pi-1e-9']:.3g} rad"
                    )
    ctx.notes.append(
        f"max_err is over {n_err} random inputs + special angles {SPECIAL} (on +-x, +-y, +-z and 16 random axes), "
        "the same for both batch rows; err_special is the max over the special angles only. Units: matrix/quaternion "
        "entries (exp, quat, slerp, interpolate_poses, kabsch: max |T - T_true|), round-trip matrix entries (log), rad "
        "(rotation_angle)."
    )
    ctx.notes.append(
        f"threads={ctx.threads}: 1-min load average {load_before:.2f} before, {os.getloadavg()[0]:.2f} after "
        f"({os.cpu_count()} CPUs, this run included); a load above the CPU count means other processes competed "
        "for the cores, which inflates the multi-threaded rows most"
    )
    ctx.notes.append(
        f"us_per_call: minimum over {rounds} interleaved rounds (ours, peers, ours, ...) of the median of 3 "
        "timed loops; this filters bursts of load from other processes on a shared machine."
    )
    ctx.notes.append(
        "kabsch: N=100 points per problem, batch = number of problems; slerp: ours takes matrices, kornia "
        "Quaternion.slerp takes quaternions (its error is measured after an exact float64 conversion); "
        "interpolate_poses batch = number of queries (2*batch sample poses); rotation_angle 'kornia' = "
        "|rotation_matrix_to_axis_angle(R)|."
    )
    return rows
