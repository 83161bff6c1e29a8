"""PNG figures of the evaluation (matplotlib, Agg back end: no display needed)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["plot_sparsification"]


def plot_sparsification(
    curves: Mapping[str, tuple[NDArray[np.floating], NDArray[np.floating]]],
    path: Path | str,
    *,
    bad_rate: float | None = None,
    title: str = "Sparsification",
    legend_extra: Mapping[str, str] | None = None,
) -> Path:
    """Plot bad-pixel rate against density for several confidence measures and write a PNG.

    Args:
        curves: label -> ``(density, bad_rate)`` arrays (shares in [0, 1]).
        path: PNG file to write (parent folders are created).
        bad_rate: overall bad-pixel rate ``eps``; when given, the optimal
            curve ``max(0, 1 - (1 - eps) / density)`` is drawn dashed.
        title: figure title.
        legend_extra: label -> text appended to the legend entry (e.g. the AUSC ratio).

    Returns:
        The path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
    try:
        extra = legend_extra or {}
        for label, (density, rate) in curves.items():
            suffix = f" ({extra[label]})" if label in extra else ""
            ax.plot(np.asarray(density) * 100.0, np.asarray(rate) * 100.0, marker=".", label=label + suffix)
        if bad_rate is not None and bad_rate > 0:
            dens = np.linspace(0.005, 1.0, 200)
            optimal = np.maximum(0.0, 1.0 - (1.0 - bad_rate) / dens)
            ax.plot(dens * 100.0, optimal * 100.0, "k--", label="optimal")
        ax.set_xlabel("density (% of pixels kept)")
        ax.set_ylabel("bad pixels of the kept (%)")
        ax.set_xlim(0, 100)
        ax.set_ylim(bottom=0)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
    return path
