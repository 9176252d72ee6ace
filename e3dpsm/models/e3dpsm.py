"""E-3DPSM: LNES frames -> convolutional pyramid with deformable attention and S5 blocks ->
joint-query decoder -> direct and delta pose heads -> pose fusion (paper, Fig. 2).

Two ways to run the same weights:
- `forward_sequence(lnes[B, T, 2, H, W], causal)`: training (bidirectional S5) and
  evaluation; the encoder runs batched over all B*T frames.
- `step(lnes[B, 2, H, W], state, window_ms)`: one pose update with every recurrent quantity
  in an explicit state dict laid out by `state_spec()`; this is what gets exported.
Stepping a stream frame by frame reproduces `forward_sequence(causal=True)` to float32
round-off, and so do chunked runs that pass the state on.
"""
from __future__ import annotations

from typing import Callable, Mapping

import torch
from torch import nn

from e3dpsm.errors import InputError
from e3dpsm.layers import DeformableTransformerBlock, EncoderStage, JointQueryDecoder, PoseFusion, S5Block
from e3dpsm.models.config import E3DPSMConfig
from e3dpsm.state import StateSpec, check_state_shapes, initial_states

State = dict[str, torch.Tensor]
Outputs = dict[str, torch.Tensor]
OUTPUT_NAMES: tuple[str, ...] = ("pose", "pose_direct", "pose_delta")


