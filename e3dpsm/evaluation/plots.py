"""Evaluation plots (matplotlib, Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from e3dpsm.utils.io import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_error_along_sequences(per_frame: Mapping[str, np.ndarray], window_ms: float, path: Path) -> Path:
    """Per-frame MPJPE along each sequence (one line per sequence)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 4))
    for name, err in per_frame.items():
        ax.plot(np.arange(err.size) * window_ms / 1000.0, err, lw=0.8, label=name)
    ax.set_xlabel("time in sequence (s)")
    ax.set_ylabel("MPJPE (mm)")
    ax.set_title("Error along each sequence")
    if len(per_frame) <= 10:
        ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def plot_per_joint(per_joint: Mapping[str, Mapping[str, float]], path: Path) -> Path:
    """Bars of MPJPE and PA-MPJPE per joint."""
    plt = _pyplot()
    names = list(per_joint)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.bar(x - 0.2, [per_joint[n]["mpjpe"] for n in names], 0.4, label="MPJPE")
    ax.bar(x + 0.2, [per_joint[n]["pa_mpjpe"] for n in names], 0.4, label="PA-MPJPE")
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("mm")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path
