"""Building blocks of E-3DPSM, one concern per file."""
from e3dpsm.layers.decoder import JointQueryDecoder
from e3dpsm.layers.deformable import ATTENTION_LAYOUTS, DeformableAttention, DeformableTransformerBlock
from e3dpsm.layers.fusion import PoseFusion
from e3dpsm.layers.residual import EncoderStage, PreActResBlock
from e3dpsm.layers.s5 import S5, S5Block

__all__ = [
    "ATTENTION_LAYOUTS", "DeformableAttention", "DeformableTransformerBlock", "EncoderStage", "JointQueryDecoder",
    "PoseFusion", "PreActResBlock", "S5", "S5Block",
]
