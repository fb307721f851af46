"""Targets and losses of the built-in networks' training (``scripts/train_default_network.py``):
depth, rays, pose encodings, the training-only flow and attention-matching terms."""

from __future__ import annotations

import math

import torch

# ----------------------------------------------------------------------------------------------
# Targets and losses
# ----------------------------------------------------------------------------------------------


def relative_c2w(cam_from_world: torch.Tensor) -> torch.Tensor:
    """``world_from_cam`` of every view with the world = the first view: ``T_0 inv(T_k)``."""
    inv = torch.linalg.inv(cam_from_world)
    return cam_from_world[:, :1] @ inv


def targets(batch: dict, arch: str = "da3") -> dict:
    """Normalised depth, c2w poses (first view = identity) and ray maps for a batch.

    ``pose`` is what the network's pose encoding describes: ``c2w`` for DA3, its inverse
    (camera-from-world, world = the first view) for VGGT; ``arch`` says which.
    """
    depth = batch["depth"].float()
    B, S, H, W = depth.shape
    valid = depth > 0
    scale = torch.stack(
        [
            depth[b, 0][valid[b, 0]].median() if valid[b, 0].any() else depth.new_tensor(1.0)
            for b in range(B)
        ]
    ).clamp(min=1e-3)
    c2w = relative_c2w(batch["cam_from_world"])  # float64
    c2w[..., :3, 3] /= scale.double()[:, None, None]
    fov = torch.deg2rad(batch["fov"])
    focal = (W / 2.0) / torch.tan(fov / 2.0)
    pose = c2w if arch == "da3" else torch.linalg.inv(c2w)
    return {
        "depth": depth / scale[:, None, None, None],
        "valid": valid,
        "c2w": c2w.float(),
        "pose": pose.float(),
        "arch": arch,
        "fov": fov.float(),
        "focal": focal.float(),
        "scale": scale,
    }


def ray_targets(tg: dict, h_r: int, w_r: int, H: int, W: int) -> torch.Tensor:
    """(B, S, h_r, w_r, 6): world (= first view) direction ``R K^-1 (u, v, 1)`` and centre."""
    c2w, f = tg["c2w"], tg["focal"]
    dev = c2w.device
    u = (torch.arange(w_r, dtype=torch.float32, device=dev) + 0.5) * (W / w_r) - 0.5
    v = (torch.arange(h_r, dtype=torch.float32, device=dev) + 0.5) * (H / h_r) - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    fb = f[:, None, None]
    x, y = (uu - cx) / fb, (vv - cy) / fb  # B,h,w
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)  # B,h,w,3
    R = c2w[..., :3, :3]  # B,S,3,3
    d = torch.einsum("bsij,bhwj->bshwi", R, d_cam)
    o = c2w[..., :3, 3][:, :, None, None, :].expand_as(d)
    return torch.cat([d, o], -1)


def partner_views(S: int) -> list[int]:
    """The view each view's tokens are matched into: 0 <-> 1, every later view -> 0."""
    return [1] + [0] * (S - 1)


