"""Preview PNGs: the LNES frame of a pose window with the projected skeleton on top."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from e3dpsm.data.sequence import Sequence
from e3dpsm.events import events_to_lnes
from e3dpsm.joints import PARENTS


def write_previews(seq: Sequence, out_dir: Path, n_frames: int = 3, window_us: int = 20_000) -> list[Path]:
    """Write `n_frames` evenly spaced previews of `seq`; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    ev = seq.events
    h, w = ev.sensor_hw
    frames = np.linspace(0, seq.t_us.size - 1, n_frames + 2).round().astype(int)[1:-1]
    paths = []
    for f in frames:
        t1 = int(seq.t_us[f])
        lo, hi = np.searchsorted(ev.t_us, [t1 - window_us, t1])
        lnes = events_to_lnes(ev.x[lo:hi], ev.y[lo:hi], ev.t_us[lo:hi], ev.p[lo:hi],
                              t1 - window_us, window_us, height=h, width=w, sensor_hw=(h, w))
        # Brighter = more recent; red: polarity 1 (brighter), blue: polarity 0.
        image = np.stack([lnes[1], 0.25 * np.maximum(lnes[0], lnes[1]), lnes[0]], axis=-1)
        fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=100)
        ax.imshow(np.clip(image * 1.5, 0, 1))
        uv, vis = seq.j2d_px[f], seq.visible[f].astype(bool)
        for j, parent in enumerate(PARENTS):
            if j != parent:
                ax.plot(uv[[j, parent], 0], uv[[j, parent], 1], "-", color="yellow", lw=1.5)
        ax.scatter(uv[vis, 0], uv[vis, 1], s=30, c="lime", edgecolors="black", label="visible", zorder=3)
        ax.scatter(uv[~vis, 0], uv[~vis, 1], s=40, c="red", marker="x", label="occluded / out of view", zorder=3)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        action = seq.action_names[seq.action[f]] if seq.action_names else "?"
        ax.set_title(f"{seq.name} frame {f} ({action}), {hi - lo} events / {window_us // 1000} ms", fontsize=9)
        ax.legend(loc="lower right", fontsize=7)
        ax.axis("off")
        path = out_dir / f"{seq.name}_frame{f:05d}.png"
        fig.savefig(path, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)
    return paths
