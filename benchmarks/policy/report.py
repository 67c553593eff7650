"""Plots of the policy benchmark: success over the object's start position, and rollouts as the
policy saw them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from benchmarks.policy.rollout import Rollout

PHASE_COLOURS = {"success": "tab:green", "reach": "tab:red", "grasp": "tab:orange", "transfer": "tab:purple",
                 "place": "tab:brown"}


def heatmaps(rollouts: dict[str, list[Rollout]], training_starts: dict[str, np.ndarray], out: Path) -> Path:
    """One panel per condition: each evaluation start (x, y) coloured by its outcome (failures by the
    phase they failed in), the training demonstrations' starts ([N, 2+] x, y, ...) as small grey dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(rollouts)
    fig, axes = plt.subplots(1, len(keys), figsize=(max(3.2 * len(keys), 4.6), 3.8), squeeze=False, sharex=True,
                             sharey=True)
    for ax, key in zip(axes[0], keys):
        starts = training_starts.get(key)
        if starts is not None and len(starts):
            ax.scatter(starts[:, 0] * 100, starts[:, 1] * 100, s=6, c="0.6", marker=".", label="training starts")
        for phase, colour in PHASE_COLOURS.items():
            xy = np.array([r.result["object_start"][:2] for r in rollouts[key] if r.phase == phase]).reshape(-1, 2)
            if len(xy):
                ax.scatter(xy[:, 0] * 100, xy[:, 1] * 100, s=28, c=colour, marker="o" if phase == "success" else "x",
                           label=phase)
        wins = sum(r.phase == "success" for r in rollouts[key])
        ax.set_title(f"{key}\n{wins} of {len(rollouts[key])} succeeded", fontsize=8)
        ax.set_xlabel("object start x (cm)")
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("object start y (cm)")
    handles = {h.get_label(): h for ax in axes[0] for h in ax.collections}
    fig.legend(list(handles.values()), list(handles), loc="lower center", ncol=min(len(handles), 3), fontsize=8,
               frameon=False)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def contact_sheet(rollouts: dict[str, list[Rollout]], out: Path, per_row: int = 8) -> Path:
    """Rows of policy views (every 8th step) of the rollouts that kept frames, labelled with the
    condition, seed and outcome."""
    rows = []
    for key, runs in rollouts.items():
        for run in (r for r in runs if r.frames):
            picks = np.linspace(0, len(run.frames) - 1, per_row).round().astype(int)
            strip = np.concatenate([run.frames[i] for i in picks], axis=1).copy()
            label = f"{key} seed {run.seed}: {run.phase}"
            cv2.putText(strip, label, (3, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 2, cv2.LINE_AA)
            cv2.putText(strip, label, (3, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
            rows.append(strip)
    if not rows:
        raise ValueError("no rollout kept frames")
    cv2.imwrite(str(out), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    return out
