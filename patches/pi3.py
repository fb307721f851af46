"""Pi3 and Pi3X (``yyfz/Pi3`` at 9fa3ddb; not on PyPI, used from a source checkout).

Two families are registered, ``pi3`` (``pi3.models.pi3.Pi3``) and ``pi3x``
(``pi3.models.pi3x.Pi3X``): they share every hook except the prediction grid, and they keep
their RoPE instances in different places.

Hook map (docs/backbones.md), all patched per instance:

* PE: ``encoder.interpolate_pos_encoding(x, w, h)`` of the DINOv2 ViT-L/14-reg image encoder
  (``w`` is the image height; row 0 is the class slot; registers get no PE). Pi3X's
  ``depth_encoder`` (a copy of the encoder) and ``ray_embed`` are conditioning inputs, not the
  image path: they are never patched;
* RoPE: ``RoPE2D.forward(tokens, positions)`` of every instance. Pi3: ``rope`` (decoder, point
  and camera decoders) and a second instance inside ``conf_decoder`` (a ``deepcopy`` of the
  point decoder). Pi3X: the single ``rope`` shared by the decoder, all head decoders and the
  metric decoder. ``decode`` assembles the positions inline (position getter, +1, 5 register
  tokens at (0, 0)); the replacement displaces each patch token by its own upstream position
  and evaluates the angles continuously (``raytun3r_plugin.hooks.grid_position_rope``). Pi3X's PRoPE
  (pose conditioning only) is a separate encoding and is left alone. A compiled ``cuRoPE2D``
  (``models.curope``) is refused by :func:`check` before anything is changed;
* patch tokenisation: ``encoder.patch_embed.forward(x)`` (the image encoder's own instance);
* prediction grid, Pi3X only: ``point_head`` and ``conf_head`` are ``ConvHead``s that
  concatenate raw uv channels from the module function
  ``pi3.models.layers.conv_head.normalized_view_plane_uv`` (looked up in that module's globals).
  Each head instance's ``forward`` is wrapped to mark a context (a ``contextvars`` variable,
  so threads and models do not see each other's); a trampoline in the module's globals returns
  the camera-aware grid (``SizeGeometry.uv_grid``, raw channels, no sinusoid) inside that
  context and defers to the original function everywhere else (see :class:`_UvTrampoline`).
  Pi3 has no grid (its ``LinearPts3d`` heads pixel-shuffle).
"""

from __future__ import annotations

import contextvars
import sys
import threading
import weakref

import torch
from torch import nn

from raytun3r_plugin import hooks
from raytun3r_plugin.errors import MissingDependencyError, UnsupportedUpstreamError, WeightsError
from raytun3r_plugin.poses import invert_rigid  # re-exported: its one home
from raytun3r_plugin.prediction import Prediction, as_batched_images
from raytun3r_plugin.registry import (
    BackboneInfo,
    BackboneSpec,
    PatchTarget,
    PromptTarget,
    UpstreamVersion,
    register,
)
from raytun3r_plugin.weights import StateSignature, count_blocks, load_into, read_checkpoint

UPSTREAM_MODULE = "pi3"
UPSTREAM_COMMIT = "9fa3ddb3f8d53041f8b2738df404f62223bbaa7b"
UPSTREAM = UpstreamVersion(source="yyfz/Pi3", version=UPSTREAM_COMMIT, module=UPSTREAM_MODULE)
#: ``RoPE2D`` is the PyTorch class; ``cuRoPE2D`` the compiled one upstream substitutes when it
#: imports (refused by :func:`_refuse_compiled_rope`, listed so a stray instance is not missed).
ROPE_CLASSES = ("RoPE2D", "cuRoPE2D")
#: ``RoPE2D.__init__(freq)`` stores the base as ``base``.
ROPE_BASE_ATTRIBUTE = "base"
_INSTALL_HINT = (
    "Pi3 is not on PyPI: clone the yyfz/Pi3 repository from GitHub and put it on PYTHONPATH "
    "(it also needs huggingface_hub)"
)
#: Conditioning branches of Pi3X that a checkpoint may lack (``Pi3X.disable_multimodal``).
_MULTIMODAL_PREFIXES = ("depth_encoder.", "depth_emb", "ray_embed.", "pose_inject_blk.")
_UV_FUNCTION = "normalized_view_plane_uv"


