"""Runs the stage table in order, each stage as its own `python -m e3dpsm <command>`
subprocess (as a user would run it), then writes the report index.

A stage whose marker file exists is not redone on a rerun, so an interrupted pipeline
resumes where it stopped; `only` reruns the named stages whatever their markers say.
"""
from __future__ import annotations

import logging
import subprocess
import sys
import time
from dataclasses import asdict

from e3dpsm.errors import ConfigError, E3DPSMError
from e3dpsm.pipeline.report import write_index
from e3dpsm.pipeline.stages import STAGE_GROUPS, STAGES, PipelineConfig, expand_stage_names

log = logging.getLogger(__name__)


class StageFailed(E3DPSMError):
    """A pipeline stage exited non-zero."""


def run_stage(argv: list[str]) -> int:
    """One stage in its own process, as a user would run it: thread pools, environment and
    memory start clean (an OpenMP pool left busy by training would slow the next stage)."""
    return subprocess.run([sys.executable, "-m", "e3dpsm", *argv], check=False).returncode


def run_pipeline(cfg: PipelineConfig, only: list[str] | None = None) -> list[dict]:
    if cfg.variant not in ("tiny", "small", "paper"):
        raise ConfigError(f"unknown variant {cfg.variant!r}; use tiny, small or paper")
    if cfg.checkpoint:
        from e3dpsm.checkpoint import read_checkpoint

        read_checkpoint(cfg.checkpoint)  # a clear error now, not at the evaluate stage
    cfg.out.mkdir(parents=True, exist_ok=True)
    done: list[dict] = []
    names = [s.name for s in STAGES]
    only = expand_stage_names(only) if only else None
    asked = expand_stage_names(cfg.with_stages)
    unknown = sorted((set(only or []) | set(asked)) - set(names))
    if unknown:
        groups = "; ".join(f"{group}: {' '.join(members)}" for group, members in STAGE_GROUPS.items())
        raise ConfigError(f"unknown stages {unknown}; stages: {', '.join(names)} (groups: {groups})")
    for index, stage in enumerate(STAGES, 1):
        marker = cfg.out / stage.marker
        header = f"[{index}/{len(STAGES)}] {stage.name}"
        if stage.name == "train" and cfg.checkpoint:
            log.info("%s: skipped, --checkpoint %s given", header, cfg.checkpoint)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        if stage.optional and stage.name not in asked and stage.name not in (only or []):
            or_group = "".join(f" or --with {g}" for g, members in STAGE_GROUPS.items() if stage.name in members)
            log.info("%s: optional, not asked for (--with %s%s)", header, stage.name, or_group)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        if only and stage.name not in only:
            log.info("%s: not in --only, left as it is", header)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        if marker.exists() and not only:
            log.info("%s: done before, skipped (%s exists)", header, stage.marker)
            done.append({"stage": stage.name, "status": "skipped", "seconds": 0.0})
            continue
        argv = stage.argv(cfg)
        log.info("%s: e3dpsm %s", header, " ".join(argv))
        start = time.perf_counter()
        code = run_stage(argv)
        seconds = time.perf_counter() - start
        if code != 0:
            raise StageFailed(f"stage {stage.name} failed (exit {code}); fix it and rerun: finished stages are kept")
        done.append({"stage": stage.name, "status": "ran", "seconds": round(seconds, 1)})
        log.info("%s: finished in %.0f s", header, seconds)
    write_index(cfg.out, asdict(cfg), done)
    return done