def flow_targets(batch: dict, patch: int = 14) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the centre of every patch token lands in its partner view (:func:`partner_views`).

    From the GT z-depth at the patch centre (mean of the central 2 x 2 pixels, all valid), the
    GT relative pose and the centred pinhole of the batch (``fov``). Occlusion is not tested.

    Returns:
        flow (B, S, h * w, 2) float32: displacement (u_b - u_a, v_b - v_a) in units of half the
        image width; valid (B, S, h * w) bool: depth known, in front of and inside the partner.
    """
    depth = batch["depth"].double()
    B, S, H, W = depth.shape
    h, w = H // patch, W // patch
    mid = patch // 2
    z4 = depth[:, :, : h * patch, : w * patch].reshape(B, S, h, patch, w, patch)
    z4 = z4[:, :, :, mid - 1 : mid + 1, :, mid - 1 : mid + 1]
    ok = (z4 > 0).all(dim=3).all(dim=-1)  # B,S,h,w
    z = z4.mean(dim=(3, 5))
    f = ((W / 2.0) / torch.tan(torch.deg2rad(batch["fov"].double()) / 2.0))[:, None, None, None]
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    u = (torch.arange(w, dtype=torch.float64) * patch + (patch - 1) / 2.0)[None, None, None, :]
    v = (torch.arange(h, dtype=torch.float64) * patch + (patch - 1) / 2.0)[None, None, :, None]
    X = torch.stack([(u - cx) / f * z, (v - cy) / f * z, z], -1)  # B,S,h,w,3 in view a
    P = batch["cam_from_world"].double()
    P_b = P[:, partner_views(S)]
    T = P_b @ torch.linalg.inv(P)  # B,S,4,4: view a -> partner view b
    Xb = torch.einsum("bsij,bshwj->bshwi", T[..., :3, :3], X) + T[..., None, None, :3, 3]
    zb = Xb[..., 2]
    ub = f * Xb[..., 0] / zb.clamp(min=1e-6) + cx
    vb = f * Xb[..., 1] / zb.clamp(min=1e-6) + cy
    ok = ok & (zb > 1e-3) & (ub > -0.5) & (ub < W - 0.5) & (vb > -0.5) & (vb < H - 0.5)
    flow = torch.stack([ub - u, vb - v], -1) / (W / 2.0)
    flow = torch.where(ok[..., None], flow, torch.zeros_like(flow))
    return flow.reshape(B, S, h * w, 2).float(), ok.reshape(B, S, h * w)


def global_layer_positions(model) -> list[int]:
    """Indices into the backbone's output list whose block attends across views (global)."""
    vit = model.backbone.pretrained
    layers = list(model.backbone.out_layers)
    return [k for k, i in enumerate(layers) if vit.alt_start != -1 and i >= vit.alt_start and i % 2]


def token_grid(H: int, W: int, patch: int = 14) -> torch.Tensor:
    """(h * w, 2) patch-centre positions (u, v) relative to the image centre, in half-widths."""
    h, w = H // patch, W // patch
    u = (torch.arange(w, dtype=torch.float32) * patch + (patch - 1) / 2.0 - (W - 1) / 2.0) / (W / 2)
    v = (torch.arange(h, dtype=torch.float32) * patch + (patch - 1) / 2.0 - (H - 1) / 2.0) / (W / 2)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)


FLOW_KINDS = ("regress", "corr", "both")


class FlowAux(torch.nn.Module):
    """Training-only token-flow heads on the global-attention output layers.

    Each reads the post-global-attention half of the ``cat_token`` features (B, S, N, C) and
    predicts, per token, the displacement of its centre into the partner view (2 numbers, units
    of half the image width). Never exported: it only shapes the backbone's cross-view tokens.

    * ``regress``: an MLP per layer regresses the displacement from the token alone, so the
      global attention itself must find the match and carry its position;
    * ``corr``: a projection per layer gives unit descriptors of the tokens that ENTER the
      global block (the ``local`` half of ``cat_token`` features: the last frame-attention
      output, from which that block's queries and keys are made); the softmax of their scaled
      dot products with the partner view's tokens (a cost volume, (B, S, N, N) logits) gives a
      soft-argmax position on the known token grid. This makes the global block's inputs
      matchable, so its attention can find the match the ``regress`` head asks for;
    * ``both``: both heads on every layer.
    """

    def __init__(self, embed_dim: int, n_layers: int, kind: str = "regress", dim: int = 64):
        super().__init__()
        if kind not in FLOW_KINDS:
            raise ValueError(f"flow head kind {kind!r} not in {FLOW_KINDS}")
        self.embed_dim, self.kind = embed_dim, kind
        if kind in ("regress", "both"):
            self.mlps = torch.nn.ModuleList(
                torch.nn.Sequential(
                    torch.nn.LayerNorm(embed_dim),
                    torch.nn.Linear(embed_dim, 2 * embed_dim),
                    torch.nn.GELU(),
                    torch.nn.Linear(2 * embed_dim, 2),
                )
                for _ in range(n_layers)
            )
        if kind in ("corr", "both"):
            self.projs = torch.nn.ModuleList(
                torch.nn.Sequential(torch.nn.LayerNorm(embed_dim), torch.nn.Linear(embed_dim, dim))
                for _ in range(n_layers)
            )
            # log of the inverse softmax temperature of the cosine similarities
            self.log_scale = torch.nn.Parameter(torch.full((n_layers,), math.log(10.0)))

    def forward(self, tokens: list[torch.Tensor], grid: torch.Tensor) -> list[dict]:
        """Per head: ``flow`` (B, S, N, 2) and, for ``corr``, ``logits`` (B, S, N, N)."""
        outs = []
        for k, t in enumerate(tokens):
            x = t[..., -self.embed_dim :]  # after the global block
            x_in = t[..., : self.embed_dim]  # its input (= x without cat_token)
            if self.kind in ("regress", "both"):
                outs.append({"flow": self.mlps[k](x), "logits": None})
            if self.kind in ("corr", "both"):
                f = torch.nn.functional.normalize(self.projs[k](x_in), dim=-1)
                fb = f[:, partner_views(f.shape[1])]
                scale = self.log_scale[k].clamp(max=math.log(100.0)).exp()
                logits = torch.einsum("bsnd,bsmd->bsnm", f, fb) * scale
                flow = logits.softmax(-1) @ grid - grid
                outs.append({"flow": flow, "logits": logits})
        return outs


