"""raytun3r's built-in networks ``raytun3r-da3-tiny`` (the default, v2; issue 7) and
``raytun3r-da3-tiny-v3`` (issue 13: the same architecture, trained so that its pose head
generalises; model card, "Versions").

A small ``DepthAnything3Net`` of the real ``depth_anything_3`` classes, trained from scratch on
procedural PINHOLE views only (``scripts/train_default_network.py``; model card
``docs/model_card_raytun3r_da3_tiny.md``). Its weights ship with the package in
``raytun3r_plugin/data/raytun3r-da3-tiny.safetensors``, the build arguments in the JSON sidecar
next to it, so ``load_backbone("raytun3r-da3-tiny")`` needs no path and no download.

``patches/da3_networks.py`` merges :data:`BUILDERS` into the DA3 spec's builders. This module
imports ``patches.da3_networks`` lazily (inside :func:`build`) because ``da3_networks`` imports
this module while it is being imported.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from raytun3r_plugin.errors import WeightsError

NAME = "raytun3r-da3-tiny"
#: The v3 weights: same build arguments, a pose head that beats "no rotation" on held-out pairs.
NAME_V3 = "raytun3r-da3-tiny-v3"
WEIGHTS_FILE = f"{NAME}.safetensors"
KWARGS_FILE = f"{NAME}.json"
METRICS_FILE = f"{NAME}.metrics.json"


def data_dir() -> Path:
    """The package's ``data/`` folder (where the shipped weights live)."""
    return Path(str(resources.files("raytun3r_plugin"))) / "data"


def _build_record(name: str) -> dict:
    path = data_dir() / f"{name}.json"
    if not path.is_file():
        raise WeightsError(
            f"{name}: the packaged build record {path} is missing; reinstall raytun3r or train the "
            "network with scripts/train_default_network.py --export <path>"
        )
    return read_build_record(path, f"{name}: {path}")


def read_build_record(path: Path, label: str) -> dict:
    """The JSON the training script writes beside exported weights (``build_kwargs``,
    ``training``, and for other architectures ``arch``), parsed and checked; ``label`` names it
    in the :class:`WeightsError` a malformed record raises."""
    try:
        record = json.loads(path.read_text())
        record["build_kwargs"].items()
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        raise WeightsError(f"{label} is not a valid build record ({error})") from error
    return record


def build_kwargs(name: str = NAME) -> dict:
    """The ``build_tiny_network`` arguments the shipped weights ``name`` were trained with."""
    kwargs = _build_record(name)["build_kwargs"]
    return {
        key: (tuple(value) if isinstance(value, list) else value) for key, value in kwargs.items()
    }


def build(path=None, name: str = NAME):
    """Build the built-in network ``name`` and load its packaged weights (or the file ``path``).

    Returns the network in eval mode, named ``name`` (``describe`` reports it).
    Raises :class:`WeightsError` when the packaged weight file is missing.
    """
    from raytun3r_plugin.patches.da3_networks import build_tiny_network, load_weights

    weights = Path(path) if path is not None else data_dir() / f"{name}.safetensors"
    if path is None and not weights.is_file():
        raise WeightsError(
            f"{name}: the packaged weight file {weights} is missing; reinstall raytun3r, pass a "
            "local path, or train it with scripts/train_default_network.py --export <path>"
        )
    kwargs = build_kwargs(name)
    # The size it was trained at is its own input size (registry.native_input_size).
    trained_at = (_build_record(name).get("training") or {}).get("args", {}).get("size")
    kwargs["seed"] = None  # the initialisation is overwritten by the weights; leave the RNG alone
    model = build_tiny_network(**kwargs)
    load_weights(model, weights)
    model.raytun3r_name = name
    model.raytun3r_input_size = int(trained_at) if trained_at else 112
    return model.eval()


def build_v3(path=None):
    """:func:`build` of ``raytun3r-da3-tiny-v3``."""
    return build(path, NAME_V3)


BUILDERS = {NAME: build, NAME_V3: build_v3}
