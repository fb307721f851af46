from . import vision_transformer as vits  # noqa: F401
