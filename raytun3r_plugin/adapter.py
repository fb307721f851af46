"""The learned part of raytun3r: radial/angular lookup tables, and their file format (v1).

A fresh adapter is all zeros and therefore the identity. The file is one ``.safetensors`` with
exactly the tensors ``pe.radial`` [N_r, C], ``pe.angular`` [N_theta, C] and, for RoPE backbones,
``rope.radial`` [N_r_rope], all float32, plus string metadata (docs/conventions.md section 4). Loading never
unpickles: safetensors stores raw tensors and a JSON header.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from raytun3r_plugin.errors import AdapterError, CameraError

if TYPE_CHECKING:  # annotations only: `import raytun3r_plugin` should not load the camera models
    from raytun3r_plugin.cameras.base import Camera

FORMAT = "raytun3r-adapter"
FORMAT_VERSION = "1"
DEFAULT_N_R = 20
DEFAULT_N_THETA = 8
DEFAULT_N_R_ROPE = 20

#: Corrections that can be switched on and off (docs/conventions.md section 5); tables are "pe" and "rope".
#: Each is a key of every components dict (``adapter.components``, ``handle.components``).
COMPONENTS = ("pe", "rope", "patch_resample", "border_tokens", "grid")
#: Switches (docs/components.md), off unless named: ``"pe_radial_only"`` applies only the
#: radial PE table (needs ``"pe"``); ``"pe_naive_remap"`` samples the backbone's own PE table at
#: the tokens' perspective (undistorted) positions instead of ``"pe"`` (excludes it);
#: ``"resample_turned"`` resamples each patch as a pinhole turned to its own ray instead of the
#: pinhole on the lens axis (needs ``"patch_resample"``; ``geometry.patch_resample_grid``). A
#: components dict carries a switch only while it is on, so files and dicts without one keep
#: their meaning.
ABLATION_SWITCHES = ("pe_radial_only", "pe_naive_remap", "resample_turned")
#: Every name ``components=`` accepts.
KNOWN_COMPONENTS = COMPONENTS + ABLATION_SWITCHES

#: The largest adapter file :meth:`Adapter.load` reads (a default adapter is about 45 KB).
MAX_FILE_BYTES = 16 * 2**20
#: ``[low, high]`` of each size in an adapter's metadata and constructor.
SIZE_LIMITS = {
    "embed_dim": (1, 8192),
    "patch_size": (1, 64),
    "n_r": (2, 1024),
    "n_theta": (1, 1024),
    "n_r_rope": (0, 1024),
}
#: Largest magnitude a table entry may have: PE units (a backbone's PE entries are O(0.1)) and
#: RoPE displacement in tokens (a 1024 px input is 73 tokens wide). A file over it is corrupt.
TABLE_LIMITS = {"pe.radial": 100.0, "pe.angular": 100.0, "rope.radial": 100.0}

_REQUIRED_METADATA = (
    "format",
    "format_version",
    "backbone",
    "embed_dim",
    "patch_size",
    "n_r",
    "n_theta",
    "n_r_rope",
    "camera",
    "components",
    "pe_fingerprint",
    "raytun3r_version",
    "training",
)


def pe_fingerprint(pos_embed: torch.Tensor | None) -> str:
    """Short hash of a backbone's absolute PE table, to tell weight sets apart ("" without one)."""
    if pos_embed is None:
        return ""
    data = pos_embed.detach().to("cpu", torch.float32).contiguous().numpy().tobytes()
    return hashlib.sha256(data).hexdigest()[:16]