# ---------------------------------------------------------------------------------------------
# Recognition, description, structural checks
# ---------------------------------------------------------------------------------------------


def _is(model: nn.Module, class_name: str) -> bool:
    return type(model).__name__ == class_name and type(model).__module__.startswith(UPSTREAM_MODULE)


def recognise_pi3(model: nn.Module) -> nn.Module | None:
    return model if _is(model, "Pi3") else None


def recognise_pi3x(model: nn.Module) -> nn.Module | None:
    return model if _is(model, "Pi3X") else None


def _describe(family: str, official: str):
    def describe(root: nn.Module) -> BackboneInfo:
        encoder = getattr(root, "encoder", None)
        if encoder is None or not isinstance(getattr(encoder, "pos_embed", None), torch.Tensor):
            found = (
                f"{type(encoder).__module__}.{type(encoder).__qualname__}"
                if encoder is not None
                else "nothing"
            )
            raise UnsupportedUpstreamError(
                f"{family}: expected a DINOv2 ViT with an absolute PE table at 'encoder', found {found} "
                f"(the {family} patch was checked against {UPSTREAM})"
            )
        depth = len(root.decoder)
        known = encoder.embed_dim == 1024 and depth == 36
        name = getattr(root, "raytun3r_name", None) or (
            official if known else f"{family}-custom-e{encoder.embed_dim}-d{depth}"
        )
        return BackboneInfo(
            name=name,
            embed_dim=encoder.embed_dim,
            patch_size=encoder.patch_size,
            has_rope=getattr(root, "rope", None) is not None,
            pos_embed=encoder.pos_embed,
            has_grid=family == "pi3x",
        )

    return describe


def _refuse_compiled_rope(root: nn.Module, family: str) -> None:
    for name, module in root.named_modules():
        klass = type(module)
        if klass.__name__ == "cuRoPE2D" or "curope" in klass.__module__.split("."):
            where = name or "<root>"
            raise UnsupportedUpstreamError(
                f"{family}: the model uses the compiled RoPE {klass.__module__}.{klass.__qualname__} at '{where}' "
                "(pi3.models.layers.pos_embed picks it when 'from models.curope import cuRoPE2D' succeeds). "
                "raytun3r needs the PyTorch RoPE2D, whose angles it evaluates at fractional positions: make "
                "'models.curope' unimportable (uninstall or rename the compiled extension), restart Python and "
                "build the model again"
            )


def _check(family: str):
    def check(root: nn.Module) -> None:
        _refuse_compiled_rope(root, family)

    return check


# ---------------------------------------------------------------------------------------------
# Pi3X ConvHead uv channels: per-instance context + module-level trampoline
# ---------------------------------------------------------------------------------------------

#: (state, image height, image width) of the ConvHead forward running in this context, or None.
_UV_CONTEXT: contextvars.ContextVar[tuple | None] = contextvars.ContextVar(
    "raytun3r_pi3x_uv", default=None
)


