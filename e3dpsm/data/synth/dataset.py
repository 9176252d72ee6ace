"""Write a whole synthetic data set in the layout of `e3dpsm.data.layout`.

Sequences are independent (one Generator each, from the seed and the sequence index), so
they are generated in parallel worker processes and written straight into the folder
being built; only their small statistics travel back.
"""
from __future__ import annotations

import concurrent.futures as cf
import os
import time
from pathlib import Path
from typing import Any

from e3dpsm.camera import ee3d_default
from e3dpsm.data.layout import write_dataset_index, write_synthetic_sequence
from e3dpsm.data.synth.generator import SynthConfig, generate_sequence
from e3dpsm.data.synth.preview import write_previews
from e3dpsm.data.synth.stats import SequenceStats, sequence_stats, summarize
from e3dpsm.errors import ConfigError
from e3dpsm.utils.env import report_header
from e3dpsm.utils.io import atomic_dir, write_json_atomic

PREVIEW_SEQUENCES = 2  # previews of the first sequences only: a few images, not hundreds


def split_names(names: list[str]) -> dict[str, list[str]]:
    """About 80/10/10 by index, with a val and a test sequence as soon as there are three."""
    n = len(names)
    n_eval = max(1, round(0.1 * n)) if n >= 3 else 0
    n_test = n_eval if n >= 3 else (1 if n == 2 else 0)
    n_train = n - n_test - n_eval
    return {"train": names[:n_train], "val": names[n_train:n_train + n_eval],
            "test": names[n_train + n_eval:]}


def _one(config: SynthConfig, index: int, root: Path, preview: bool,
         progress: bool) -> tuple[SequenceStats, list[str]]:
    """Generate and write one sequence (runs in a worker process)."""
    from threadpoolctl import threadpool_limits

    camera = ee3d_default()
    # Parallelism is one sequence per process; a multi-threaded BLAS under each worker
    # oversubscribes the cores (measured: a [3, 3] @ [3, 76800] product took 7.6 ms with
    # BLAS threads contending, 0.5 ms with one).
    with threadpool_limits(limits=1, user_api="blas"):
        seq, extras = generate_sequence(config, index, camera, progress=progress)
    write_synthetic_sequence(root / seq.name, seq, camera.to_json())
    previews = write_previews(seq, root / "preview") if preview and index < PREVIEW_SEQUENCES else []
    return sequence_stats(seq, extras), [str(p.relative_to(root)) for p in previews]


def write_dataset(out: str | os.PathLike, config: SynthConfig, sequences: int, *, workers: int = 1,
                  preview: bool = False, force: bool = False, progress: bool = True) -> dict[str, Any]:
    """Generate `sequences` sequences into `out` (built under a temporary name); returns the
    report also written to `out/report.json`."""
    config.validate()
    if sequences < 1:
        raise ConfigError(f"number of sequences must be at least 1, got {sequences}")
    if workers < 1:
        raise ConfigError(f"workers must be at least 1, got {workers}")
    from tqdm import tqdm

    start = time.perf_counter()
    names = [f"seq_{i:04d}" for i in range(sequences)]
    with atomic_dir(out, force=force) as root:
        if workers == 1:
            results = [_one(config, i, root, preview, progress) for i in range(sequences)]
        else:
            with cf.ProcessPoolExecutor(max_workers=min(workers, sequences)) as pool:
                futures = [pool.submit(_one, config, i, root, preview, False) for i in range(sequences)]
                done = cf.as_completed(futures)
                for _ in tqdm(done, total=sequences, desc="sequences", disable=not progress):
                    pass
                results = [f.result() for f in futures]
        stats = [r[0] for r in results]
        info = {"seed": config.seed, "sequences": sequences, "seconds": config.seconds,
                "pose_hz": config.pose_hz, "render_hz": config.render_hz,
                "render_scale": config.render_scale, "generator": config.to_json(),
                "camera": ee3d_default().to_json()}
        write_dataset_index(root, split_names(names), info)
        elapsed = time.perf_counter() - start
        report = report_header("synth", {**config.to_json(), "sequences": sequences, "workers": workers})
        report.update({
            "output": str(Path(out)),
            "realism": summarize(stats),
            "sequences": [{"name": n, "events": s.events, "frames": s.frames, "actions": s.actions}
                          for n, s in zip(names, stats)],
            "previews": [p for r in results for p in r[1]],
            "timing": {"wall_s": elapsed, "data_s": sequences * config.seconds,
                       "wall_per_data_s": elapsed / (sequences * config.seconds)},
        })
        write_json_atomic(root / "report.json", report)
    return report
