"""raytun3r's built-in default network ``raytun3r-da3-tiny`` (issue 7).

A small ``DepthAnything3Net`` of the real ``depth_anything_3`` classes, trained from scratch on
procedural PINHOLE views only (``scripts/train_default_network.py``; model card
``docs/model_card_raytun3r_da3_tiny.md``). Its weights ship with the package in
``raytun3r_plugin/data/raytun3r-da3-tiny.safetensors``, the build arguments in the JSON sidecar
next to it, so ``load_backbone("raytun3r-da3-tiny")`` needs no path and no download.

``patches/da3.py`` merges :data:`BUILDERS` into the DA3 spec's builders. This module imports
``patches.da3`` lazily (inside :func:`build`) because ``da3`` imports this module while it is
being imported.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from raytun3r_plugin.errors import WeightsError

NAME = "raytun3r-da3-tiny"
WEIGHTS_FILE = f"{NAME}.safetensors"
KWARGS_FILE = f"{NAME}.json"
METRICS_FILE = f"{NAME}.metrics.json"


def data_dir() -> Path:
    """The package's ``data/`` folder (where the shipped weights live)."""
    return Path(str(resources.files("raytun3r_plugin"))) / "data"


def build_kwargs() -> dict:
    """The ``build_tiny_network`` arguments the shipped weights were trained with."""
    path = data_dir() / KWARGS_FILE
    if not path.is_file():
        raise WeightsError(
            f"{NAME}: the packaged build record {path} is missing; reinstall raytun3r or train the "
            "network with scripts/train_default_network.py --export <path>"
        )
    try:
        kwargs = json.loads(path.read_text())["build_kwargs"]
    except (ValueError, KeyError, TypeError) as error:
        raise WeightsError(f"{NAME}: {path} is not a valid build record ({error})") from error
    return {
        key: (tuple(value) if isinstance(value, list) else value) for key, value in kwargs.items()
    }


def build(path=None):
    """Build ``raytun3r-da3-tiny`` and load the packaged weights (or the file ``path``).

    Returns the network in eval mode, named ``raytun3r-da3-tiny`` (``describe`` reports it).
    Raises :class:`WeightsError` when the packaged weight file is missing.
    """
    from raytun3r_plugin.patches.da3 import build_tiny_network, load_weights

    weights = Path(path) if path is not None else data_dir() / WEIGHTS_FILE
    if path is None and not weights.is_file():
        raise WeightsError(
            f"{NAME}: the packaged weight file {weights} is missing; reinstall raytun3r, pass a "
            "local path, or train it with scripts/train_default_network.py --export <path>"
        )
    kwargs = build_kwargs()
    kwargs["seed"] = None  # the initialisation is overwritten by the weights; leave the RNG alone
    model = build_tiny_network(**kwargs)
    load_weights(model, weights)
    model.raytun3r_name = NAME
    return model.eval()


BUILDERS = {NAME: build}