class _UvTrampoline:
    """Stands in for ``normalized_view_plane_uv`` in the ``conv_head`` module's globals.

    ``ConvHead.forward`` looks the function up by name at call time, so a per-instance hook is
    impossible there; instead each patched head's ``forward`` sets :data:`_UV_CONTEXT`, and this
    function returns the camera-aware grid while (and only while) that context is active. Outside
    it (other models, unpatched heads, disabled handles, other threads) it calls the original
    function with the same arguments, so it is harmless while installed.

    Lifetime: installed lazily by the first patched forward that needs it (``apply`` itself
    changes no module global), shared by every patched Pi3X, and removed again (the original
    function put back) when the last head wrapper that uses it is released, which is at
    ``remove()`` (the wrappers are freed when the core deletes them from the heads) or when a
    patched model is garbage-collected; a deep copy of a patched Pi3X rebuilds its head wrappers,
    which count as users of their own. If something
    else replaced the module attribute in the meantime, it is left as found.
    """

    _lock = threading.Lock()
    _users: dict[str, int] = {}  # module name -> live head wrappers

    def __init__(self, module, original):
        self.module = module
        self.original = original
        self.__wrapped__ = original
        self.__name__ = getattr(original, "__name__", _UV_FUNCTION)
        self.__doc__ = getattr(original, "__doc__", None)

    def __call__(self, width, height, aspect_ratio=None, dtype=None, device=None):
        active = _UV_CONTEXT.get()
        if active is not None:
            state, image_h, image_w = active
            if state.uses("grid"):
                grid = state.geometry(image_h, image_w).uv_grid(
                    int(height),
                    int(width),
                    device if device is not None else torch.device("cpu"),
                    dtype or torch.get_default_dtype(),
                )
                if grid is not None:
                    return grid
        return self.original(
            width=width, height=height, aspect_ratio=aspect_ratio, dtype=dtype, device=device
        )

    @classmethod
    def installed(cls, module) -> _UvTrampoline | None:
        current = getattr(module, _UV_FUNCTION, None)
        return current if isinstance(current, cls) else None

    @classmethod
    def retain(cls, module) -> None:
        with cls._lock:
            cls._users[module.__name__] = cls._users.get(module.__name__, 0) + 1

    @classmethod
    def release(cls, module) -> None:
        with cls._lock:
            left = cls._users.get(module.__name__, 0) - 1
            cls._users[module.__name__] = max(left, 0)
            trampoline = cls.installed(module)
            if left <= 0 and trampoline is not None:
                setattr(module, _UV_FUNCTION, trampoline.original)

    @classmethod
    def ensure(cls, module) -> None:
        if cls.installed(module) is not None:
            return
        with cls._lock:
            if cls.installed(module) is None:
                setattr(module, _UV_FUNCTION, cls(module, getattr(module, _UV_FUNCTION)))


def conv_head_uv(owner, state):
    """Wrap ``ConvHead.forward(hidden_states, image, patch_h, patch_w)`` of one head instance."""
    module = sys.modules.get(type(owner).__module__)
    if module is None or not callable(getattr(module, _UV_FUNCTION, None)):
        raise UnsupportedUpstreamError(
            f"{type(owner).__module__}: expected a module-level '{_UV_FUNCTION}' next to {type(owner).__qualname__}, found none"
        )
    patch = state.info.patch_size

    def forward(original, hidden_states, image=None, patch_h=None, patch_w=None):
        if not state.uses("grid"):
            return original(hidden_states, image, patch_h, patch_w)
        if image is not None:
            image_h, image_w = image.shape[-2:]
        else:  # as upstream: the image is patch_h x patch_w patches of 14 px
            image_h, image_w = patch_h * patch, patch_w * patch
        _UvTrampoline.ensure(module)
        token = _UV_CONTEXT.set((state, int(image_h), int(image_w)))
        try:
            return original(hidden_states, image, patch_h, patch_w)
        finally:
            _UV_CONTEXT.reset(token)

    _UvTrampoline.retain(module)
    weakref.finalize(forward, _UvTrampoline.release, module)
    return forward


# ---------------------------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------------------------

_PE = PatchTarget(
    name="pe_interpolation",
    hook="pe",
    owners=("encoder",),
    attribute="interpolate_pos_encoding",
    signature=("x", "w", "h"),
    owner_classes=("DinoVisionTransformer",),
    build=hooks.pe_interpolation,
)
_PATCH_EMBED = PatchTarget(
    name="patch_embedding",
    hook="patch_embed",
    owners=("encoder.patch_embed",),
    attribute="forward",
    signature=("x",),
    owner_classes=("PatchEmbed",),
    build=hooks.patch_embedding,
)


def _rope_target(owners: tuple[str, ...]) -> PatchTarget:
    return PatchTarget(
        name="rope",
        hook="rope",
        owners=owners,
        attribute="forward",
        signature=("tokens", "positions"),
        owner_classes=("RoPE2D",),
        build=hooks.grid_position_rope,
    )


PI3_ROPE_OWNERS = (
    "rope",
    "conf_decoder.blocks.0.attn.rope",
)  # conf_decoder is a deepcopy: own instance
PI3X_ROPE_OWNERS = ("rope",)  # one instance shared by the decoder and every head decoder

PI3_TARGETS = (_PE, _rope_target(PI3_ROPE_OWNERS), _PATCH_EMBED)
PI3X_TARGETS = (
    _PE,
    _rope_target(PI3X_ROPE_OWNERS),
    _PATCH_EMBED,
    PatchTarget(
        name="prediction_grid",
        hook="grid",
        owners=("point_head", "conf_head"),
        attribute="forward",
        signature=("hidden_states", "image", "patch_h", "patch_w"),
        owner_classes=("ConvHead",),
        build=conv_head_uv,
        per_view=False,  # upstream builds one uv grid for the whole batch
    ),
)


