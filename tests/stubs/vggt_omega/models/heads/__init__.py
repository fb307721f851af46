from .camera_head import CameraHead
from .dense_head import DenseHead
from .text_alignment_head import TextAlignmentHead

__all__ = ["CameraHead", "DenseHead", "TextAlignmentHead"]
