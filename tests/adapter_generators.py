"""Valid adapter files and mutations of them, from a ``random.Random``.

Shared by the property tests (tests/test_adapter_properties.py, which draw the ``Random`` from
hypothesis) and the robustness campaign (benchmarks/robustness_campaign.py, which seeds it).
Every mutation targets one way a file can be wrong: the bytes (truncation, flips, a header
length that lies), the header's structure (duplicate keys, offsets, shapes, dtypes) or one
metadata field (wrong JSON type, integer syntax, huge numbers, deep nesting, absurd camera
parameters, absurd table values).
"""

from __future__ import annotations

import json
import random
import struct

import torch

from raytun3r_plugin.adapter import _REQUIRED_METADATA

_NASTY_TEXT = [
    "",
    " 20 ",
    "2_0",
    "+20",
    "020",
    "-1",
    "0",
    "1e3",
    "20.0",
    "9" * 400,
    "9" * 5000,
    "true",
    "null",
    "NaN",
    "Infinity",
    "[]",
    "{}",
    "[[1]]",
    "7",
    '"a string"',
    "[" * 3000 + "]" * 3000,
    "{" * 10 + "}" * 10,
    '{"a": 1, "a": 2}',
    "\x00\x01",
    "\ud800".encode("utf-8", "surrogatepass").decode("utf-8", "replace"),
    "x" * 10_000,
]
_CAMERA_VALUES = [
    0.0,
    -1.0,
    1e-310,
    1e300,
    -1e300,
    1e308,
    10**400,
    "9" * 400,
    None,
    True,
    [],
    [1.0, 2.0],
    {"a": 1},
    float("nan"),
    -0.999,
    -1.0,
    1000.0,
    1e10,
    100000,
]


def _components(rng: random.Random, names: tuple[str, ...]) -> dict[str, bool]:
    """Random on/off corrections, sometimes with the ablation switch that fits them."""
    components = {name: rng.random() < 0.7 for name in names}
    if rng.random() < 0.3:
        # "pe_radial_only" modifies "pe"; "pe_naive_remap" replaces it (docs/components.md).
        components["pe_radial_only" if components["pe"] else "pe_naive_remap"] = True
    return components


def valid_adapter(rng: random.Random):
    """A random but valid adapter: sizes, tables, components, training record and camera."""
    import raytun3r_plugin as rt
    from raytun3r_plugin.adapter import COMPONENTS
    from raytun3r_plugin.cameras import fisheye

    embed_dim = rng.choice([8, 16, 64])
    n_rope = rng.choice([0, 4, 20])
    size = rng.choice([(84, 70), (112, 84), (64, 64)])
    camera = fisheye(size, rng.uniform(120.0, 200.0), rng.choice(["kb4", "ds"]))
    adapter = rt.Adapter(
        backbone=rng.choice(["da3-small", "vggt-1b", "pi3"]),
        embed_dim=embed_dim,
        patch_size=rng.choice([14, 16]),
        n_r=rng.randint(2, 24),
        n_theta=rng.randint(1, 10),
        n_r_rope=n_rope,
        camera=camera if rng.random() < 0.9 else None,
        components=_components(rng, COMPONENTS),
        training={"steps": rng.randint(0, 500), "final": {"reproj": rng.random()}},
    )
    generator = torch.Generator().manual_seed(rng.randrange(2**31))
    with torch.no_grad():
        for parameter in adapter.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * 0.05)
    return adapter


def _split(data: bytes) -> tuple[dict, bytes]:
    (size,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8 : 8 + size]), data[8 + size :]


def _join(header: dict | str, body: bytes) -> bytes:
    text = header if isinstance(header, str) else json.dumps(header)
    raw = text.encode("utf-8", "surrogatepass")
    return struct.pack("<Q", len(raw)) + raw + body


def adapter_bytes(adapter) -> bytes:
    from safetensors.torch import save

    return save(adapter.tensors(), metadata=adapter.metadata())


def _camera_mutation(rng: random.Random, camera_json: str) -> str:
    if not camera_json:
        return json.dumps({"model": "kb4", "width": 84})
    record = json.loads(camera_json)
    target = rng.choice(["params", "width", "height", "model", "max_fov_deg", "drop"])
    if target == "params" and isinstance(record.get("params"), dict):
        name = rng.choice(sorted(record["params"]))
        record["params"][name] = rng.choice(_CAMERA_VALUES)
    elif target == "drop":
        record.pop(rng.choice(sorted(record)), None)
    elif target == "model":
        record["model"] = rng.choice(["nope", 3, [], "pinhole", "ds"])
    else:
        record[target] = rng.choice(_CAMERA_VALUES)

    def default(value):
        return str(value)

    text = json.dumps(record, default=default, allow_nan=True)
    return text


def mutate(rng: random.Random, data: bytes) -> bytes:
    """One random mutation of a valid adapter file's bytes."""
    kind = rng.choice(
        ["truncate", "flip", "header_size", "metadata", "camera", "table", "duplicate", "entry"]
    )
    if kind == "truncate":
        return data[: rng.randrange(len(data))]
    if kind == "flip":
        flipped = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            flipped[rng.randrange(len(flipped))] ^= 1 << rng.randrange(8)
        return bytes(flipped)
    header, body = _split(data)
    if kind == "header_size":
        return struct.pack("<Q", rng.choice([0, 7, len(data), 2**63, 2**64 - 1])) + data[8:]
    metadata = header["__metadata__"]
    if kind == "metadata":
        field = rng.choice(_REQUIRED_METADATA)
        if rng.random() < 0.2:
            metadata.pop(field)
        else:
            metadata[field] = rng.choice(_NASTY_TEXT)
        return _join(header, body)
    if kind == "camera":
        metadata["camera"] = _camera_mutation(rng, metadata["camera"])
        return _join(header, body)
    if kind == "table":
        name = rng.choice(sorted(key for key in header if key != "__metadata__"))
        begin, end = header[name]["data_offsets"]
        values = torch.frombuffer(bytearray(body[begin:end]), dtype=torch.float32).clone()
        index = rng.randrange(values.numel())
        values[index] = rng.choice([1e30, -1e30, 99.0, 101.0, float("inf"), float("nan"), 1e-45])
        return _join(header, body[:begin] + values.numpy().tobytes() + body[end:])
    if kind == "duplicate":
        text = json.dumps(header)
        name = rng.choice(sorted(header))
        duplicate = json.dumps({name: header[name]})[1:-1]
        return _join(text[:-1] + ", " + duplicate + "}", body)
    # kind == "entry": one tensor entry's dtype, shape or offsets
    name = rng.choice(sorted(key for key in header if key != "__metadata__"))
    entry = header[name]
    field = rng.choice(["dtype", "shape", "data_offsets", "extra"])
    if field == "dtype":
        entry["dtype"] = rng.choice(["F64", "F16", "I8", "U8", "BOOL", "x"])
    elif field == "shape":
        entry["shape"] = rng.choice([[], [-1], [2**40], [1, 2, 3], "3", [1.5]])
    elif field == "data_offsets":
        entry["data_offsets"] = rng.choice([[0, 0], [0, 2**62], [-4, 4], [8, 4], [0]])
    else:
        entry["extra"] = 1
    return _join(header, body)
