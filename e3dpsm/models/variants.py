"""Registered variants. Parameter counts at the default 192 x 256 input (Kalman log Q and
log R, 96 values, included)."""
from __future__ import annotations

from e3dpsm.models.config import E3DPSMConfig
from e3dpsm.models.registry import register_model

# The release works in metres and evaluates in millimetres (x1000, docs/model.md#citations,
# Units), so its Kalman variances (m^2) are x1e6 in this project's millimetre filter.
RELEASED_VARIANCE_TO_MM2 = 1000.0**2


@register_model
def paper() -> E3DPSMConfig:
    """The released network where the paper is silent, the paper where it is explicit
    (learned 2-D reference grid, exact carried state): 6,648,662 parameters."""
    return E3DPSMConfig(variant="paper")


@register_model
def released() -> E3DPSMConfig:
    """The released network number for number (6,640,406 + 96 parameters), so that its
    checkpoints import (`e3dpsm import --released`): 1-D attention layout, min-max input
    normalisation, the released backward branch at t = 0. Its heads predict metres, as the
    release's do; outputs and the Kalman filter are in millimetres like every variant's, so
    the release's filter (Q = 1e-3, R = 1e-2, P0 = I, in m^2) starts here at x1e6 (mm^2)."""
    return E3DPSMConfig(
        variant="released", attn_layout="1d", input_norm="minmax", ssm_backward_first_frame="own_input",
        kalman_q_init=1e-3 * RELEASED_VARIANCE_TO_MM2, kalman_r_init=1e-2 * RELEASED_VARIANCE_TO_MM2,
        kalman_p0=RELEASED_VARIANCE_TO_MM2,
    )


@register_model
def small() -> E3DPSMConfig:
    """Half-width pyramid, lighter decoder: trains on two CPU cores in minutes. 1,474,790
    parameters (1,468,670 at 96 x 128: the reference grid follows the input size)."""
    return E3DPSMConfig(
        variant="small", stem_width=8, widths=(16, 32, 64, 96), attn_heads=(2, 2, 4, 4),
        attn_head_dim=(8, 16, 16, 24), attn_points=4, decoder_layers=2, decoder_heads=4,
        decoder_ffn=256, pose_embed_dim=32,
    )


@register_model
def tiny() -> E3DPSMConfig:
    """Smallest graph with every component, for tests and CI: 94,610 parameters."""
    return E3DPSMConfig(
        variant="tiny", stem_width=8, widths=(8, 16, 16, 24), extra_res_block=False,
        attn_heads=(1, 2, 2, 2), attn_head_dim=(8, 8, 8, 12), attn_points=4, decoder_layers=1,
        decoder_heads=2, decoder_ffn=48, pose_embed_dim=16,
    )
