from .vggt_omega import VGGTOmega

__all__ = ["VGGTOmega"]
