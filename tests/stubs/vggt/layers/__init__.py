from .mlp import Mlp
from .patch_embed import PatchEmbed
from .swiglu_ffn import SwiGLUFFN, SwiGLUFFNFused
from .block import NestedTensorBlock
from .attention import MemEffAttention

__all__ = ["Mlp", "PatchEmbed", "SwiGLUFFN", "SwiGLUFFNFused", "NestedTensorBlock", "MemEffAttention"]