class E3DPSM(nn.Module):
    def __init__(self, config: E3DPSMConfig) -> None:
        super().__init__()
        self.config = cfg = config
        if cfg.seed is not None:
            torch.manual_seed(cfg.seed)
        self.stem = nn.Sequential(nn.Conv2d(cfg.in_channels, cfg.stem_width, 3, stride=2, padding=1), nn.ReLU())
        widths = (cfg.stem_width, *cfg.widths)
        self.stages = nn.ModuleList(
            EncoderStage(widths[i], widths[i + 1], cfg.extra_res_block,
                         tuple(cfg.res_hidden_width(i, b) for b in range(cfg.blocks_per_stage)))
            for i in range(len(cfg.widths))
        )
        self.attention = nn.ModuleList(
            DeformableTransformerBlock(
                w, cfg.attn_heads[i], cfg.attn_head_dim[i], cfg.attn_points, *cfg.stage_hw(i), layout=cfg.attn_layout,
                ff_hidden=cfg.attn_ff_width(i),
            )
            if cfg.has_attention(i) else nn.Identity()
            for i, w in enumerate(cfg.widths)
        )
        self.ssm = nn.ModuleDict({
            str(s): S5Block(
                cfg.widths[s], cfg.ssm_state_dim(s), ff_hidden=cfg.ssm_ff_width(s), bidirectional=cfg.ssm_bidirectional,
                discretization=cfg.ssm_discretization, bandlimit=cfg.ssm_bandlimit,
                backward_first_frame=cfg.ssm_backward_first_frame,
                seed=cfg.seed + 101 * (s + 1) if cfg.seed is not None else None,
            )
            for s in sorted(cfg.ssm_stages)
        })
        dim = cfg.widths[-1]
        self.decoder = JointQueryDecoder(dim, cfg.num_joints, cfg.decoder_layers, cfg.decoder_heads, cfg.decoder_ffn)
        self.direct_head = nn.Linear(dim, 3)
        self.pose_embed = nn.Sequential(
            nn.Linear(3, cfg.pose_embed_dim), nn.ReLU(), nn.Linear(cfg.pose_embed_dim, cfg.pose_embed_dim)
        )
        self.delta_head = nn.Linear(dim + cfg.pose_embed_dim, 3)
        self.fusion = PoseFusion(cfg.num_joints, cfg.fusion, cfg.kalman_q_init, cfg.kalman_r_init, cfg.kalman_p0)
        # Mean training pose (mm), added to the direct head: the heads then learn residuals of
        # a few hundred mm instead of climbing to metres at Adam's per-step pace.
        self.register_buffer("pose_prior_mm", torch.zeros(cfg.num_joints, 3))
        for head in (self.direct_head, self.delta_head):
            nn.init.normal_(head.weight, std=1e-3)
            nn.init.zeros_(head.bias)

    def set_pose_prior(self, mean_pose_mm: torch.Tensor) -> None:
        """Set the direct head's offset, typically the mean pose of the training set."""
        self.pose_prior_mm.copy_(torch.as_tensor(mean_pose_mm, dtype=torch.float32).view_as(self.pose_prior_mm))

    def num_parameters(self) -> int:
        """Trainable and frozen parameters alike (buffers such as the pose prior excluded)."""
        return sum(p.numel() for p in self.parameters())

    # -- state layout --------------------------------------------------------------------
    def state_spec(self) -> tuple[StateSpec, ...]:
        cfg, specs = self.config, []
        for s in sorted(cfg.ssm_stages):
            h, w = cfg.stage_hw(s)
            p = cfg.ssm_state_dim(s)
            for part in ("re", "im"):
                specs.append(StateSpec(
                    f"s5_stage{s + 1}_{part}", (h, w, p),
                    doc=f"S5 state after stage {s + 1}, {'real' if part == 're' else 'imaginary'} part, [h, w, P]",
                ))
        j = cfg.num_joints
        specs.append(StateSpec("fusion_pose", (j, 3), doc="previous fused pose (mm), Kalman estimate X"))
        if self.fusion.uses_covariance:
            specs.append(StateSpec(
                "fusion_cov", (j, 3), init=(self.fusion.p0,) * (3 * j),
                doc="diagonal of the Kalman covariance Sigma (mm^2)",
            ))
        specs.append(StateSpec("fusion_initialised", (1,), doc="1 once the stream has had its first step"))
        return tuple(specs)

    def init_state(self, batch: int, device: torch.device | str | None = None) -> State:
        device = device or next(self.parameters()).device
        return {name: torch.from_numpy(value).to(device) for name, value in initial_states(self.state_spec(), batch).items()}

    # -- input checks (user input: typed errors, not asserts) ------------------------------
    def _check_frames(self, lnes: torch.Tensor, leading: str) -> None:
        cfg = self.config
        expected = f"[{leading}, {cfg.in_channels}, {cfg.height}, {cfg.width}]"
        if not isinstance(lnes, torch.Tensor):
            raise InputError(f"LNES must be a torch.Tensor {expected} float32, got {type(lnes).__name__}")
        ndim = len(leading.split(", ")) + 3
        if lnes.dim() != ndim or tuple(lnes.shape[-3:]) != (cfg.in_channels, cfg.height, cfg.width):
            raise InputError(f"LNES has shape {list(lnes.shape)}, expected {expected}")
        if lnes.dtype != torch.float32:
            raise InputError(f"LNES has dtype {lnes.dtype}, expected torch.float32 {expected}")

    def _step_scale(self, window_ms: float | torch.Tensor | None, batch: int, like: torch.Tensor) -> torch.Tensor:
        """Window length / training window, as a [B] (or [1]) tensor."""
        if window_ms is None:
            window_ms = self.config.train_window_ms
        if not isinstance(window_ms, torch.Tensor):
            if not window_ms > 0:
                raise InputError(f"window_ms must be positive, got {window_ms}")
            window_ms = torch.tensor([float(window_ms)], device=like.device)
        window_ms = window_ms.to(like.dtype).reshape(-1)
        if window_ms.shape[0] not in (1, batch):
            raise InputError(f"window_ms has {window_ms.shape[0]} values, expected 1 or the batch size {batch}")
        return window_ms / self.config.train_window_ms

    def _normalise(self, frames: torch.Tensor, per_frame: bool) -> torch.Tensor:
        """The release's min-max rescaling to [0, 1]: per frame ([N, C, H, W] -> each n), or
        over the whole tensor. A constant frame (no events) stays at 0, where the release
        divides by zero."""
        if self.config.input_norm == "none":
            return frames
        dims = tuple(range(1, frames.dim())) if per_frame else tuple(range(frames.dim()))
        low, high = frames.amin(dim=dims, keepdim=True), frames.amax(dim=dims, keepdim=True)
        return (frames - low) / (high - low).clamp_min(torch.finfo(frames.dtype).tiny)

    # -- shared pieces -------------------------------------------------------------------
    def _encode(self, x: torch.Tensor, apply_ssm: Callable[[str, S5Block, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """Frames [N, 2, H, W] -> memory tokens [N, h*w, D]; `apply_ssm` runs the S5 blocks."""
        x = self.stem(x)
        for i, (stage, attention) in enumerate(zip(self.stages, self.attention)):
            x = attention(stage(x))
            if str(i) in self.ssm:
                x = apply_ssm(str(i), self.ssm[str(i)], x)
        return x.flatten(2).transpose(1, 2)

    def _direct_pose(self, feats: torch.Tensor) -> torch.Tensor:
        return self.direct_head(feats) * self.config.pose_unit_mm + self.pose_prior_mm

    def _pose_update(
        self, feats: torch.Tensor, direct: torch.Tensor, state: Mapping[str, torch.Tensor]
    ) -> tuple[Outputs, State]:
        """One fusion step from joint features [B, J, D] and the direct pose [B, J, 3]."""
        unit = self.config.pose_unit_mm
        prev = state["fusion_pose"]
        embed = self.pose_embed(prev / unit)
        delta = self.delta_head(torch.cat([feats, embed], dim=-1)) * unit
        fused, cov = self.fusion(direct, delta, prev, state.get("fusion_cov"), state["fusion_initialised"])
        new_state: State = {"fusion_pose": fused, "fusion_initialised": torch.ones_like(state["fusion_initialised"])}
        if cov is not None:
            new_state["fusion_cov"] = cov
        return {"pose": fused, "pose_direct": direct, "pose_delta": delta}, new_state

    def _ssm_state(self, state: Mapping[str, torch.Tensor], key: str) -> tuple[torch.Tensor, torch.Tensor]:
        s = int(key) + 1
        return state[f"s5_stage{s}_re"], state[f"s5_stage{s}_im"]

    # -- public API ----------------------------------------------------------------------
    def step(
        self, lnes: torch.Tensor, state: Mapping[str, torch.Tensor], window_ms: float | torch.Tensor | None = None
    ) -> tuple[Outputs, State]:
        """One pose update. lnes [B, 2, H, W]; state laid out by `state_spec()`."""
        self._check_frames(lnes, "B")
        batch = lnes.shape[0]
        specs = self.state_spec()
        check_state_shapes(specs, {k: tuple(v.shape) for k, v in state.items()}, batch)
        scale = self._step_scale(window_ms, batch, lnes)
        new_state: State = {}

        def apply_ssm(key: str, block: S5Block, x: torch.Tensor) -> torch.Tensor:
            y, (re, im) = block.step(x, self._ssm_state(state, key), scale)
            new_state[f"s5_stage{int(key) + 1}_re"], new_state[f"s5_stage{int(key) + 1}_im"] = re, im
            return y

        feats = self.decoder(self._encode(self._normalise(lnes, per_frame=True), apply_ssm))
        direct = self._direct_pose(feats)
        outputs, fusion_state = self._pose_update(feats, direct, state)
        new_state.update(fusion_state)
        return outputs, {s.name: new_state[s.name] for s in specs}

    def forward_sequence(
        self,
        lnes: torch.Tensor,
        causal: bool = True,
        state: Mapping[str, torch.Tensor] | None = None,
        window_ms: float | torch.Tensor | None = None,
        return_state: bool = False,
    ) -> Outputs | tuple[Outputs, State]:
        """lnes [B, T, 2, H, W] -> outputs [B, T, J, 3].

        causal=False runs the S5 blocks bidirectionally (training). With causal=True and a
        `state`, the run continues a stream; `return_state` gives the state after frame T.
        """
        self._check_frames(lnes, "B, T")
        batch, steps = lnes.shape[:2]
        if steps < 1:
            raise InputError("LNES sequence must have at least one frame (T >= 1)")
        specs = self.state_spec()
        if state is None:
            state = self.init_state(batch, lnes.device)
        else:
            check_state_shapes(specs, {k: tuple(v.shape) for k, v in state.items()}, batch)
        scale = self._step_scale(window_ms, batch, lnes)
        final: State = {}

        def apply_ssm(key: str, block: S5Block, x: torch.Tensor) -> torch.Tensor:
            seq = x.view(batch, steps, *x.shape[1:])
            y, (re, im) = block.sequence(seq, self._ssm_state(state, key), scale, causal)
            final[f"s5_stage{int(key) + 1}_re"], final[f"s5_stage{int(key) + 1}_im"] = re, im
            return y.flatten(0, 1)

        frames = self._normalise(lnes.flatten(0, 1), per_frame=causal)
        feats = self.decoder(self._encode(frames, apply_ssm))
        feats = feats.view(batch, steps, *feats.shape[1:])
        direct = self._direct_pose(feats)
        fusion_state: Mapping[str, torch.Tensor] = state
        per_step: list[Outputs] = []
        for t in range(steps):  # the fusion is a 48-value recurrence: cheap to loop
            out, fusion_state = self._pose_update(feats[:, t], direct[:, t], fusion_state)
            per_step.append(out)
        outputs = {k: torch.stack([o[k] for o in per_step], dim=1) for k in OUTPUT_NAMES}
        if not return_state:
            return outputs
        final.update(fusion_state)
        return outputs, {s.name: final[s.name] for s in specs}

    def forward(self, lnes: torch.Tensor, causal: bool = False) -> Outputs:
        return self.forward_sequence(lnes, causal=causal)  # type: ignore[return-value]
