"""Networks trained by ``scripts/train_default_network.py`` that do not ship with raytun3r.

The built-in networks (``patches/da3_default.py``) are DA3-architecture files in the package.
The training script can also train a small VGGT-architecture network (``--arch vggt``, issue 37)
so that the VGGT rows of a benchmark measure adaptation on a network of that family; its
weights stay wherever the run wrote them and are loaded from that file with
:func:`load_trained_network` (``benchmarks/fisheye_synthetic.py --weights FILE``).

Upstream ``VGGT.__init__`` fixes every size but the embedding width (24 aggregator blocks,
a ViT-L patch embedding, ...), so a small VGGT is built from the ``vggt`` package's stub
(``tests/stubs/vggt``), whose ``_stub_config.stub_sizes`` sets those hard-wired numbers; the
classes, forward pass and output conventions are upstream's. The weight file's JSON sidecar
(``<file>.json``: ``arch``, ``build_kwargs``) says how to build it.
"""

from __future__ import annotations

from pathlib import Path

from torch import nn

from raytun3r_plugin.errors import MissingDependencyError, WeightsError

#: ``arch`` values of a training run's sidecar, besides DA3 (the built-in networks' family).
ARCHITECTURES = ("da3", "vggt")
#: ``metadata["format"]`` of an exported small VGGT file.
VGGT_FORMAT = "raytun3r-vggt-small"
_STUB_HINT = (
    "a small VGGT is built with the stub package's sizes: run with PYTHONPATH=tests/stubs "
    "(from the raytun3r source tree)"
)


def build_small_vggt(build_kwargs: dict) -> nn.Module:
    """A ``VGGT`` of the stub package's classes with the sizes of ``build_kwargs``.

    ``build_kwargs``: ``img_size``, ``patch_size``, ``embed_dim`` (``VGGT``'s own arguments),
    ``sizes`` (fields of the stub's ``StubSizes``: depths, heads, DPT widths, ``seed``). The
    point and track heads are left out (``enable_point=False``, ``enable_track=False``): the
    training targets are depth and pose, and the adaptation reads only those. Returns it in
    eval mode. Raises :class:`MissingDependencyError` when ``vggt`` or its stub sizing is absent.
    """
    try:
        from vggt.models.vggt import VGGT
    except ImportError as error:
        raise MissingDependencyError(f"vggt is not importable ({error}); {_STUB_HINT}") from error
    try:
        from vggt import _stub_config
    except ImportError as error:
        raise MissingDependencyError(
            f"the installed vggt has no _stub_config (upstream builds only VGGT-1B); {_STUB_HINT}"
        ) from error
    sizes = {
        key: (tuple(value) if isinstance(value, list) else value)
        for key, value in build_kwargs.get("sizes", {}).items()
    }
    with _stub_config.stub_sizes(**sizes):
        model = VGGT(
            img_size=build_kwargs["img_size"],
            patch_size=build_kwargs["patch_size"],
            embed_dim=build_kwargs["embed_dim"],
            enable_camera=True,
            enable_point=False,
            enable_depth=True,
            enable_track=False,
        )
    return model.eval()


def read_sidecar(path: str | Path) -> dict:
    """The JSON written beside an exported weight file (``arch``, ``build_kwargs``, ``training``)."""
    weights = Path(path)
    side = weights.with_suffix(".json")
    if not weights.is_file():
        raise WeightsError(f"{weights}: no such weight file")
    if not side.is_file():
        raise WeightsError(
            f"{weights}: the build record {side} is missing (scripts/train_default_network.py "
            "--export writes it beside the weights)"
        )
    from raytun3r_plugin.patches.da3_default import read_build_record

    record = read_build_record(side, str(side))
    arch = record.get("arch", "da3")  # DA3 records predate the field
    if arch not in ARCHITECTURES:
        raise WeightsError(f"{side}: unknown arch {arch!r}; known: {ARCHITECTURES}")
    record["arch"] = arch
    return record


def load_trained_network(path: str | Path) -> tuple[nn.Module, str]:
    """(model in eval mode, one-line description) of a network exported by the training script.

    ``path``: the ``.safetensors`` file of ``--export``; its sidecar names the architecture.
    Raises :class:`WeightsError` for a missing or malformed file or record.
    """
    record = read_sidecar(path)
    kwargs = record["build_kwargs"]
    steps = (record.get("training") or {}).get("steps", "?")
    if record["arch"] == "vggt":
        from raytun3r_plugin.patches.vggt import load_weights

        unseeded = {**kwargs, "sizes": {**kwargs["sizes"], "seed": None}}  # weights overwrite it
        model = load_weights(build_small_vggt(unseeded), path)
        what = "a small VGGT-architecture network (stub package classes)"
    else:
        from raytun3r_plugin.patches.da3_networks import build_tiny_network, load_weights

        built = {k: (tuple(v) if isinstance(v, list) else v) for k, v in kwargs.items()}
        model = load_weights(build_tiny_network(**{**built, "seed": None}), path)
        what = "a small Depth Anything 3 network"
    model.raytun3r_name = Path(path).stem
    # The size it was trained at is its own input size (registry.native_input_size).
    trained_at = ((record.get("training") or {}).get("args") or {}).get("size")
    if trained_at:
        model.raytun3r_input_size = int(trained_at)
    description = (
        f"{Path(path).name}: {what} trained by raytun3r on pinhole renders only "
        f"({steps} steps; scripts/train_default_network.py)"
    )
    return model.eval(), description


def network_from(name: str, weights: str | Path | None = None) -> tuple[nn.Module, str]:
    """(model, one-line description) of the network a script's ``--network`` and
    ``--weights`` name: with ``weights``, the file exported by the training script
    (:func:`load_trained_network`, ``name`` unused); otherwise the built-in network ``name``
    (:func:`raytun3r_plugin.apps.demo.default_network`)."""
    if weights:
        return load_trained_network(weights)
    from raytun3r_plugin.apps.demo import default_network

    return default_network(name)
