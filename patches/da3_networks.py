"""Depth Anything 3 networks: which a weight file holds, how one is built and loaded.

The patch module (``patches/da3.py``) exposes these as its family's weight-file hooks
(``identify``, ``config_name``, ``canonical_name``, ``require_modules``, ``SIZE_NAMES``: see
``raytun3r_plugin/weights.py``) and its builders; they live here because building a network is
another idea than patching one. ``build_tiny_network`` and ``build_tiny_nested_network`` are the
small networks of DA3's own classes that tests and the built-in networks use.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn

from raytun3r_plugin.errors import MissingDependencyError, WeightsError
from raytun3r_plugin.weights import (
    StateSignature,
    count_blocks,
    load_into,
    read_checkpoint,
    strip_prefix,
)

FAMILY = "da3"

# (embed_dim, depth, RoPE) -> name, for the official configs (docs/backbones.md, Depth Anything 3).
KNOWN_CONFIGS = {
    (384, 12, True): "da3-small",
    (768, 12, True): "da3-base",
    (1024, 24, True): "da3-large",
    (1536, 40, True): "da3-giant",
    (1024, 24, False): "da3mono-large",
}
_INSTALL_HINT = "pip install --no-deps depth-anything-3 && pip install omegaconf addict einops"
#: The official sizes :func:`identify` tells apart by their tensors (``load_backbone`` refuses a
#: file of another size for these names).
SIZE_NAMES = (
    "da3-small",
    "da3-base",
    "da3-large",
    "da3-giant",
    "da3mono-large",
    "da3metric-large",
    "da3-large-1.1",
    "da3-giant-1.1",
    "da3nested-giant-large",
    "da3nested-giant-large-1.1",
)
#: Releases that reuse an architecture (same config, new weights): name -> DA3 config name.
NAME_ALIASES = {
    "da3-large-1.1": "da3-large",
    "da3-giant-1.1": "da3-giant",
    "da3nested-giant-large-1.1": "da3nested-giant-large",
}
#: Names of the nested model (an any-view da3-giant and a da3metric-large in one
#: ``NestedDepthAnything3Net``; patched through :data:`NESTED_SPEC`).
NESTED_NAMES = ("da3nested-giant-large", "da3nested-giant-large-1.1")
#: Modules some DA3 configs import beyond the ``[da3]`` extra -> what to pip install.
_EXTRA_MODULES = {"evo": "pip install evo  (or: pip install 'raytun3r[da3-giant]')"}
#: Which configs need which of those modules (da3-giant's Gaussian-splat adapter imports evo).
_NEEDS = {"da3-giant": ("evo",), "da3nested-giant-large": ("evo",)}


def _import_upstream():
    try:
        with warnings.catch_warnings():  # omegaconf deprecation noise from depth_anything_3.cfg
            warnings.simplefilter("ignore")
            from depth_anything_3.cfg import create_object, load_config
            from depth_anything_3.registry import MODEL_REGISTRY
    except ImportError as error:
        raise MissingDependencyError(
            f"Depth Anything 3 is not importable ({error}); install it with: {_INSTALL_HINT}"
        ) from error
    return create_object, load_config, MODEL_REGISTRY


def canonical_name(name: str) -> str:
    """The DA3 config a model name builds (``da3-large-1.1`` -> ``da3-large``); others unchanged."""
    return NAME_ALIASES.get(name, name)


def config_name(config: dict) -> str | None:
    """The model a DA3 ``config.json`` declares: ``{"model_name": "da3-small", ...}``."""
    name = config.get("model_name")
    return name if isinstance(name, str) and name.startswith("da3") else None


def identify(state: dict[str, torch.Tensor]) -> StateSignature | None:
    """Name a DA3 state dict (keys with or without ``model.``) from its ViT's shapes.

    The PE table ``backbone.pretrained.pos_embed`` (1, 1 + 37 * 37, D) gives the embed dim D,
    the ``blocks.N`` the depth, the q/k-norm weights the RoPE (multi-view) models; returns
    ``None`` for a state dict of another family.
    """
    state = strip_prefix(state, "model.")
    if "da3.backbone.pretrained.pos_embed" in state and any(
        k.startswith("da3_metric.") for k in state
    ):
        pe = state["da3.backbone.pretrained.pos_embed"]
        metric = state.get("da3_metric.backbone.pretrained.pos_embed")
        widths = f"embed dims {pe.shape[-1]} and {'?' if metric is None else metric.shape[-1]}"
        detail = f"nested: an any-view da3 and a metric da3 ({widths})"
        return StateSignature(FAMILY, NESTED_NAMES, detail, tuple(pe.shape))
    pe = state.get("backbone.pretrained.pos_embed")
    if pe is None:
        return None
    prefix = "backbone.pretrained.blocks."
    depth = count_blocks(state, prefix)
    has_rope = any(".attn.q_norm." in key for key in state if key.startswith(prefix))
    embed = int(pe.shape[-1])
    known = KNOWN_CONFIGS.get((embed, depth, has_rope))
    if known == "da3mono-large":
        names: tuple[str, ...] = ("da3mono-large", "da3metric-large")  # one architecture
    elif known is not None:
        names = (known, *(alias for alias, base in NAME_ALIASES.items() if base == known))
    else:
        names = ()
    detail = f"embed dim {embed}, {depth} blocks, {'RoPE' if has_rope else 'no RoPE'}"
    return StateSignature(FAMILY, names, detail, tuple(pe.shape))


def require_modules(name: str) -> None:
    """Fail before any file is read when a config needs a module that is not installed."""
    from importlib.util import find_spec

    for module in _NEEDS.get(canonical_name(name), ()):
        if find_spec(module) is None:
            raise MissingDependencyError(
                f"{name} needs the {module!r} package (depth_anything_3 imports it for this "
                f"model's Gaussian-splat adapter); install it with: {_EXTRA_MODULES[module]}"
            )


def build_network(name: str) -> nn.Module:
    """A randomly initialised ``DepthAnything3Net`` from the package's own config ``name``.

    ``name`` may be an alias of :data:`NAME_ALIASES`; the network records it as ``raytun3r_name``
    (``describe`` reports it: ``da3metric-large`` and ``da3mono-large`` share one architecture).
    """
    create_object, load_config, registry = _import_upstream()
    config = canonical_name(name)
    if config not in registry:
        raise WeightsError(
            f"depth_anything_3 defines no config {config!r}; it has {sorted(registry)}"
        )
    require_modules(name)
    try:
        model = create_object(load_config(registry[config]))
    except ModuleNotFoundError as error:  # a module imported only by this config
        hint = _EXTRA_MODULES.get((error.name or "").split(".")[0], f"pip install {error.name}")
        raise MissingDependencyError(
            f"{name}: depth_anything_3 needs {error.name!r} for this model; install it with: {hint}"
        ) from error
    model.raytun3r_name = name
    return model


def load_weights(model: nn.Module, path) -> nn.Module:
    """Load an official DA3 checkpoint (keys prefixed ``model.``) or a plain state dict.

    ``path`` is a weight file, a folder holding one, or a read
    :class:`~raytun3r_plugin.weights.Checkpoint`.
    """
    checkpoint = read_checkpoint(path)
    state = strip_prefix(checkpoint.state, "model.")
    return load_into(model, state, checkpoint.source)


def _builder(name: str):
    def build(path=None) -> nn.Module:
        if path is None:
            raise WeightsError(
                f"{name} needs a local weight file (.safetensors or .pt); raytun3r never downloads"
            )
        require_modules(name)
        checkpoint = read_checkpoint(path)  # before the (slow) build: a bad path fails at once
        return load_weights(build_network(name), checkpoint)

    build.takes_checkpoint = True  # load_backbone passes the Checkpoint it has already read
    return build


def build_tiny_network(
    embed_dim: int = 64,
    depth: int = 6,
    num_heads: int = 2,
    alt_start: int = 2,
    out_layers: tuple[int, ...] = (2, 3, 4, 5),
    head_features: int = 32,
    head_channels: tuple[int, ...] = (16, 32, 64, 64),
    camera_decoder: bool = True,
    camera_encoder: bool = True,
    seed: int | None = 0,
) -> nn.Module:
    """A small ``DepthAnything3Net`` made of DA3's own classes (for tests and CPU training).

    Same structure as the official configs: DINOv2 ViT with a 37x37 absolute PE table trained at
    518 px, q/k-norm, RoPE and alternating frame/global attention from ``alt_start``, DualDPT head,
    camera decoder and encoder. Unlike DA3's own constructor (which leaves ``pos_embed`` and
    ``cls_token`` at zero), the PE table gets a trunc-normal init so the PE hook is exercised.
    ``camera_encoder=False`` leaves out the encoder of known poses (upstream accepts ``cam_enc=None``;
    passing extrinsics then raises), e.g. for a network never trained with known poses.
    """
    _import_upstream()
    from depth_anything_3.model.cam_dec import CameraDec
    from depth_anything_3.model.cam_enc import CameraEnc
    from depth_anything_3.model.da3 import DepthAnything3Net
    from depth_anything_3.model.dinov2.dinov2 import DinoV2
    from depth_anything_3.model.dinov2.vision_transformer import DinoVisionTransformer
    from depth_anything_3.model.dualdpt import DualDPT

    generator_state = torch.random.get_rng_state()
    if seed is not None:
        torch.manual_seed(seed)
    try:
        backbone = DinoV2.__new__(DinoV2)
        nn.Module.__init__(backbone)
        # DinoV2.__init__ only offers the four official ViT sizes; set the same attributes it sets.
        backbone.name, backbone.out_layers = "vits", list(out_layers)
        backbone.alt_start = backbone.qknorm_start = backbone.rope_start = alt_start
        backbone.cat_token = True
        backbone.pretrained = DinoVisionTransformer(
            img_size=518,
            patch_size=14,
            embed_dim=embed_dim,
            depth=depth,
            num_heads=num_heads,
            mlp_ratio=4,
            alt_start=alt_start,
            qknorm_start=alt_start,
            rope_start=alt_start,
            cat_token=True,
        )
        nn.init.trunc_normal_(backbone.pretrained.pos_embed, std=0.02)
        nn.init.trunc_normal_(backbone.pretrained.cls_token, std=0.02)
        head = DualDPT(
            dim_in=2 * embed_dim,
            output_dim=2,
            features=head_features,
            out_channels=list(head_channels),
        )
        cam_dec = CameraDec(dim_in=2 * embed_dim) if camera_decoder else None
        # Built last, so dropping it (camera_encoder=False) leaves every other initial weight as it is.
        cam_enc = CameraEnc(dim_out=embed_dim, num_heads=num_heads) if camera_decoder else None
        model = DepthAnything3Net(backbone, head, cam_dec=cam_dec, cam_enc=cam_enc)
        if not camera_encoder:
            model.cam_enc = None  # upstream's constructor insists on an encoder next to a decoder
        return model.eval()
    finally:
        if seed is not None:
            torch.random.set_rng_state(generator_state)


def build_tiny_nested_network(
    embed_dim: int = 64, metric_embed_dim: int = 48, seed: int | None = 0
) -> nn.Module:
    """A small ``NestedDepthAnything3Net`` of DA3's own classes (for tests).

    The ``da3`` branch is :func:`build_tiny_network`; the ``da3_metric`` branch is built as
    ``da3metric-large`` is: a DINOv2 ViT without RoPE, q/k-norm or alternating attention, no
    camera token, a DPT head with a sky head. The metric sky head's last bias is negative, so
    (ReLU) no pixel is sky and upstream's alignment has pixels to fit.
    """
    _import_upstream()
    from depth_anything_3.model.da3 import DepthAnything3Net, NestedDepthAnything3Net
    from depth_anything_3.model.dinov2.dinov2 import DinoV2
    from depth_anything_3.model.dinov2.vision_transformer import DinoVisionTransformer
    from depth_anything_3.model.dpt import DPT

    generator_state = torch.random.get_rng_state()
    if seed is not None:
        torch.manual_seed(seed)
    try:
        main = build_tiny_network(embed_dim=embed_dim, seed=None)
        backbone = DinoV2.__new__(DinoV2)
        nn.Module.__init__(backbone)
        backbone.name, backbone.out_layers = "vits", [0, 1, 2, 3]
        backbone.alt_start = backbone.qknorm_start = backbone.rope_start = -1
        backbone.cat_token = False
        backbone.pretrained = DinoVisionTransformer(
            img_size=518,
            patch_size=14,
            embed_dim=metric_embed_dim,
            depth=4,
            num_heads=2,
            mlp_ratio=4,
            alt_start=-1,
            qknorm_start=-1,
            rope_start=-1,
            cat_token=False,
        )
        nn.init.trunc_normal_(backbone.pretrained.pos_embed, std=0.02)
        nn.init.trunc_normal_(backbone.pretrained.cls_token, std=0.02)
        head = DPT(dim_in=metric_embed_dim, output_dim=1, features=16, out_channels=[8, 16, 32, 32])
        with torch.no_grad():
            head.scratch.sky_output_conv2[-1].bias.fill_(-1.0)
        nested = NestedDepthAnything3Net.__new__(NestedDepthAnything3Net)
        nn.Module.__init__(nested)  # upstream's __init__ builds from configs (official sizes only)
        nested.da3 = main
        nested.da3_metric = DepthAnything3Net(backbone, head).eval()
        return nested.eval()
    finally:
        if seed is not None:
            torch.random.set_rng_state(generator_state)


def _builders() -> dict:
    builders = {name: _builder(name) for name in SIZE_NAMES}
    try:  # the network raytun3r trains and ships (patches/da3_default.py)
        from raytun3r_plugin.patches.da3_default import BUILDERS as shipped
    except ImportError:
        shipped = {}
    return builders | shipped