def normalise_components(
    components: Mapping[str, bool] | list[str] | tuple[str, ...] | set[str] | None,
) -> dict[str, bool]:
    """Turn a component list or mapping into ``{name: enabled}``.

    The result has every name of :data:`COMPONENTS` and, only while switched on, the
    :data:`ABLATION_SWITCHES`. A mapping's missing corrections are on and its missing ablation
    switches off; a list names exactly what is on (a single name is a list of one); None is
    every correction, no ablation.

    Raises:
        AdapterError: an unknown name, a value that is not a bool, ``"pe_naive_remap"`` together
            with ``"pe"`` (the remap replaces the PE correction), or ``"pe_radial_only"``
            without ``"pe"`` or ``"resample_turned"`` without ``"patch_resample"`` (each
            modifies a correction that is off).
    """
    if components is None:
        return dict.fromkeys(COMPONENTS, True)
    if isinstance(components, str):
        # A bare string would otherwise be read as a set of one-letter names.
        components = [components]
    unknown = set(components) - set(KNOWN_COMPONENTS)
    if unknown:
        raise AdapterError(
            f"unknown components {sorted(map(str, unknown))}; known: {list(KNOWN_COMPONENTS)}"
        )
    if isinstance(components, Mapping):
        not_bool = [name for name, value in components.items() if not isinstance(value, bool)]
        if not_bool:
            raise AdapterError(
                f"component {not_bool[0]!r} must be True or False, got {components[not_bool[0]]!r}"
            )
        result = {name: components.get(name, True) for name in COMPONENTS}
        result |= {name: True for name in ABLATION_SWITCHES if components.get(name, False)}
    else:
        names = set(components)
        result = {name: name in names for name in COMPONENTS}
        result |= {name: True for name in ABLATION_SWITCHES if name in names}
    if result.get("pe_naive_remap") and result["pe"]:
        raise AdapterError(
            "components 'pe_naive_remap' and 'pe' exclude each other: the naive remap replaces "
            "raytun3r's PE correction; switch 'pe' off (e.g. components=['pe_naive_remap', ...])"
        )
    if result.get("pe_radial_only") and not result["pe"]:
        raise AdapterError(
            "component 'pe_radial_only' restricts the 'pe' correction to its radial table, "
            "but 'pe' is off; switch 'pe' on or leave 'pe_radial_only' out"
        )
    if result.get("resample_turned") and not result["patch_resample"]:
        raise AdapterError(
            "component 'resample_turned' chooses the local map of the 'patch_resample' "
            "correction, but 'patch_resample' is off; switch it on or leave 'resample_turned' out"
        )
    return result


