"""Figures of a hand episode: the hand, the object at its truth and its estimate, the
contacts with their friction cones, and the grasp quality over time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from firmware_if import kinematics as kin  # noqa: E402
from service.episode.hand_episode import HandEpisodeReport  # noqa: E402
from service.localization.grasp import cone_edges  # noqa: E402
from service.localization.objects.contour import Contour  # noqa: E402
from service.localization.objects.rolling import contacts  # noqa: E402
from tools.words import steps_text  # noqa: E402


def _placed(contour: Contour, pose) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    closed = np.vstack([contour.points, contour.points[:1]])
    return closed @ np.array([[c, s], [-s, c]]) + np.asarray(pose[:2])


def draw_hand(ax: plt.Axes, report: HandEpisodeReport) -> None:
    """Fingers (links and tips), the object at truth and estimate, contacts and cones, mm."""
    parts = report.parts
    steps = report.result.steps
    centres = np.array(steps[-1].centres if steps else report.result.start_centres)
    truth = _placed(parts.contour, report.truth) * 1e3
    ax.fill(truth[:, 0], truth[:, 1], color="0.85", zorder=0)
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.5, label="object (truth)")
    est = report.result.estimate
    if est is not None and est.pose is not None:
        placed = _placed(parts.contour, est.pose) * 1e3
        style = "b--" if est.converged else "b:"
        ax.plot(placed[:, 0], placed[:, 1], style, lw=1.5,
                label="estimate" + ("" if est.converged else " (not converged)"))
    path = [np.array(report.result.start_centres)] + [np.array(s.centres) for s in steps]
    trail = np.stack(path) * 1e3  # (steps + 1, n, 2)
    radii = np.array([f.radius for f in parts.hand.fingers])
    points, normals = contacts(parts.field, np.asarray([report.truth]), centres[None], radii)
    cones = cone_edges(normals[0], report.settings.mu)
    for i, finger in enumerate(parts.hand.fingers):
        q = kin.inverse(finger, np.array([centres[i, 0], 0.0, centres[i, 1]]),
                        np.array(finger.home), iterations=300).q
        joints = _joint_points(finger, q)
        ax.plot(joints[:, 0] * 1e3, joints[:, 1] * 1e3, "-o", color="tab:orange", lw=3, ms=4)
        ax.add_patch(plt.Circle(centres[i] * 1e3, finger.radius * 1e3, fill=False,
                                color="tab:orange", lw=1.5))
        ax.plot(trail[:, i, 0], trail[:, i, 1], ".", color="tab:red", ms=3)
        p = points[0, i] * 1e3
        for edge in cones[i]:
            tip = p + 8 * edge / np.linalg.norm(edge)
            ax.plot([p[0], tip[0]], [p[1], tip[1]], color="tab:green", lw=1.2)
        ax.plot(*p, "g^", ms=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm, up)")
    ax.legend(loc="lower left", fontsize=7)


def _joint_points(finger, q: np.ndarray) -> np.ndarray:
    """Base, each joint and the tip centre of a finger, hand plane (x, z)."""
    rot, origin = kin.base_frame(finger)
    points = [origin.copy()]
    frame, pos = rot.copy(), origin.copy()
    for joint, angle in zip(finger.joints, q, strict=True):
        pos = pos + frame @ np.asarray(joint.origin)
        points.append(pos.copy())
        frame = frame @ kin._rotations(np.asarray(joint.axis), np.array([angle]))[0]
    points.append(kin.forward(finger, q))
    return np.array(points)[:, [0, 2]]


def draw_quality(ax: plt.Axes, report: HandEpisodeReport) -> None:
    steps = report.result.steps
    index = [0] + [s.index for s in steps]
    true_q = [report.start_quality] + [s.quality for s in steps]
    predicted = [np.nan] + [s.predicted_quality for s in steps]
    ax.plot(index, true_q, "k-o", ms=3, label="quality (truth)")
    ax.plot(index, predicted, "b.", ms=5, label="least predicted over plausible poses")
    for s in steps:
        if s.kind == "manipulate":
            ax.axvline(s.index, color="tab:purple", alpha=0.3)
    ax.axhline(report.settings.threshold_n, color="tab:green", ls="--", label="gate threshold")
    ax.axhline(report.settings.margin_n, color="tab:red", ls="--", label="drop margin")
    ax.set(xlabel="step (purple: manipulation)", ylabel="N",
           title="grasp quality: disturbance resisted beyond the weight",
           xlim=(-0.5, max(index) + 0.5))  # whole steps, even for an episode of none
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(fontsize=7)


def hand_figure(report: HandEpisodeReport, path: Path) -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 5.2))
    draw_hand(left, report)
    result = ("DROPPED" if report.result.dropped else "localized" if report.score.success
              else "WRONG" if report.score.wrong_declaration else "not localized")
    why = ": no safe move left" if report.result.stuck and result == "not localized" else ""
    if report.result.fault is not None:
        result, why = "stopped by a hardware fault", ""
    left.set_title(f"{report.parts.contour.name} in {report.parts.hand.name}: {result} "
                   f"after {steps_text(len(report.result.steps))}{why}")
    draw_quality(right, report)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
