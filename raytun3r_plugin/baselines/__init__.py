"""Baselines the paper compares raytun3r with, on the same frozen backbones.

- :mod:`raytun3r_plugin.baselines.lora`: LoRA on the fused ``attn.qkv`` of the backbone's own
  transformer blocks (declared per family as ``BackboneSpec.transformer_blocks``), reversible
  like :func:`raytun3r_plugin.apply` and saved in PEFT's layout.
"""

from raytun3r_plugin.baselines.lora import LoraHandle, LoraWeights, inject_lora, lora_targets

__all__ = ["LoraHandle", "LoraWeights", "inject_lora", "lora_targets"]