class Adapter(nn.Module):
    """Radial/angular PE tables and a radial RoPE table for one backbone and one camera.

    Attributes:
        pe.radial: (n_r, C) radial PE update at rho_k = k / (n_r - 1).
        pe.angular: (n_theta, C) angular PE update at 2 pi k / n_theta, scaled by rho when applied.
        rope.radial: (n_r_rope,) radial RoPE displacement in token units (RoPE backbones only).
        camera: the camera the adapter was fitted on (or None before fitting).
    """

    def __init__(
        self,
        backbone: str,
        embed_dim: int,
        patch_size: int = 14,
        n_r: int = DEFAULT_N_R,
        n_theta: int = DEFAULT_N_THETA,
        n_r_rope: int = DEFAULT_N_R_ROPE,
        camera: Camera | None = None,
        components=None,
        pe_fingerprint: str = "",
        training: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        given = {
            "embed_dim": embed_dim,
            "patch_size": patch_size,
            "n_r": n_r,
            "n_theta": n_theta,
            "n_r_rope": n_r_rope,
        }
        for name, value in given.items():
            low, high = SIZE_LIMITS[name]
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise AdapterError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
        if not isinstance(backbone, str) or not backbone:
            raise AdapterError(f"backbone must be a non-empty string, got {backbone!r}")
        if training is not None and not isinstance(training, Mapping):
            raise AdapterError(f"training must be a mapping, got {type(training).__name__}")
        self.backbone = backbone
        self.embed_dim = embed_dim
        self.patch_size = patch_size
        self.camera = camera
        self.components = normalise_components(components)
        self.pe_fingerprint = pe_fingerprint
        self.training_info: dict[str, Any] = dict(training or {})
        self.pe = nn.ParameterDict(
            {
                "radial": nn.Parameter(torch.zeros(n_r, embed_dim)),
                "angular": nn.Parameter(torch.zeros(n_theta, embed_dim)),
            }
        )
        self.rope = (
            nn.ParameterDict({"radial": nn.Parameter(torch.zeros(n_r_rope))}) if n_r_rope else None
        )

    # ------------------------------------------------------------------ sizes
    @property
    def n_r(self) -> int:
        return self.pe["radial"].shape[0]

    @property
    def n_theta(self) -> int:
        return self.pe["angular"].shape[0]

    @property
    def n_r_rope(self) -> int:
        return 0 if self.rope is None else self.rope["radial"].shape[0]

    def num_parameters(self) -> dict[str, int]:
        """Parameter counts: ``{"pe": ..., "rope": ..., "total": ...}``."""
        pe = self.pe["radial"].numel() + self.pe["angular"].numel()
        return {"pe": pe, "rope": self.n_r_rope, "total": pe + self.n_r_rope}

    @classmethod
    def for_model(
        cls,
        model: nn.Module,
        camera: Camera | None = None,
        *,
        n_r: int = DEFAULT_N_R,
        n_theta: int = DEFAULT_N_THETA,
        n_r_rope: int = DEFAULT_N_R_ROPE,
        components=None,
    ) -> Adapter:
        """A zero (identity) adapter sized for ``model``'s backbone."""
        from raytun3r_plugin.registry import spec_for

        spec, root = spec_for(model)
        info = spec.describe(root)
        return cls(
            backbone=info.name,
            embed_dim=info.embed_dim,
            patch_size=info.patch_size,
            n_r=n_r,
            n_theta=n_theta,
            n_r_rope=n_r_rope if info.has_rope else 0,
            camera=camera,
            components=components,
            pe_fingerprint=pe_fingerprint(info.pos_embed),
        )

    # ------------------------------------------------------------------ file format
    def metadata(self) -> dict[str, str]:
        from raytun3r_plugin._version import __version__

        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "backbone": self.backbone,
            "embed_dim": str(self.embed_dim),
            "patch_size": str(self.patch_size),
            "n_r": str(self.n_r),
            "n_theta": str(self.n_theta),
            "n_r_rope": str(self.n_r_rope),
            "camera": "" if self.camera is None else self.camera.to_json(),
            "components": json.dumps(self.components, sort_keys=True),
            "pe_fingerprint": self.pe_fingerprint,
            "raytun3r_version": __version__,
            "training": json.dumps(self.training_info, sort_keys=True, default=str),
        }

    def tensors(self) -> dict[str, torch.Tensor]:
        """The file's tensors: detached, contiguous float32 CPU copies."""
        return {
            name: value.detach().to("cpu", torch.float32).contiguous().clone()
            for name, value in self.state_dict().items()
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the adapter atomically (:func:`raytun3r_plugin.atomic_files.atomic_save_safetensors`)."""
        from raytun3r_plugin.atomic_files import atomic_save_safetensors

        return atomic_save_safetensors(path, self.tensors(), self.metadata())

    @classmethod
    def load(cls, path: str | os.PathLike) -> Adapter:
        """Read and validate an adapter file; raises :class:`AdapterError` naming the problem.

        Strict and bounded for any bytes (docs/conventions.md section 4, "What a reader
        accepts"): at most :data:`MAX_FILE_BYTES`, a header of unique keys, exactly the
        metadata keys of the format, integers in ``str(int)`` syntax within
        :data:`SIZE_LIMITS`, ``components`` as JSON booleans, finite tables within
        :data:`TABLE_LIMITS`, and a camera that passes its own construction checks.
        """
        from raytun3r_plugin._strict import read_safetensors

        path = Path(path)
        if not path.is_file():
            raise AdapterError(f"{path}: no such adapter file")
        metadata, tensors = read_safetensors(path, MAX_FILE_BYTES, AdapterError)
        return cls._from_parts(path, metadata, tensors)

    @classmethod
    def _from_parts(
        cls, path: Path, metadata: dict[str, str], tensors: dict[str, torch.Tensor]
    ) -> Adapter:
        where = str(path)
        sizes, fingerprint, components, training = _checked_metadata(where, metadata)
        _check_tables(where, tensors, sizes)
        camera = _stored_camera(where, metadata)
        try:
            adapter = cls(
                backbone=metadata["backbone"],
                camera=camera,
                components=components,
                pe_fingerprint=fingerprint,
                training=training,
                **sizes,
            )
        except AdapterError as error:
            raise AdapterError(f"{where}: {error}") from None
        with torch.no_grad():
            for name, value in adapter.state_dict().items():
                value.copy_(tensors[name])
        return adapter

    # ------------------------------------------------------------------ corrections
    def pe_correction(
        self,
        geometry: Any,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        angular: bool | None = None,
    ) -> torch.Tensor:
        """The PE update ``t_r(rho) + rho d_theta(theta)`` of every patch token, (h w, C).

        The one place the tables meet the geometry: the patched PE hook adds it to the
        backbone's table, and the adaptation's PE regularisers
        (:func:`~raytun3r_plugin.adaptation.losses.pe_correction_grid`) read it, so both see
        the same matmuls. Differentiable in the tables.

        Args:
            geometry: a :class:`raytun3r_plugin.size_geometry.SizeGeometry` (camera at the input
                size), whose interpolation matrices spread the tables over the token grid.
            device: of the result (default: the tables' device).
            dtype: of the result (default: float32).
            angular: include the angular term; False gives ``t_r(rho)`` alone (the
                ``"pe_radial_only"`` ablation: the angular table is then outside the graph and
                gets no gradient). None: as this adapter's own components say.

        Returns:
            (h * w, C) correction in PE units, tokens in row-major order of the patch grid.
        """
        device = self.pe["radial"].device if device is None else device
        if angular is None:
            angular = not self.components.get("pe_radial_only", False)
        radial_weights, angular_weights = geometry.pe_weights(self.n_r, self.n_theta, device, dtype)
        correction = radial_weights @ self.pe["radial"].to(device, dtype)
        if angular:
            correction = correction + angular_weights @ self.pe["angular"].to(device, dtype)
        return correction

    # ------------------------------------------------------------------ comparisons
    def same_as(self, other: Adapter) -> bool:
        """True when ``other`` holds the same tables, sizes, backbone and camera."""
        if self is other:
            return True
        if self.metadata() | {"training": ""} != other.metadata() | {"training": ""}:
            return False
        mine, theirs = self.state_dict(), other.state_dict()
        return all(torch.equal(mine[k].detach(), theirs[k].detach()) for k in mine)

    def is_zero(self) -> bool:
        return all(not bool(p.detach().abs().max() > 0) for p in self.parameters())

    def extra_repr(self) -> str:
        counts = self.num_parameters()
        return f"backbone={self.backbone!r}, embed_dim={self.embed_dim}, n_r={self.n_r}, n_theta={self.n_theta}, n_r_rope={self.n_r_rope}, parameters={counts['total']}"


def _checked_metadata(
    where: str, metadata: dict[str, str]
) -> tuple[dict[str, int], str, dict[str, bool], dict[str, Any]]:
    """An adapter file's metadata, checked: (sizes, PE fingerprint, components, training
    record); :class:`AdapterError` naming ``where`` and the first problem otherwise."""
    from raytun3r_plugin._strict import quote, strict_int, strict_json

    def fail(message: str) -> AdapterError:
        return AdapterError(f"{where}: {message}")

    missing = [key for key in _REQUIRED_METADATA if key not in metadata]
    if missing:
        raise fail(f"missing metadata {missing}")
    unknown = sorted(set(metadata) - set(_REQUIRED_METADATA))
    if unknown:
        raise fail(f"unknown metadata {[quote(key) for key in unknown[:8]]}")
    if metadata["format"] != FORMAT:
        raise fail(f"metadata 'format' is {quote(metadata['format'])}, expected {FORMAT!r}")
    if metadata["format_version"] != FORMAT_VERSION:
        raise fail(
            f"format_version {quote(metadata['format_version'])} is not supported (this raytun3r reads version {FORMAT_VERSION})"
        )
    sizes = {
        key: strict_int(metadata[key], f"metadata {key!r}", low, high, AdapterError, where)
        for key, (low, high) in SIZE_LIMITS.items()
    }
    for key, limit in (("backbone", 200), ("raytun3r_version", 64)):
        value = metadata[key]
        if not 0 < len(value) <= limit or not value.isprintable():
            raise fail(
                f"metadata {key!r} must be 1 to {limit} printable characters, got {quote(value)}"
            )
    fingerprint = metadata["pe_fingerprint"]
    if fingerprint and re.fullmatch(r"[0-9a-f]{16}", fingerprint) is None:
        raise fail(
            f"metadata 'pe_fingerprint' must be 16 hex digits or empty, got {quote(fingerprint)}"
        )
    components = strict_json(metadata["components"], "metadata 'components'", AdapterError, where)
    # The five corrections always; an ablation switch only in files written while it was on
    # (so files from before the switches existed read with their old meaning).
    if not isinstance(components, dict) or not set(COMPONENTS) <= set(components) <= set(
        KNOWN_COMPONENTS
    ):
        raise fail(
            f"metadata 'components' must be an object with exactly the keys {list(COMPONENTS)} "
            f"(and optionally {list(ABLATION_SWITCHES)}), got {quote(components)}"
        )
    not_bool = [name for name, value in components.items() if not isinstance(value, bool)]
    if not_bool:
        raise fail(
            f"metadata 'components': {not_bool[0]!r} must be true or false, got {quote(components[not_bool[0]])}"
        )
    training = strict_json(metadata["training"], "metadata 'training'", AdapterError, where)
    if not isinstance(training, dict):
        raise fail(f"metadata 'training' must be a JSON object, got {quote(training)}")
    return sizes, fingerprint, components, training


def _check_tables(where: str, tensors: dict[str, torch.Tensor], sizes: dict[str, int]) -> None:
    """The file's tensors are exactly the tables its sizes name: float32, those shapes, finite
    and within :data:`TABLE_LIMITS`."""
    from raytun3r_plugin._strict import quote

    expected: dict[str, tuple[int, ...]] = {
        "pe.radial": (sizes["n_r"], sizes["embed_dim"]),
        "pe.angular": (sizes["n_theta"], sizes["embed_dim"]),
    }
    if sizes["n_r_rope"]:
        expected["rope.radial"] = (sizes["n_r_rope"],)
    if set(tensors) != set(expected):
        raise AdapterError(
            f"{where}: tensors {[quote(name) for name in sorted(tensors)[:8]]} do not match the expected {sorted(expected)}"
        )
    for name, shape in expected.items():
        tensor = tensors[name]
        if tensor.dtype != torch.float32:
            raise AdapterError(
                f"{where}: tensor {name!r} has dtype {tensor.dtype}, expected torch.float32"
            )
        if tuple(tensor.shape) != shape:
            raise AdapterError(
                f"{where}: tensor {name!r} has shape {tuple(tensor.shape)}, expected {shape} from the metadata"
            )
        if not bool(torch.isfinite(tensor).all()):
            raise AdapterError(f"{where}: tensor {name!r} has non-finite values")
        table_limit = TABLE_LIMITS[name]
        largest = float(tensor.abs().max()) if tensor.numel() else 0.0
        if largest > table_limit:
            raise AdapterError(
                f"{where}: tensor {name!r} has a value of magnitude {largest:.3g}, over the limit {table_limit:g}"
            )


def _stored_camera(where: str, metadata: dict[str, str]) -> Camera | None:
    """The camera an adapter file records (None when it records none)."""
    if not metadata["camera"]:
        return None
    from raytun3r_plugin._strict import quote, strict_json
    from raytun3r_plugin.cameras import from_dict

    record = strict_json(metadata["camera"], "metadata 'camera'", AdapterError, where)
    if not isinstance(record, dict):
        raise AdapterError(f"{where}: metadata 'camera' must be a JSON object, got {quote(record)}")
    try:
        return from_dict(record)
    except CameraError as error:
        raise AdapterError(
            f"{where}: metadata 'camera' is not a valid camera ({quote(str(error))})"
        ) from None