def flow_loss(
    preds: list[dict], flow: torch.Tensor, valid: torch.Tensor, grid: torch.Tensor, w: int
) -> torch.Tensor:
    """Mean over heads of the smooth-L1 flow error (beta 0.05 half-widths) on valid tokens,
    plus, for cost-volume heads, 0.1 x the cross-entropy of the partner token nearest to the
    true position (a sharp gradient even while the soft-argmax is still flat)."""
    n = valid.sum().clamp(min=1)
    index = nearest_partner_token(flow, grid, w)
    terms = []
    for p in preds:
        e = torch.nn.functional.smooth_l1_loss(p["flow"], flow, reduction="none", beta=0.05).sum(-1)
        term = torch.where(valid, e, torch.zeros_like(e)).sum() / n
        if p["logits"] is not None:
            ce = torch.nn.functional.cross_entropy(
                p["logits"].flatten(0, 2), index.flatten(), reduction="none"
            ).view_as(e)
            term = term + 0.1 * torch.where(valid, ce, torch.zeros_like(ce)).sum() / n
        terms.append(term)
    return torch.stack(terms).mean()


def nearest_partner_token(flow: torch.Tensor, grid: torch.Tensor, w: int) -> torch.Tensor:
    """(B, S, N) index of the partner token nearest to where each token's centre lands."""
    target = grid[None, None] + flow
    spacing = float(grid[1, 0] - grid[0, 0]) if grid.shape[0] > 1 else 1.0
    col = ((target[..., 0] - grid[0, 0]) / spacing).round().clamp(0, w - 1)
    row = ((target[..., 1] - grid[0, 1]) / spacing).round().clamp(0, grid.shape[0] // w - 1)
    return (row * w + col).long()


def attention_match_loss(
    model, feats: list, flow: torch.Tensor, valid: torch.Tensor, grid: torch.Tensor, heads: int
) -> torch.Tensor:
    """Cross-entropy of the network's OWN global-attention logits towards the true match.

    For every global block among the output layers, its queries and keys are recomputed from
    the block's input (the ``local`` half of the ``cat_token`` features: the raw output of the
    frame block before it) with the block's own ``norm1``, ``qkv`` and q/k norms. The global
    blocks' RoPE positions are all equal, which leaves dot products unchanged, so these are the
    logits the block uses (camera and register tokens left out). For the first ``heads`` heads,
    each patch token of a view is pushed to attend, among the patch tokens of its own view and
    of its partner view, to the partner token nearest to where its centre lands. No parameter is
    added: this trains the shipped attention to match across views.
    """
    vit = model.backbone.pretrained
    layers = list(model.backbone.out_layers)
    B, S, N = valid.shape
    w = int(round(math.sqrt(N)))
    index = nearest_partner_token(flow, grid, w) + N  # keys: [own view, partner view]
    n = valid.sum().clamp(min=1)
    terms = []
    for k in global_layer_positions(model):
        blk = vit.blocks[layers[k]]
        x = blk.norm1(feats[k][0][..., : vit.embed_dim])  # B,S,N,C: the global block's input
        C, nh = x.shape[-1], blk.attn.num_heads
        q, key, _ = blk.attn.qkv(x).reshape(B, S, N, 3, nh, C // nh).unbind(3)
        q, key = blk.attn.q_norm(q[..., :heads, :]), blk.attn.k_norm(key[..., :heads, :])
        keys = torch.cat([key, key[:, partner_views(S)]], dim=2)  # B,S,2N,h,d
        logits = torch.einsum("bsnhd,bsmhd->bshnm", q, keys) * blk.attn.scale
        ce = torch.nn.functional.cross_entropy(
            logits.flatten(0, 3),
            index[:, :, None].expand(B, S, heads, N).flatten(),
            reduction="none",
        ).view(B, S, heads, N)
        terms.append(torch.where(valid[:, :, None], ce, torch.zeros_like(ce)).sum() / (n * heads))
    return torch.stack(terms).mean()


def forward_train(
    model, images: torch.Tensor, pose_only: bool = False
) -> tuple[dict | None, torch.Tensor, list]:
    """The network's own forward, split to keep DualDPT's ray map and the raw pose encoding.

    Returns the head's outputs (None with ``pose_only``: the DPT head is skipped), the raw pose
    encoding (B, S, 9) and the backbone's per-layer (tokens (B, S, N, 2C), camera token).
    """
    from default_network_vggt import forward_train_vggt, is_vggt

    from raytun3r_plugin.prediction import imagenet_normalise

    if is_vggt(model):
        return forward_train_vggt(model, images, pose_only)
    H, W = images.shape[-2:]
    feats, _ = model.backbone(imagenet_normalise(images), cam_token=None, export_feat_layers=[])
    out = None if pose_only else model.head(feats, H, W, patch_start_idx=0)
    pose_enc = model.cam_dec(feats[-1][1])
    return out, pose_enc, feats


def losses(out: dict | None, pose_enc: torch.Tensor, tg: dict, weights: dict) -> dict:
    """Loss terms and logged batch metrics; ``out`` None (``--pose-only``) drops depth and rays."""

    if out is None:
        ls = pose_losses(pose_enc, tg, weights, zero=pose_enc.new_zeros(()))
        del ls["_pose_term"], ls["_quat_term"]  # already in ls["loss"]
        return ls
    pred, gt, valid = out["depth"], tg["depth"], tg["valid"]
    H, W = pred.shape[-2:]
    n = valid.sum(dim=(-1, -2)).clamp(min=1)
    diff = torch.where(
        valid,
        torch.log(pred.clamp(min=1e-6)) - torch.log(gt.clamp(min=1e-6)),
        torch.zeros_like(pred),
    )
    mean = diff.sum(dim=(-1, -2)) / n
    l_si = (
        torch.where(valid, (diff - mean[..., None, None]).abs(), torch.zeros_like(diff)).sum(
            dim=(-1, -2)
        )
        / n
    ).mean()
    l_abs = (diff.abs().sum(dim=(-1, -2)) / n).mean()
    conf = out["depth_conf"]
    err = diff.abs().detach()
    l_conf = (
        torch.where(valid, conf * err - 0.05 * torch.log(conf), torch.zeros_like(conf)).sum(
            dim=(-1, -2)
        )
        / n
    ).mean()

    if "ray" in out:  # DA3's DualDPT; VGGT has no ray head
        ray = out["ray"]  # B,S,h,w,6
        ray_gt = ray_targets(tg, ray.shape[2], ray.shape[3], H, W)
        l_ray = (ray - ray_gt).abs().mean()
    else:
        l_ray = pred.new_zeros(())
    ls = pose_losses(pose_enc, tg, weights, zero=pred.new_zeros(()))
    # summed in the order of earlier versions, so default runs stay bit-identical to them
    ls["loss"] = (
        weights["depth"] * (l_si + 0.25 * l_abs)
        + weights["conf"] * l_conf
        + weights["ray"] * l_ray
        + ls.pop("_pose_term")
        + ls.pop("_quat_term")
    )
    if weights.get("tdir", 0.0) > 0:
        ls["loss"] = ls["loss"] + weights["tdir"] * ls["tdir"]
    ls.update(depth_si=l_si, depth_abs=l_abs, conf=l_conf, ray=l_ray)
    return ls


def pose_losses(pose_enc: torch.Tensor, tg: dict, weights: dict, zero: torch.Tensor) -> dict:
    """Pose + quaternion terms of the camera decoder; depth/ray entries are ``zero``.

    The pose is compared in the network's own convention (``tg["pose"]``: DA3 world_from_cam,
    VGGT cam_from_world); both decode the same absT_quaR_FoV encoding, each with its own code.
    """
    if tg.get("arch", "da3") == "vggt":
        from vggt.utils.pose_enc import pose_encoding_to_extri_intri
    else:
        from depth_anything_3.model.utils.transform import pose_encoding_to_extri_intri

    H, W = tg["depth"].shape[-2:]
    pose_pred, _ = pose_encoding_to_extri_intri(pose_enc, (H, W))  # B,S,3,4
    R_p, t_p = pose_pred[..., :3, :3], pose_pred[..., :3, 3]
    R_g, t_g = tg["pose"][..., :3, :3], tg["pose"][..., :3, 3]
    l_rot = (R_p - R_g).pow(2).sum(dim=(-1, -2)).add(1e-8).sqrt().mean()
    l_trans = (t_p - t_g).abs().sum(-1).mean()
    l_fov = (pose_enc[..., 7:9] - tg["fov"][:, None, None]).abs().mean()
    # The decoder normalises the raw quaternion, so a loss on the rotation matrix alone lets its
    # norm grow, which shrinks the gradient of the imaginary part and locks the head at the
    # identity (all earlier runs: raw w about 9.5, rotation error = no-rotation error). A loss on
    # the raw encoding, as VGGT's camera loss does, pins the norm to 1 and keeps that gradient.
    l_quat = (pose_enc[..., 3:7] - quaternion_target(R_g)).abs().sum(-1).mean()
    pose_term = weights["pose"] * (l_rot + l_trans + 0.5 * l_fov)
    quat_term = weights["quat"] * l_quat
    total = pose_term + quat_term
    # Translation direction (1 - cosine) of the later views: the normalised translations are
    # small (about 0.1), so the L1 term is nearly met by predicting none, in any direction.
    moving = t_g[:, 1:].norm(dim=-1) > 1e-4
    cos_t = torch.nn.functional.cosine_similarity(t_p[:, 1:], t_g[:, 1:], dim=-1, eps=1e-6)
    l_tdir = torch.where(moving, 1.0 - cos_t, torch.zeros_like(cos_t)).sum() / moving.sum().clamp(
        min=1
    )
    if weights.get("tdir", 0.0) > 0:
        total = total + weights["tdir"] * l_tdir
    with torch.no_grad():
        from raytun3r_plugin.metrics import rotation_error_deg

        rot_deg = rotation_error_deg(R_p[:, 1:].double(), R_g[:, 1:].double()).mean()
        rot_gt_deg = rotation_error_deg(
            torch.eye(3, dtype=torch.float64, device=R_g.device).expand_as(R_g[:, 1:]),
            R_g[:, 1:].double(),
        ).mean()
        # translation direction of the second view (signed, 0..180 degrees)
        cos = torch.nn.functional.cosine_similarity(t_p[:, 1:].double(), t_g[:, 1:].double(), -1)
        trans_deg = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0))).mean()
    return {
        "loss": total,
        "_pose_term": pose_term,
        "_quat_term": quat_term,
        "depth_si": zero,
        "depth_abs": zero,
        "conf": zero,
        "ray": zero,
        "rot": l_rot,
        "trans": l_trans,
        "fov": l_fov,
        "quat": l_quat,
        "tdir": l_tdir,
        "rot_deg": rot_deg,
        "rot_gt_deg": rot_gt_deg,
        "trans_deg": trans_deg,
    }


def quaternion_target(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (x, y, z, w; w >= 0, DA3's encoding order) of (..., 3, 3) rotations."""
    from depth_anything_3.model.utils.transform import mat_to_quat

    return mat_to_quat(rotation)
