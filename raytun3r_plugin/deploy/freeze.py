"""Freeze a (patched) model for one camera and input size: a plain module for export.

On a device the camera and the input size are fixed, so everything raytun3r computes from them
(the PE table after the adapter, the RoPE positions and their displacement, the patch
resampling grid, the valid-token mask, the heads' coordinate embedding) is a constant.
:func:`freeze` copies the model, runs it once at that size to record those values, removes the
copy's patch, and installs in place of each hooked upstream method a frozen one
(:mod:`raytun3r_plugin.deploy.frozen`) that reads them from registered buffers. The result runs
no patching code, camera model, adapter or cache, and has no data-dependent shape: upstream's
RoPE table length ``int(positions.max()) + 1`` becomes a constant too. Upstream code that no
exported graph can hold is replaced in the copy by an equivalent (``EXPORT_EQUIVALENTS``): Pi3's
SVD orthogonalisation (:mod:`~raytun3r_plugin.deploy.rotation`), nested DA3's masked quantiles
(:mod:`~raytun3r_plugin.deploy.metric_alignment`). It is checked against the model it was
frozen from before it is returned.

The same path freezes an unpatched model (every upstream PE table, position grid and head
embedding made a constant as well), which is the fair baseline of the deployment costs
(benchmarks/deploy_cost.py).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from raytun3r_plugin import hooks
from raytun3r_plugin.deploy import frozen, metric_alignment, rotation
from raytun3r_plugin.errors import InputError, UnsupportedUpstreamError
from raytun3r_plugin.patching import handle_of
from raytun3r_plugin.prediction import Prediction
from raytun3r_plugin.registry import (
    HOOK_KINDS,
    BackboneSpec,
    branch_roots,
    resolve_targets,
    rope_base,
    spec_for,
    uncompiled,
)

#: The families :func:`freeze` supports; the others are refused with the hook that blocks them.
SUPPORTED = ("da3", "da3nested", "vggt", "pi3")
#: RoPE classes -> (table method, 1-D apply method) of upstream, both used as they are.
ROPE_METHODS = {
    "RotaryPositionEmbedding2D": ("_compute_frequency_components", "_apply_1d_rope"),
    "RoPE2D": ("get_cos_sin", "apply_rope1d"),
}
#: Upstream methods that block export, by family: (class name, method, the export-friendly
#: equivalent installed on every instance in the frozen copy). Pi3's SVD has no ONNX operator;
#: DA3's sky handling and nested alignment select pixels with boolean masks (data-dependent
#: sizes). docs/decisions.md "Export equivalents of Pi3's SVD and nested DA3's masked quantiles".
EXPORT_EQUIVALENTS: dict[str, tuple[tuple[str, str, Callable], ...]] = {
    "da3nested": (
        (
            "DepthAnything3Net",  # the metric branch's own sky handling
            "_process_mono_sky_estimation",
            metric_alignment.frozen_mono_sky_estimation,
        ),
        (
            "NestedDepthAnything3Net",
            "_apply_depth_alignment",
            metric_alignment.frozen_depth_alignment,
        ),
        ("NestedDepthAnything3Net", "_handle_sky_regions", metric_alignment.frozen_sky_regions),
    ),
    "pi3": (("CameraHead", "svd_orthogonalize", rotation.frozen_svd_orthogonalize),),
}
#: The frozen model against the model it was frozen from, on the probe images (max relative).
SELF_CHECK_TOLERANCE = 1e-5


class FrozenModel(nn.Module):
    """A model frozen for one camera and input size: ``forward(images) -> (depth, confidence,
    cam_from_world)``.

    images: (batch, views, 3, H, W) in [0, 1], exactly the frozen shape. Returns depth
    (batch, views, H, W), confidence (same shape; ones where the backbone predicts none) and
    cam_from_world (batch, views, 4, 4), in the conventions of :class:`~raytun3r_plugin.Prediction`.
    """

    def __init__(self, network: nn.Module, predict: Callable, shape: tuple[int, ...], info: dict):
        super().__init__()
        self.network = network
        self._predict = predict
        self.shape = tuple(shape)
        self.info = dict(info)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if tuple(images.shape) != self.shape:
            raise InputError(
                f"this model is frozen for images of shape {self.shape} (batch, views, 3, H, W), got {tuple(images.shape)}"
            )
        prediction = self._predict(self._root(), images)
        return _outputs(prediction)

    def _root(self) -> nn.Module:
        return spec_for(self.network)[1]


def _outputs(prediction: Prediction) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    confidence = prediction.confidence
    if confidence is None:
        confidence = torch.ones_like(prediction.depth)
    return prediction.depth, confidence.reshape(prediction.depth.shape), prediction.cam_from_world


@dataclass
class _Recording:
    """Every call of one hooked method during the probe forward."""

    calls: list[tuple[tuple, dict, Any]] = field(default_factory=list)
    zero_outputs: list[torch.Tensor] = field(default_factory=list)


def freeze(
    model: nn.Module,
    size: tuple[int, int],
    views: int,
    batch: int = 1,
    images: torch.Tensor | None = None,
) -> FrozenModel:
    """A :class:`FrozenModel` of ``model`` (patched or not) for images of ``size`` = (H, W) px.

    Args:
        model: a supported backbone (``SUPPORTED``), patched with one camera (``apply``) or not.
        size: the input (height, width) in pixels, multiples of the patch size.
        views: the number of views S of every forward.
        batch: the batch size B.
        images: probe images (batch, views, 3, H, W) in [0, 1] (default: a fixed random draw);
            the frozen model is checked against ``model`` on them.

    Raises:
        UnsupportedUpstreamError: a backbone whose hooks have no constant form here
            (Pi3X's uv trampoline, VGGT-Omega), naming the hook.
        InputError: a rig (several cameras; freeze each camera's model instead), a size that
            is not a multiple of the patch size, or probe images of another shape.
    """
    spec, root = spec_for(model)
    height, width = (int(v) for v in size)
    shape = (int(batch), int(views), 3, height, width)
    _check_request(model, spec, root, shape)
    if images is None:
        generator = torch.Generator().manual_seed(0)
        images = 0.25 + 0.5 * torch.rand(shape, generator=generator)
    if tuple(images.shape) != shape:
        raise InputError(f"probe images have shape {tuple(images.shape)}, expected {shape}")
    device = next(root.parameters()).device
    images = images.to(device)

    work = copy.deepcopy(uncompiled(model))  # patched copies get their own handle
    work_spec, work_root = spec_for(work)
    targets = [
        (target, owner, branch_spec)
        for _path, branch_spec, branch in branch_roots(work_spec, work_root)
        for target, _owner_path, owner in resolve_targets(branch_spec, branch, set(HOOK_KINDS))
    ]
    recordings = _record(targets)
    with torch.no_grad():
        expected = _outputs(work_spec.predict(work_root, images))
    states = {id(owner): _state_of(owner, target) for target, owner, _ in targets}
    handle = handle_of(work)
    if handle is not None:
        handle.remove()
    for target, owner, _ in targets:  # the recorders (of an unpatched copy) go too
        if isinstance(vars(owner).get(target.attribute), _Recorder):
            del vars(owner)[target.attribute]
    for target, owner, branch_spec in targets:
        _install(
            target,
            owner,
            branch_spec,
            recordings[id(owner), target.attribute],
            states[id(owner)],
            (height, width),
        )

    replaced = _install_export_equivalents(work, spec.family)
    info = {"family": spec.family, "patched": handle is not None, "size": (height, width)}
    result = FrozenModel(work, work_spec.predict, shape, {**info, "replaced": replaced}).eval()
    with torch.no_grad():
        got = result(images)
    _self_check(expected, got)
    return result


def _check_request(model: nn.Module, spec: BackboneSpec, root: nn.Module, shape) -> None:
    if spec.family not in SUPPORTED:
        blocker = {
            "pi3x": "its heads' uv channels come from a module-global trampoline with a context "
            "variable (patches/pi3.py), which has no constant form here",
            "vggt_omega": "its RoPE table and unflattened patch embedding hooks have no constant "
            "form here",
        }.get(spec.family, "no frozen form of its hooks is written")
        raise UnsupportedUpstreamError(
            f"{spec.family} cannot be frozen for export: {blocker}; supported: {', '.join(SUPPORTED)}"
        )
    handle = handle_of(model)
    if handle is not None and handle.is_rig:
        raise InputError(
            "a rig (several cameras) cannot be frozen into one graph: apply and freeze one model per camera"
        )
    patch = spec.describe(root).patch_size
    if shape[3] % patch or shape[4] % patch or min(shape) < 1:
        raise InputError(
            f"size {shape[3]}x{shape[4]} px (H x W) is not a positive multiple of the patch size {patch}"
        )


class _Recorder:
    """Stands in for one hooked method during the probe: calls it and keeps every call."""

    def __init__(self, current: Callable, recording: _Recording, zero_probe: bool):
        self.current, self.recording, self.zero_probe = current, recording, zero_probe

    def __call__(self, *args, **kwargs):
        output = self.current(*args, **kwargs)
        self.recording.calls.append((args, kwargs, output))
        if self.zero_probe:  # x + embedding at x = 0 is the embedding, exactly
            self.recording.zero_outputs.append(
                self.current(torch.zeros_like(args[0]), *args[1:], **kwargs)
            )
        return output


def _record(targets) -> dict:
    recordings = {}
    for target, owner, _spec in targets:
        recording = _Recording()
        recordings[id(owner), target.attribute] = recording
        current = getattr(owner, target.attribute)  # the wrapper, or upstream's bound method
        additive = target.build is hooks.uv_grid_embedding
        object.__setattr__(owner, target.attribute, _Recorder(current, recording, additive))
    return recordings


def _state_of(owner, target):
    recorder = vars(owner).get(target.attribute)
    wrapper = getattr(recorder, "current", None)
    return getattr(wrapper, "_state", None)


def _install(target, owner, spec, recording: _Recording, state, size: tuple[int, int]) -> None:
    """Install the frozen form of one hooked method (nothing where upstream's needs none)."""
    where = f"{type(owner).__qualname__}.{target.attribute}"
    build = target.build
    if build in (hooks.pe_interpolation,) or target.name == "rope_positions":
        _install_constant(owner, target.attribute, recording, where)
    elif build is hooks.uv_grid_embedding:
        _install_added(owner, target.attribute, recording, where)
    elif build is hooks.patch_embedding:
        _install_patch_embedding(owner, state, size)
    elif build in (hooks.continuous_rope, hooks.grid_position_rope):
        _install_rope(owner, spec, recording, state, size, build is hooks.grid_position_rope)
    elif target.name == "rope_reference_view":
        pass  # it changes only a rig's forward, and rigs are refused
    else:
        raise UnsupportedUpstreamError(
            f"{spec.family}: the {target.name!r} hook ({where}) has no frozen form"
        )


def _install_export_equivalents(work: nn.Module, family: str) -> list[str]:
    """Install ``EXPORT_EQUIVALENTS[family]`` on the frozen copy; returns what was replaced
    (``Class.method`` names)."""
    replaced = []
    for module in work.modules():
        names = {klass.__name__ for klass in type(module).__mro__}
        for class_name, attribute, function in EXPORT_EQUIVALENTS.get(family, ()):
            if class_name in names and callable(getattr(type(module), attribute, None)):
                method = frozen.FrozenMethod(module, attribute, function)
                object.__setattr__(module, attribute, method)
                replaced.append(f"{class_name}.{attribute}")
    return sorted(set(replaced))


def _register(owner: nn.Module, name: str, value: torch.Tensor) -> str:
    full = f"{frozen.BUFFER_PREFIX}{name}"
    owner.register_buffer(full, value.detach().clone(), persistent=False)
    return full


def _install_constant(owner, attribute: str, recording: _Recording, where: str) -> None:
    if not recording.calls:
        return
    args, _kwargs, output = recording.calls[0]
    single = not isinstance(output, tuple)
    values = (output,) if single else output
    for _args, _kwargs, other in recording.calls[1:]:
        others = (other,) if single else other
        if not all(_same(a, b) for a, b in zip(values, others, strict=True)):
            raise UnsupportedUpstreamError(
                f"{where}: differs between calls of one forward; cannot freeze it"
            )
    names = [
        None if value is None else _register(owner, f"{attribute}_{index}", value)
        for index, value in enumerate(values)
    ]
    key = tuple(arg for arg in args if isinstance(arg, int))
    method = frozen.FrozenMethod(
        owner, attribute, frozen.constant_output, names=names, single=single, key=key, where=where
    )
    object.__setattr__(owner, attribute, method)


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and bool(torch.equal(a, b))


def _install_added(owner, attribute: str, recording: _Recording, where: str) -> None:
    if not recording.calls:
        return
    table = {}
    for (args, _kwargs, _output), embedding in zip(
        recording.calls, recording.zero_outputs, strict=True
    ):
        shape = tuple(args[0].shape[1:])
        if shape not in table:
            table[shape] = _register(owner, f"{attribute}_{len(table)}", embedding)
    method = frozen.FrozenMethod(owner, attribute, frozen.added_constant, table=table, where=where)
    object.__setattr__(owner, attribute, method)


def _install_patch_embedding(owner, state, size: tuple[int, int]) -> None:
    if state is None:
        return  # upstream's patch embedding is already static
    geometry = state.geometry(*size)
    device = next(owner.parameters()).device
    grid = valid = None
    if state.uses("patch_resample"):
        sampled = geometry.resample_grid(device, torch.float32, state.resample_map)
        grid = None if sampled is None else _register(owner, "resample_grid", sampled)
    if state.uses("border_tokens"):
        mask = geometry.token_valid(device)
        valid = None if mask is None else _register(owner, "valid_tokens", mask)
    if grid is None and valid is None:
        return
    method = frozen.FrozenMethod(
        owner, "forward", frozen.resampled_patch_embedding, grid=grid, valid=valid
    )
    object.__setattr__(owner, "forward", method)


def _install_rope(
    owner, spec: BackboneSpec, recording: _Recording, state, size, by_grid: bool
) -> None:
    """Fixed-size RoPE: upstream's tables as buffers, and the adapter's displacement table
    where the patch displaced each call's positions (VGGT, Pi3: ``grid_position_rope``); DA3's
    displaced positions are already constants (``_prepare_rope``)."""
    methods = next(
        (
            ROPE_METHODS[klass.__name__]
            for klass in type(owner).__mro__
            if klass.__name__ in ROPE_METHODS
        ),
        None,
    )
    if methods is None:
        raise UnsupportedUpstreamError(
            f"{spec.family}: RoPE class {type(owner).__qualname__} has no known table methods ({sorted(ROPE_METHODS)})"
        )
    table_method, apply_1d = methods
    integer = [args[1] for args, _, _ in recording.calls if not args[1].is_floating_point()]
    calls = [args for args, _, _ in recording.calls]
    if not calls:
        return
    tokens = calls[0][0]
    half = tokens.shape[-1] // 2
    count = max([int(p.max()) for p in integer], default=0) + 1
    cos, sin = getattr(owner, table_method)(half, count, tokens.device, tokens.dtype)
    displacement = None
    columns = size[1] // state.info.patch_size if state is not None else 1
    if state is not None and by_grid and state.uses("rope"):
        geometry = state.geometry(*size)
        table = state.rope_displacement(geometry, tokens.device, torch.float32)
        table = torch.cat((table.new_zeros(1, 2), table))
        displacement = _register(owner, "rope_displacement", table)
    method = frozen.FrozenMethod(
        owner,
        "forward",
        frozen.fixed_size_rope,
        cos=_register(owner, "rope_cos", cos),
        sin=_register(owner, "rope_sin", sin),
        apply_1d=apply_1d,
        base=rope_base(spec, owner),
        displacement=displacement,
        columns=columns,
    )
    object.__setattr__(owner, "forward", method)


def _self_check(expected: tuple, got: tuple) -> None:
    """The frozen model must give the outputs of the model it was frozen from."""
    for name, want, have in zip(
        ("depth", "confidence", "cam_from_world"), expected, got, strict=True
    ):
        scale = float(want.abs().max()) or 1.0
        difference = float((want - have).abs().max()) / scale
        if not difference <= SELF_CHECK_TOLERANCE:
            raise UnsupportedUpstreamError(
                f"the frozen model's {name} differs from the model's by {difference:.2e} (relative): "
                "an upstream method this freeze does not know computes a size-dependent value; "
                "export is refused rather than wrong"
            )