# ---------------------------------------------------------------------------------------------
# Prediction
# ---------------------------------------------------------------------------------------------


_PREDICT_LOCKS: weakref.WeakKeyDictionary[nn.Module, threading.Lock] = weakref.WeakKeyDictionary()
_PREDICT_LOCKS_GUARD = threading.Lock()


def _run_keeping_pi3x_poses(
    root: nn.Module, images: torch.Tensor, kwargs: dict
) -> tuple[dict, torch.Tensor]:
    """Run Pi3X and return (outputs, differentiable world_from_cam (B, N, 4, 4)).

    Upstream ``Pi3X.forward_head`` scales the pose translations by the metric scale *in place*
    (``camera_poses[..., :3, 3] = camera_poses[..., :3, 3] * metric``) after using them for
    ``points``, so backpropagating through its ``camera_poses`` (or ``points``) fails. A forward
    hook on ``camera_head``, present only during this call, hands upstream a copy to modify and
    keeps the head's own output; the same scaling is then applied out of place here. Values are
    identical to upstream's ``camera_poses``.
    """
    with _PREDICT_LOCKS_GUARD:
        lock = _PREDICT_LOCKS.setdefault(root, threading.Lock())
    kept = []

    def keep(module, args, output):
        kept.append(output)
        return output.clone()

    with lock:  # hooks of one module must not be added / removed by two threads at once
        hook = root.camera_head.register_forward_hook(keep)
        try:
            output = root(images, **kwargs)
        finally:
            hook.remove()
    batch, views = images.shape[:2]
    poses = kept[-1].reshape(batch, views, 4, 4)
    translation = poses[..., :3, 3:] * output["metric"].reshape(batch, 1, 1, 1)
    world_from_cam = torch.cat(
        (torch.cat((poses[..., :3, :3], translation), dim=-1), poses[..., 3:, :]), dim=-2
    )
    return output, world_from_cam


def predict(root: nn.Module, images: torch.Tensor, **kwargs) -> Prediction:
    """Run Pi3 / Pi3X on images in [0, 1] (they normalise them themselves).

    * cam_from_world = inverse of upstream's ``camera_poses`` (world_from_cam, OpenCV axes);
      differentiable for Pi3X too (see :func:`_run_keeping_pi3x_poses`);
    * depth = |local_points|, the distance from the camera centre to the predicted point, i.e.
      the range along the ray: Pi3 predicts camera-frame points, and raytun3r reads the depth
      channel as range (docs/conventions.md section 2), so X = depth * ray(u, v) gives the point back when
      its direction follows the camera. Upstream's z (planar depth) is ``extras["depth_z"]``;
    * confidence = sigmoid of upstream's ``conf`` logits.

    ``extras`` also holds ``local_points`` and ``points`` (and Pi3X's ``rays``, ``metric``); with
    Pi3X, ``points`` carries no usable gradient (upstream's in-place scaling). Keyword arguments
    go to the model's forward (e.g. Pi3X conditions).
    """
    images = as_batched_images(images, getattr(root, "patch_size", 14))
    if _is(root, "Pi3X") and torch.is_grad_enabled():
        output, world_from_cam = _run_keeping_pi3x_poses(root, images, kwargs)
    else:
        output = root(images, **kwargs)
        world_from_cam = output["camera_poses"]
    local_points = output["local_points"]
    extras = {
        "local_points": local_points,
        "points": output["points"],
        "depth_z": local_points[..., 2],
    }
    for key in ("rays", "metric"):
        if key in output:
            extras[key] = output[key]
    return Prediction(
        depth=local_points.norm(dim=-1),
        cam_from_world=invert_rigid(world_from_cam),
        confidence=torch.sigmoid(output["conf"][..., 0]),
        extras=extras,
    )


# ---------------------------------------------------------------------------------------------
# Builders
# ---------------------------------------------------------------------------------------------


def build_network(name: str) -> nn.Module:
    """A randomly initialised ``Pi3()`` or ``Pi3X()`` from the user's installed upstream code."""
    try:
        if name == "pi3":
            from pi3.models.pi3 import Pi3 as network
        else:
            from pi3.models.pi3x import Pi3X as network
    except ImportError as error:
        raise MissingDependencyError(f"Pi3 is not importable ({error}); {_INSTALL_HINT}") from error
    return network()


