"""Pictures of the matching evaluation: MMA-vs-threshold curves and match pictures (correct vs wrong matches)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ruslam.atomic_files import atomic_path, atomic_write

CORRECT = (40, 220, 40)  # RGB green
WRONG = (230, 40, 40)  # RGB red


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image atomically (temp name, then rename)."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"Could not encode {path} as PNG.")
    atomic_write(path, data.tobytes())


def draw_matches(
    image1: np.ndarray,
    image2: np.ndarray,
    keypoints1: np.ndarray,
    keypoints2: np.ndarray,
    matches: np.ndarray,
    correct: np.ndarray,
    max_lines: int = 300,
) -> np.ndarray:
    """Side-by-side RGB picture; correct matches in green, wrong ones in red (evenly subsampled to max_lines)."""
    h = max(image1.shape[0], image2.shape[0])
    canvas = np.zeros((h, image1.shape[1] + image2.shape[1], 3), np.uint8)
    canvas[: image1.shape[0], : image1.shape[1]] = image1
    canvas[: image2.shape[0], image1.shape[1] :] = image2
    canvas = (canvas * 0.7).astype(np.uint8)  # dim the images so the lines stand out
    order = np.arange(len(matches))
    if len(order) > max_lines:
        order = order[np.linspace(0, len(order) - 1, max_lines).astype(int)]
    offset = np.array([image1.shape[1], 0])
    for m in order[np.argsort(correct[order], kind="stable")]:  # wrong first, correct drawn on top
        p = tuple(np.round(keypoints1[matches[m, 0]]).astype(int))
        q = tuple(np.round(keypoints2[matches[m, 1]] + offset).astype(int))
        colour = CORRECT if correct[m] else WRONG
        cv2.line(canvas, p, q, colour, 1, cv2.LINE_AA)
        cv2.circle(canvas, p, 2, colour, -1, cv2.LINE_AA)
        cv2.circle(canvas, q, 2, colour, -1, cv2.LINE_AA)
    return canvas


def plot_mma(curves: dict[str, list[float]], thresholds, path: Path, title: str) -> None:
    """One MMA-vs-threshold curve per method, written atomically as PNG."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for label, curve in curves.items():
        ax.plot(list(thresholds), curve, marker="o", label=label)
    ax.set(xlabel="threshold [px]", ylabel="MMA [%]", title=title, ylim=(0, 100))
    ax.set_xlim(min(thresholds), max(thresholds))
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
