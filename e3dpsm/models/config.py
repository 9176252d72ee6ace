"""Model configuration: a frozen dataclass saved inside every checkpoint and ONNX graph, so
either rebuilds its model alone."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from e3dpsm.errors import ConfigError
from e3dpsm.layers.deformable import ATTENTION_LAYOUTS
from e3dpsm.layers.fusion import FUSION_MODES
from e3dpsm.layers.s5 import BACKWARD_FIRST_FRAME

INPUT_NORMS: tuple[str, ...] = ("none", "minmax")


@dataclass(frozen=True)
class E3DPSMConfig:
    variant: str = "paper"
    in_channels: int = 2
    height: int = 192
    width: int = 256
    num_joints: int = 16
    stem_width: int = 16
    widths: tuple[int, ...] = (32, 64, 128, 192)
    extra_res_block: bool = True  # the released stages carry a third residual block
    # Deformable attention per stage (heads x head width = stage width in the release).
    deformable: bool = True
    attn_heads: tuple[int, ...] = (4, 4, 4, 6)
    attn_head_dim: tuple[int, ...] = (8, 16, 32, 32)
    attn_points: int = 8
    # "2d": the paper's learned 2-D reference grid; "1d": the release's (h*w) x 1 column with
    # every reference point at (0.5, 0.5) (docs/model.md#citations, Deformable attention).
    attn_layout: str = "2d"
    # S5 blocks: after these stages (0-based). Released code: stages 1 and 4 -> (0, 3);
    # the paper's text: stages 2 and 4 -> (1, 3). State size P = width * ssm_state_ratio.
    ssm_stages: tuple[int, ...] = (0, 3)
    ssm_state_ratio: float = 0.5
    ssm_bidirectional: bool = True
    ssm_discretization: str = "bilinear"
    ssm_bandlimit: float | None = 0.5
    # Non-causal backward branch at a sequence's first frame: "scan" (the full backward scan)
    # or "own_input" (the release: its carried backward state, zero at a stream's start,
    # gates that frame, which then sees its own input only; docs/model.md#citations,
    # Carried S5 state).
    ssm_backward_first_frame: str = "scan"
    # Joint-query decoder over the last stage's tokens (its width is widths[-1]).
    decoder_layers: int = 3
    decoder_heads: int = 4
    decoder_ffn: int = 768
    pose_embed_dim: int = 64
    fusion: str = "learned"
    # Kalman variances in mm^2 (the filter runs on poses in mm): initial Q and R, and the
    # covariance P0 a stream starts from.
    kalman_q_init: float = 1e-3
    kalman_r_init: float = 1e-2
    kalman_p0: float = 1.0
    # "minmax": the release rescales its whole input tensor to [0, 1] (network.py); here per
    # frame in causal runs and steps, over the whole tensor in non-causal runs.
    input_norm: str = "none"
    # Millimetres per unit of the heads' output: the heads predict metres (the release's unit,
    # docs/model.md#citations, Units), the model's outputs and its Kalman filter are in
    # millimetres.
    pose_unit_mm: float = 1000.0
    train_window_ms: float = 20.0
    seed: int = 0
    # Pruned widths (`e3dpsm prune`, e3dpsm/compress): empty means unpruned, so every config
    # written before pruning existed reads back unchanged.
    # Hidden width of every residual block, stage-major (2 or 3 blocks per stage); 0 removes
    # the block's residual branch, leaving its shortcut.
    res_hidden: tuple[int, ...] = ()
    # GEGLU hidden width of each stage's deformable block (default 4 x heads x head width).
    attn_ff_hidden: tuple[int, ...] = ()
    # Stages whose deformable block was pruned away (the block becomes the identity).
    attn_removed: tuple[int, ...] = ()
    # Per S5 block, in sorted `ssm_stages` order: GEGLU hidden width (default the stage
    # width) and state size P (default width * ssm_state_ratio).
    ssm_ff_hidden: tuple[int, ...] = ()
    ssm_state_dims: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.widths)
        if len(self.attn_heads) != n or len(self.attn_head_dim) != n:
            raise ConfigError(f"attn_heads and attn_head_dim need one entry per stage ({n})")
        for i, (w, h, d) in enumerate(zip(self.widths, self.attn_heads, self.attn_head_dim)):
            if self.deformable and w % 8:
                raise ConfigError(f"stage {i} width {w} must be a multiple of 8 (GroupNorm(8))")
            if self.deformable and h * d <= 0:
                raise ConfigError(f"stage {i}: attention heads x head width must be positive")
        self._check_pruned_widths()
        if any(not 0 <= s < n for s in self.ssm_stages):
            raise ConfigError(f"ssm_stages {self.ssm_stages} must index stages 0..{n - 1}")
        if self.fusion not in FUSION_MODES:
            raise ConfigError(f"unknown fusion {self.fusion!r}; choose from {list(FUSION_MODES)}")
        for field, value, allowed in (
            ("attn_layout", self.attn_layout, ATTENTION_LAYOUTS),
            ("ssm_backward_first_frame", self.ssm_backward_first_frame, BACKWARD_FIRST_FRAME),
            ("input_norm", self.input_norm, INPUT_NORMS),
        ):
            if value not in allowed:
                raise ConfigError(f"unknown {field} {value!r}; choose from {list(allowed)}")
        if self.ssm_discretization not in ("bilinear", "zoh"):
            raise ConfigError("ssm_discretization must be 'bilinear' or 'zoh'")
        if self.widths[-1] % self.decoder_heads:
            raise ConfigError(f"decoder width {self.widths[-1]} is not divisible by {self.decoder_heads} heads")
        stride = 2 ** (n + 1)
        if self.height % stride or self.width % stride:
            raise ConfigError(f"input {self.height}x{self.width} must be divisible by {stride}")
        if self.train_window_ms <= 0:
            raise ConfigError("train_window_ms must be positive")
        for field, value in (("pose_unit_mm", self.pose_unit_mm), ("kalman_q_init", self.kalman_q_init),
                             ("kalman_r_init", self.kalman_r_init), ("kalman_p0", self.kalman_p0)):
            if not value > 0:
                raise ConfigError(f"{field} must be positive, got {value}")

    @property
    def blocks_per_stage(self) -> int:
        return 3 if self.extra_res_block else 2

    def _check_pruned_widths(self) -> None:
        n, n_ssm = len(self.widths), len(self.ssm_stages)
        for field, value, count, low in (
            ("res_hidden", self.res_hidden, n * self.blocks_per_stage, 0),
            ("attn_ff_hidden", self.attn_ff_hidden, n, 1),
            ("ssm_ff_hidden", self.ssm_ff_hidden, n_ssm, 1),
            ("ssm_state_dims", self.ssm_state_dims, n_ssm, 1),
        ):
            if value and len(value) != count:
                raise ConfigError(f"{field} needs {count} entries (or none for unpruned), got {len(value)}")
            if any(not isinstance(v, int) or v < low for v in value):
                raise ConfigError(f"{field} entries must be integers >= {low}, got {list(value)}")
        if any(not 0 <= s < n for s in self.attn_removed):
            raise ConfigError(f"attn_removed {self.attn_removed} must index stages 0..{n - 1}")

    def res_hidden_width(self, stage: int, block: int) -> int:
        """Hidden width of residual block `block` (0-based) of `stage`; 0: branch removed."""
        if self.res_hidden:
            return self.res_hidden[stage * self.blocks_per_stage + block]
        return self.widths[stage]

    def attn_inner(self, stage: int) -> int:
        return self.attn_heads[stage] * self.attn_head_dim[stage]

    def attn_ff_width(self, stage: int) -> int:
        return self.attn_ff_hidden[stage] if self.attn_ff_hidden else 4 * self.attn_inner(stage)

    def has_attention(self, stage: int) -> bool:
        return self.deformable and stage not in self.attn_removed

    def _ssm_index(self, stage: int) -> int:
        return sorted(self.ssm_stages).index(stage)

    def ssm_ff_width(self, stage: int) -> int:
        return self.ssm_ff_hidden[self._ssm_index(stage)] if self.ssm_ff_hidden else self.widths[stage]

    def stage_hw(self, stage: int) -> tuple[int, int]:
        """Output map size of a stage: the stem halves the input, each stage halves again."""
        f = 2 ** (stage + 2)
        return self.height // f, self.width // f

    def ssm_state_dim(self, stage: int) -> int:
        if self.ssm_state_dims:
            return self.ssm_state_dims[self._ssm_index(stage)]
        return max(1, int(round(self.widths[stage] * self.ssm_state_ratio)))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "E3DPSMConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"unknown config fields {unknown}; known: {sorted(names)}")
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**kwargs)

    def replace(self, **overrides: Any) -> "E3DPSMConfig":
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ConfigError(f"unknown config fields {unknown}; known: {sorted(names)}")
        return dataclasses.replace(self, **overrides)
