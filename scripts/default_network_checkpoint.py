"""Checkpoints (safetensors + JSON, never pickle), the sin-cos PE start, validation and the
learning-rate schedule of the built-in networks' training (``scripts/train_default_network.py``)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import torch
from default_network_data import log  # noqa: E402  (beside this script)
from default_network_losses import forward_train  # noqa: E402  (beside this script)

VAL_GAP = 2  # pairs (k, k + VAL_GAP), as in the held-out evaluation


# ----------------------------------------------------------------------------------------------
# Checkpoints (safetensors + JSON, never pickle)
# ----------------------------------------------------------------------------------------------


def named_trainables(model, aux) -> dict:
    """Parameter name -> parameter of the network and (prefixed ``flowaux.``) the aux head."""
    params = dict(model.named_parameters())
    if aux is not None:
        params.update({f"flowaux.{n}": p for n, p in aux.named_parameters()})
    return params


def save_checkpoint(out: Path, model, opt, step: int, args: dict, aux=None) -> None:
    from safetensors.torch import save_model

    from raytun3r_plugin.atomic_files import atomic_path, atomic_save_safetensors, atomic_write_text

    with atomic_path(out / "checkpoint.safetensors") as tmp:
        save_model(model, str(tmp))
    if aux is not None:  # the training-only flow head, kept apart from the network's weights
        atomic_save_safetensors(
            out / "aux.safetensors",
            {k: v.detach().clone().contiguous() for k, v in aux.state_dict().items()},
        )
    names = {id(p): name for name, p in named_trainables(model, aux).items()}
    tensors = {}
    for group in opt.param_groups:
        for p in group["params"]:
            st = opt.state.get(p)
            if not st:
                continue
            for key, value in st.items():
                tensors[f"{names[id(p)]}::{key}"] = value.detach().clone().contiguous()
    atomic_save_safetensors(out / "optimizer.safetensors", tensors)
    hyper = [{k: v for k, v in g.items() if k != "params"} for g in opt.param_groups]
    atomic_write_text(
        out / "checkpoint.json",
        json.dumps({"step": step, "args": args, "param_groups": hyper}, indent=1, default=list),
    )


def load_checkpoint(out: Path, model, opt, aux=None) -> int:
    from default_network_vggt import is_vggt
    from safetensors.torch import load_file

    if is_vggt(model):
        from raytun3r_plugin.patches.vggt import load_weights
    else:
        from raytun3r_plugin.patches.da3_networks import load_weights

    meta = json.loads((out / "checkpoint.json").read_text())
    load_weights(model, out / "checkpoint.safetensors")
    if aux is not None:
        aux.load_state_dict(load_file(str(out / "aux.safetensors")))
    state = load_file(str(out / "optimizer.safetensors"))
    params = named_trainables(model, aux)
    for key, value in state.items():
        name, field = key.split("::")
        # AdamW keeps its step counter on the CPU; the moments live with their parameter
        p = params[name]
        opt.state[p][field] = value if field == "step" else value.to(p.device)
    for group, saved in zip(opt.param_groups, meta["param_groups"], strict=True):
        group.update({k: (tuple(v) if isinstance(v, list) else v) for k, v in saved.items()})
    return int(meta["step"])


def sincos_table(side: int, dim: int, std: float, max_cycles: float = 3.0) -> torch.Tensor:
    """(side * side, dim) 2D sin-cos PE with 0.5..``max_cycles`` cycles across the image, scaled to ``std``.

    A freshly built DA3 has an all-zero PE, and a small random one is ignored by a network trained
    from scratch (it learns position from RoPE and content instead): the PE adapter would then have
    nothing to correct. Starting from a map whose magnitude is comparable to the patch tokens, with
    frequencies the 8x8 token grid of a 112 px input resolves, makes the network rely on absolute
    position the way pretrained DINOv2 backbones do.
    """
    n_freq = dim // 4
    cycles = torch.logspace(math.log10(0.5), math.log10(max_cycles), n_freq, dtype=torch.float64)
    coords = (torch.arange(side, dtype=torch.float64) + 0.5) / side
    yy, xx = torch.meshgrid(coords, coords, indexing="ij")
    parts = []
    for axis in (xx.reshape(-1), yy.reshape(-1)):
        phase = 2 * math.pi * axis[:, None] * cycles[None, :]
        parts += [torch.sin(phase), torch.cos(phase)]
    table = torch.cat(parts, dim=1)
    table = torch.nn.functional.pad(table, (0, dim - table.shape[1]))
    return (table / table.std() * std).float()


@torch.no_grad()
def validate(model, val: dict, pose_only: bool, device: str, chunk: int = 16) -> dict:
    """Validation metrics on pairs (k, k + VAL_GAP) of every validation sequence.

    Same measures as ``scripts/eval_default_network.py`` on its pinhole views: mean geodesic
    rotation error over the error of predicting no rotation (``val_rot_ratio``), mean signed
    translation-direction error (degrees) and, unless ``pose_only``, median-aligned depth AbsRel.
    """
    from default_network_vggt import cam_from_world

    from raytun3r_plugin.metrics import abs_rel, relative_pose_errors

    n_seq, n_frames = val["images"].shape[:2]
    pairs = [(s, k) for s in range(n_seq) for k in range(n_frames - VAL_GAP)]
    was_training = model.training
    model.eval()
    rot, rot0, trans, ar = [], [], [], []
    for i in range(0, len(pairs), chunk):
        part = pairs[i : i + chunk]
        imgs = np.stack([val["images"][s, [k, k + VAL_GAP]] for s, k in part])
        x = torch.from_numpy(imgs.astype(np.float32) / 255.0).permute(0, 1, 4, 2, 3).to(device)
        out, pose_enc, _ = forward_train(model, x, pose_only=pose_only)
        T_all = cam_from_world(model, pose_enc, x.shape[-2:]).cpu().numpy()
        for j, (s, k) in enumerate(part):
            T_pred = T_all[j]
            T_gt = val["poses"][s, [k, k + VAL_GAP]]
            e = relative_pose_errors(T_pred, T_gt, pairs=[(0, 1)])
            e0 = relative_pose_errors(np.stack([np.eye(4), np.eye(4)]), T_gt, pairs=[(0, 1)])
            rot += list(e["rotation_deg"])
            trans += list(e["translation_deg"])
            rot0 += list(e0["rotation_deg"])
            if out is not None:
                gt = val["depth"][s, [k, k + VAL_GAP]].astype(np.float64)
                dp = out["depth"][j].double().cpu().numpy()
                ar += list(abs_rel(dp, gt, gt > 0))
    model.train(was_training)
    return {
        "val_rot_ratio": float(np.mean(rot) / np.mean(rot0)),
        "val_trans_deg": float(np.mean(trans)),
        "val_abs_rel": float(np.nanmean(ar)) if ar else float("nan"),
    }


def lr_at(step: int, total: int, base: float, warmup: int) -> float:
    if step < warmup:
        return base * (step + 1) / warmup
    p = (step - warmup) / max(1, total - warmup)
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, p))))


#: ``metadata["format"]`` of an exported file, per ``--arch``.
FORMATS = {"da3": "raytun3r-da3-tiny", "vggt": "raytun3r-vggt-small"}


def export(model, kwargs: dict, path: Path, training: dict, arch: str = "da3") -> None:
    """Write the shipped weights and the build-kwargs JSON next to them.

    ``arch`` "vggt" writes the small VGGT's file (format ``raytun3r-vggt-small``), with
    ``"arch": "vggt"`` in the JSON, for ``apps.trained_networks.load_trained_network``.

    The weights are stored as float16 (half the size; the loader casts them back to the float32
    parameters), which keeps the packaged file under 5 MB.
    """
    from safetensors.torch import save_file

    from raytun3r_plugin.atomic_files import atomic_path
    from raytun3r_plugin.weights import alias_keys

    aliases = alias_keys(model)  # tensors shared with an earlier key are stored once
    state = {
        name: tensor.detach().to(torch.float16).contiguous()
        for name, tensor in model.eval().state_dict().items()
        if name not in aliases
    }
    with atomic_path(path) as tmp:
        save_file(
            state,
            str(tmp),
            metadata={"format": FORMATS[arch], "build_kwargs": json.dumps(kwargs)},
        )
        os.chmod(tmp, 0o644)  # a package data file: world-readable
    side = path.with_suffix(".json")
    record = {"build_kwargs": kwargs, "training": training}
    if arch != "da3":  # the built-ins' records stay as they were
        record = {"arch": arch, **record}
    side.write_text(json.dumps(record, indent=1) + "\n")
    log(f"exported {path} ({path.stat().st_size / 1e6:.2f} MB) and {side}")
