"""Calibration report: ``report.png`` (per-view residuals, residual scatter, closed forms vs
the refined result, latency curve), ``overlay_NNNNNN.png`` (detected corners in green, corners
projected through the calibrated chain in red, error vectors magnified) and ``report.html``."""

from __future__ import annotations

import html
import json
from pathlib import Path

import cv2
import numpy as np

from manisplat.calib.episode_solve import EpisodeSolve
from manisplat.calib.handeye import predicted_board_poses, to_problem
from manisplat.calib.latency import LatencyEstimate
from manisplat.episode import Episode

OVERLAY_GAIN = 20.0
"""Error vectors are drawn this many times longer than they are."""


def _figure(solved: EpisodeSolve, latency: LatencyEstimate | None, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = solved.result
    per = r.per_view()
    n_plots = 4 if latency is not None else 3
    fig, axes = plt.subplots(1, n_plots, figsize=(5 * n_plots, 4.2))
    frames = [p["frame"] for p in per]
    colors = ["tab:blue" if p["used"] else "tab:red" for p in per]
    axes[0].bar(range(len(per)), [p["rms_px"] for p in per], color=colors)
    axes[0].plot(range(len(per)), [p["max_px"] for p in per], "k.", label="max")
    axes[0].set_xticks(range(len(per)), [str(f) for f in frames], rotation=90, fontsize=7)
    axes[0].set_xlabel("frame (red: dropped)")
    axes[0].set_ylabel("corner reprojection error (px)")
    axes[0].set_title("per view: RMS (bars) and max (dots)")
    axes[0].legend()
    res = np.concatenate([x[m] for x, m in zip(r.refine.residuals, r.refine.inliers)])
    out = np.concatenate([x[~m] for x, m in zip(r.refine.residuals, r.refine.inliers)])
    axes[1].scatter(res[:, 0], res[:, 1], s=3, alpha=0.5, label=f"inliers ({len(res)})")
    if len(out):
        axes[1].scatter(out[:, 0], out[:, 1], s=6, c="r", label=f"outliers ({len(out)})")
    lim = max(0.5, float(np.percentile(np.abs(res), 99.5)) * 1.3)
    axes[1].set_xlim(-lim, lim)
    axes[1].set_ylim(-lim, lim)
    axes[1].set_aspect("equal")
    axes[1].set_xlabel("dx (px)")
    axes[1].set_ylabel("dy (px)")
    axes[1].set_title("corner residuals (detected - projected)")
    axes[1].legend(fontsize=8)
    names = [k for k, v in r.closed_forms.items() if "error" not in v]
    axes[2].barh(names, [r.closed_forms[k]["trans_diff_mm"] for k in names], color="tab:gray")
    axes[2].set_xlabel("distance to the refined T_mount_cam (mm)")
    axes[2].set_title(f"closed forms (start: {r.start})")
    for k, name in enumerate(names):
        axes[2].text(0, k, f" {r.closed_forms[name]['rot_diff_deg']:.3f} deg", va="center", fontsize=8)
    if latency is not None:
        axes[3].plot(latency.offsets_s * 1000, latency.scores)
        axes[3].axvline(latency.latency_s * 1000, color="r")
        axes[3].set_xlabel("offset (ms)")
        axes[3].set_ylabel("correlation")
        axes[3].set_title(f"latency {latency.latency_s * 1000:.1f} +- {latency.std_s * 1000:.1f} ms")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def overlay(image: np.ndarray, detected: np.ndarray, projected: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """RGB image with detected (green circles) and projected (red dots) corners and magnified
    error vectors (yellow; red for outliers)."""
    out = image.copy() if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    for d, p, ok in zip(detected, projected, inliers):
        dp = tuple(int(round(v)) for v in d)
        tip = tuple(int(round(v)) for v in p + OVERLAY_GAIN * (d - p))
        cv2.circle(out, dp, 5, (0, 200, 0), 1, cv2.LINE_AA)
        cv2.line(out, tuple(int(round(v)) for v in p), tip, (255, 220, 0) if ok else (255, 0, 0), 1, cv2.LINE_AA)
        cv2.circle(out, tuple(int(round(v)) for v in p), 1, (255, 0, 0), -1)
    return out


def write_report(solved: EpisodeSolve, out_dir: str | Path, calibration: dict, latency: LatencyEstimate | None = None,
                 max_overlays: int = 6) -> Path:
    """Write the report into ``out_dir``; returns the HTML path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _figure(solved, latency, out_dir / "report.png")
    r = solved.result
    ep = Episode.open(solved.episode)
    A = np.stack([ep.frames.q[v.index] for v in solved.views])
    from manisplat.robot import load_robot
    robot = load_robot(ep.meta.robot.description, base_dir=ep.path, load_meshes=False)
    A = robot.link_pose(A, r.link).numpy()
    Apb, _ = to_problem(r.mount, A, np.stack([v.T_cam_board for v in solved.views]))
    B = predicted_board_poses(r.mount, Apb, r.refine.P, r.refine.Q)
    worst = np.argsort([-p["rms_px"] for p in r.per_view()])
    chosen = sorted(set(worst[: max_overlays // 2].tolist() + np.linspace(0, len(solved.views) - 1,
                                                                            max_overlays // 2).astype(int).tolist()))
    overlays = []
    for k in chosen:
        v = solved.views[k]
        proj = solved.camera.project(B[k], solved.spec.corners_3d()[v.ids])
        img = overlay(ep.rgb(v.index), v.corners, proj, r.refine.inliers[k])
        name = f"overlay_{v.index:06d}.png"
        cv2.imwrite(str(out_dir / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        overlays.append((name, v.index, r.per_view()[k]["rms_px"]))
    stats = calibration["residuals"]
    unc = calibration["uncertainty"]
    rows = "".join(f"<tr><td>{p['frame']}</td><td>{'yes' if p['used'] else 'no'}</td><td>{p['corners']}</td>"
                   f"<td>{p['inliers']}</td><td>{p['rms_px']:.3f}</td><td>{p['max_px']:.3f}</td></tr>"
                   for p in r.per_view())
    cf = "".join(f"<tr><td>{html.escape(k)}</td><td>" +
                 (html.escape(v['error']) + "</td><td></td><td></td>" if "error" in v else
                  f"{v['rot_diff_deg']:.4f}</td><td>{v['trans_diff_mm']:.3f}</td><td>"
                  f"{'' if v['median_px'] is None else format(v['median_px'], '.3f')}") + "</td></tr>"
                 for k, v in r.closed_forms.items())
    imgs = "".join(f"<figure><img src='{n}' width='640'><figcaption>frame {i}: RMS {e:.3f} px (error x"
                   f"{OVERLAY_GAIN:g})</figcaption></figure>" for n, i, e in overlays)
    T = np.asarray(calibration["T_mount_cam"])
    lat = ("not estimated" if latency is None else
           f"{latency.latency_s * 1000:.2f} &plusmn; {latency.std_s * 1000:.2f} ms (correlation {latency.correlation:.3f})")
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>manisplat calibration</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:auto}} td,th{{padding:2px 8px;text-align:right}}
table{{border-collapse:collapse}} tr:nth-child(even){{background:#eee}} figure{{display:inline-block}}</style></head><body>
<h1>Calibration of {html.escape(str(solved.episode))}</h1>
<p>mount <b>{html.escape(r.mount)}</b> (link {html.escape(r.link)}), {stats['views_used']} of {stats['views_total']} views,
{stats['corners_used']} of {stats['corners_total']} corners; reprojection RMS <b>{stats['rms_px']:.3f} px</b>,
median {stats['median_px']:.3f}, p95 {stats['p95_px']:.3f}, max {stats['max_px']:.3f} px.
1-sigma of T_mount_cam: {unc['T_mount_cam_rot_std_deg']:.4f} deg, {unc['T_mount_cam_trans_std_mm']:.3f} mm.
Motion: axis spread {r.diversity.axis_spread_deg:.1f} deg, largest rotation {r.diversity.max_angle_deg:.1f} deg,
{r.poses} distinct poses. Latency: {lat}. Corner offset subtracted: {solved.corner_offset_px:g} px.</p>
<pre>T_mount_cam =
{html.escape(np.array2string(T, precision=6, suppress_small=True))}</pre>
<img src="report.png" width="100%">
<h2>Closed forms (distance to the refined result)</h2><table><tr><th>method</th><th>deg</th><th>mm</th><th>median px</th></tr>{cf}</table>
<h2>Per view</h2><table><tr><th>frame</th><th>used</th><th>corners</th><th>inliers</th><th>RMS px</th><th>max px</th></tr>{rows}</table>
<h2>Overlays (green: detected, red: projected through the calibration)</h2>{imgs}
<h2>calibration.json</h2><pre>{html.escape(json.dumps({k: v for k, v in calibration.items() if k not in ('residuals',)}, indent=1))}</pre>
</body></html>"""
    path = out_dir / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
