"""Registered variants. Parameter counts at the default 192 x 256 input."""
from __future__ import annotations

from e3dpsm.models.config import E3DPSMConfig
from e3dpsm.models.registry import register_model


@register_model
def paper() -> E3DPSMConfig:
    """The released architecture (FACTS section 3)."""
    return E3DPSMConfig(variant="paper")


@register_model
def small() -> E3DPSMConfig:
    """Half-width pyramid, lighter decoder: trains on two CPU cores in minutes."""
    return E3DPSMConfig(
        variant="small", stem_width=8, widths=(16, 32, 64, 96), attn_heads=(2, 2, 4, 4),
        attn_head_dim=(8, 16, 16, 24), attn_points=4, decoder_layers=2, decoder_heads=4,
        decoder_ffn=256, pose_embed_dim=32,
    )


@register_model
def tiny() -> E3DPSMConfig:
    """Smallest graph with every component: for tests and CI."""
    return E3DPSMConfig(
        variant="tiny", stem_width=8, widths=(8, 16, 16, 24), extra_res_block=False,
        attn_heads=(1, 2, 2, 2), attn_head_dim=(8, 8, 8, 12), attn_points=4, decoder_layers=1,
        decoder_heads=2, decoder_ffn=48, pose_embed_dim=16,
    )