def load_weights(model: nn.Module, state: dict, source: str) -> nn.Module:
    """Load a Pi3 / Pi3X checkpoint (keys unprefixed) strictly.

    A Pi3X checkpoint saved without the conditioning branches (``disable_multimodal``) is loaded
    into a model with those branches removed, still strictly.
    """
    if _is(model, "Pi3X") and getattr(model, "use_multimodal", False):
        if not any(key.startswith(_MULTIMODAL_PREFIXES) for key in state):
            model.disable_multimodal(free_cuda_cache=False)
    return load_into(model, state, source)


#: One official size per family; Pi3X is told from Pi3 by its metric branch.
SIZE_NAMES = ("pi3", "pi3x")
_PI3X_ONLY = ("metric_token", "metric_decoder.", "metric_head.")


def identify(state: dict[str, torch.Tensor]) -> StateSignature | None:
    """A Pi3 or Pi3X state dict (DINOv2 ``encoder`` PE table + ``point_decoder``), else ``None``."""
    pe = state.get("encoder.pos_embed")
    if pe is None or not any(key.startswith("point_decoder.") for key in state):
        return None
    name = "pi3x" if any(key.startswith(_PI3X_ONLY) for key in state) else "pi3"
    depth = count_blocks(state, "encoder.blocks.")
    multimodal = any(key.startswith(_MULTIMODAL_PREFIXES) for key in state)
    detail = f"encoder embed dim {int(pe.shape[-1])}, {depth} encoder blocks"
    if name == "pi3x":
        detail += ", with" if multimodal else ", without"
        detail += " the conditioning branches"
    return StateSignature(name, (name,), detail, tuple(pe.shape))


def _builder(name: str):
    def build(path=None) -> nn.Module:
        if path is None:
            raise WeightsError(
                f"{name} needs a local weight file (.safetensors or .pt); raytun3r never downloads"
            )
        checkpoint = read_checkpoint(path)  # before the (slow) build: a bad path fails at once
        model = load_weights(build_network(name), checkpoint.state, checkpoint.source)
        model.raytun3r_name = name
        return model

    build.takes_checkpoint = True  # load_backbone passes the Checkpoint it has read
    return build


#: Calibration tokens (Pi3 and Pi3X share the decoder loop of ``decode``): one token set per
#: ``decoder`` BlockRope (36 at full size; even index: frame attention on (B*N, hw, C), odd:
#: global attention on (B, N*hw, C)), inserted after the 5 register tokens. Each block's own
#: ``forward`` is the runner; ``decode``'s N gives the frame count of the global layout. The
#: DINOv2 encoder is not covered.
PROMPT_TARGET = PromptTarget(
    owner="decoder",
    attribute="forward",
    signature=("x", "xpos"),
    blocks="decoder",
    insert_at=5,
    select=None,
    pos_argument="xpos",
    layout=("frame", "global"),
    frames=("", "decode", "N"),
)


PI3_SPEC = register(
    BackboneSpec(
        family="pi3",
        upstream=UPSTREAM,
        recognise=recognise_pi3,
        describe=_describe("pi3", "pi3"),
        targets=PI3_TARGETS,
        predict=predict,
        builders={"pi3": _builder("pi3")},
        rope_classes=ROPE_CLASSES,
        rope_base_attribute=ROPE_BASE_ATTRIBUTE,
        transformer_blocks=("encoder.blocks", "decoder"),
        prompt_target=PROMPT_TARGET,
        check=_check("pi3"),
    )
)
PI3X_SPEC = register(
    BackboneSpec(
        family="pi3x",
        upstream=UPSTREAM,
        recognise=recognise_pi3x,
        describe=_describe("pi3x", "pi3x"),
        targets=PI3X_TARGETS,
        predict=predict,
        builders={"pi3x": _builder("pi3x")},
        rope_classes=ROPE_CLASSES,
        rope_base_attribute=ROPE_BASE_ATTRIBUTE,
        transformer_blocks=("encoder.blocks", "decoder"),
        prompt_target=PROMPT_TARGET,
        check=_check("pi3x"),
    )
)
SPEC = PI3_SPEC
