"""Pictures of results: instance colours (the node's palette) beside predicted center scores.

Organized clouds are drawn as images (one pixel per point, as the camera saw them); unorganized
ones as a top-down scatter. Used by `fpcc render`, `fpcc demo` and the README figure.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msg_tools.palette import label_colors


def render_segmentation(path: Path, xyz: np.ndarray, labels: np.ndarray,
                        center_score: np.ndarray | None = None,
                        shape: tuple[int, int] | None = None, title: str = "",
                        ground_truth: np.ndarray | None = None) -> Path:
    """Write a PNG with panels: [ground truth,] predicted instances, center scores."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    valid = np.isfinite(xyz).all(axis=1)
    panels = []
    if ground_truth is not None:
        panels.append(("ground truth", _colours(np.asarray(ground_truth).reshape(-1), valid)))
    k = len(np.unique(labels[labels > 0]))
    panels.append((f"instances ({k})", _colours(labels, valid)))
    if center_score is not None:
        cs = np.where(valid, np.asarray(center_score, np.float64).reshape(-1), np.nan)
        panels.append(("center score", cs))

    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.4), squeeze=False)
    for ax, (name, values) in zip(axes[0], panels):
        _draw(ax, xyz, valid, values, shape)
        ax.set_title(name)
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Lay out, write (creating folders) and close a matplotlib figure."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _colours(labels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    rgb = label_colors(labels.astype(np.int64)).astype(np.float64) / 255.0
    rgb[~valid] = 1.0  # no return: white
    return rgb


def _draw(ax, xyz: np.ndarray, valid: np.ndarray, values: np.ndarray,
          shape: tuple[int, int] | None) -> None:
    scalar = values.ndim == 1
    if shape is not None and shape[0] > 1:
        image = values.reshape(*shape, *([] if scalar else [3]))
        ax.imshow(image, cmap="jet" if scalar else None, vmin=0, vmax=1, interpolation="nearest")
        return
    pts, vals = xyz[valid], values[valid]
    order = np.argsort(pts[:, 2])[::-1]  # far first, near points on top (camera looks along z)
    kwargs = {"c": vals[order], "cmap": "jet", "vmin": 0, "vmax": 1} if scalar else \
        {"c": vals[order]}
    ax.scatter(pts[order, 0], pts[order, 1], s=1.0, linewidths=0, **kwargs)
    ax.set_aspect("equal")
    ax.invert_yaxis()
