"""Depth Anything V2 reference outputs from ``transformers``' PyTorch port, on random weights in the official format.

Usage: ``python tests/torch_refs/make_dav2_reference.py OUT_DIR``. For each case below it builds
``DepthAnythingForDepthEstimation`` (a DINOv2 backbone config), draws seeded random weights, renames them to the
official checkpoint's keys (``pretrained.*``, ``depth_head.*``: the inverse of the official → HF key map of
transformers' ``convert_depth_anything_to_hf.py``, q/k/v fused back into ``qkv``; every HF key used once),
writes it with ``torch.save`` as ``<case>.pth`` and writes
``<case>.npz`` with the inputs (NHWC), the output depth, the backbone's four normalised token maps and the
four fusion outputs.

One deliberate change to the port: DINOv2's position-embedding resize. The official ``interpolate_pos_encoding``
(depth_anything_v2/dinov2.py) calls the bicubic ``F.interpolate`` with ``scale_factor = (n + 0.1) / G``
(``interpolate_offset``); transformers passes the output size instead, which moves the sample points. The port's
method is replaced by one that does what the official code does, so the reference is the official model.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
from transformers.models.dinov2 import modeling_dinov2

# name: (hidden, depth, heads, layers (0-based), fusion width, neck widths, trained grid, head, max_depth,
#        input sizes (H, W), batch)
CASES = {
    "tiny_relative": (32, 4, 2, (0, 1, 2, 3), 8, (4, 8, 16, 32), 4, "relative", 1, ((70, 98), (56, 56)), 2),
    "tiny_metric": (32, 5, 2, (1, 2, 3, 4), 8, (4, 8, 16, 32), 4, "metric", 80, ((70, 98), (56, 56)), 2),
    # The released Small architecture (ViT-S/14, 37² position grid, blocks 2/5/8/11), once, at a tiny input.
    "small_metric": (384, 12, 6, (2, 5, 8, 11), 64, (48, 96, 192, 384), 37, "metric", 80, ((42, 56),), 1),
}
# The released relative Small (not written by main(); benchmarks/models_speed.py builds it for its timings).
SMALL_RELATIVE = (384, 12, 6, (2, 5, 8, 11), 64, (48, 96, 192, 384), 37, "relative", 1, (), 1)


def official_interpolate_pos_encoding(self, embeddings, height, width):
    """depth_anything_v2/dinov2.py's rule: identity for the trained square grid, else bicubic by scale factor."""
    pos = self.position_embeddings
    n_pos = pos.shape[1] - 1
    h, w = height // self.patch_size, width // self.patch_size
    if embeddings.shape[1] - 1 == n_pos and height == width:
        return pos
    g = int(math.sqrt(n_pos))
    grid = pos[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
    grid = F.interpolate(grid, scale_factor=((h + 0.1) / g, (w + 0.1) / g), mode="bicubic", antialias=False)
    assert grid.shape[-2:] == (h, w), grid.shape
    return torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)], dim=1)


def hf_to_official(sd: dict[str, torch.Tensor], depth: int) -> dict[str, torch.Tensor]:
    """HF DepthAnythingForDepthEstimation keys → the official checkpoint's keys (every key used exactly once)."""
    out: dict[str, torch.Tensor] = {}
    sd = dict(sd)

    def move(src: str, dst: str) -> None:
        out[dst] = sd.pop(src)

    move("backbone.embeddings.cls_token", "pretrained.cls_token")
    move("backbone.embeddings.mask_token", "pretrained.mask_token")
    move("backbone.embeddings.position_embeddings", "pretrained.pos_embed")
    for leaf in ("weight", "bias"):
        move(f"backbone.embeddings.patch_embeddings.projection.{leaf}", f"pretrained.patch_embed.proj.{leaf}")
        move(f"backbone.layernorm.{leaf}", f"pretrained.norm.{leaf}")
    for i in range(depth):
        hf, og = f"backbone.encoder.layer.{i}", f"pretrained.blocks.{i}"
        move(f"{hf}.layer_scale1.lambda1", f"{og}.ls1.gamma")
        move(f"{hf}.layer_scale2.lambda1", f"{og}.ls2.gamma")
        for leaf in ("weight", "bias"):
            for a, b in (("norm1", "norm1"), ("norm2", "norm2"), ("mlp.fc1", "mlp.fc1"), ("mlp.fc2", "mlp.fc2")):
                move(f"{hf}.{a}.{leaf}", f"{og}.{b}.{leaf}")
            # transformers 5 names them q/k/v/o_proj (its 4.x converter: attention.attention.query, ...).
            move(f"{hf}.attention.o_proj.{leaf}", f"{og}.attn.proj.{leaf}")
            qkv = [sd.pop(f"{hf}.attention.{p}_proj.{leaf}") for p in ("q", "k", "v")]
            out[f"{og}.attn.qkv.{leaf}"] = torch.cat(qkv, dim=0)
    for i in range(4):
        for leaf in ("weight", "bias"):
            move(f"neck.reassemble_stage.layers.{i}.projection.{leaf}", f"depth_head.projects.{i}.{leaf}")
            if i != 2:
                move(f"neck.reassemble_stage.layers.{i}.resize.{leaf}", f"depth_head.resize_layers.{i}.{leaf}")
        move(f"neck.convs.{i}.weight", f"depth_head.scratch.layer{i + 1}_rn.weight")
        j = 4 - i  # HF's fusion layer 0 is the official refinenet4 (the coarsest)
        for leaf in ("weight", "bias"):
            move(f"neck.fusion_stage.layers.{i}.projection.{leaf}", f"depth_head.scratch.refinenet{j}.out_conv.{leaf}")
            for r in (1, 2):
                for c in (1, 2):
                    move(
                        f"neck.fusion_stage.layers.{i}.residual_layer{r}.convolution{c}.{leaf}",
                        f"depth_head.scratch.refinenet{j}.resConfUnit{r}.conv{c}.{leaf}",
                    )
    for leaf in ("weight", "bias"):
        move(f"head.conv1.{leaf}", f"depth_head.scratch.output_conv1.{leaf}")
        move(f"head.conv2.{leaf}", f"depth_head.scratch.output_conv2.0.{leaf}")
        move(f"head.conv3.{leaf}", f"depth_head.scratch.output_conv2.2.{leaf}")
    if sd:
        raise SystemExit(f"HF keys left unmapped: {sorted(sd)}")
    return out


def build(spec: tuple) -> DepthAnythingForDepthEstimation:
    """The HF model of one ``CASES`` entry (or ``SMALL_RELATIVE``), default-initialised, in eval mode."""
    hidden, depth, heads, layers, fusion, neck, grid, head, max_depth, _, _ = spec
    backbone = Dinov2Config(
        hidden_size=hidden,
        num_hidden_layers=depth,
        num_attention_heads=heads,
        intermediate_size=4 * hidden,
        mlp_ratio=4,
        patch_size=14,
        image_size=14 * grid,
        layerscale_value=1.0,
        layer_norm_eps=1e-6,
        hidden_act="gelu",
        qkv_bias=True,
        use_swiglu_ffn=False,
        out_indices=[i + 1 for i in layers],
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    config = DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=hidden,
        patch_size=14,
        fusion_hidden_size=fusion,
        neck_hidden_sizes=list(neck),
        head_hidden_size=32,
        depth_estimation_type=head,
        max_depth=max_depth,
    )
    return DepthAnythingForDepthEstimation(config).eval()


def randomise(model: torch.nn.Module, seed: int) -> None:
    """Seeded weights that exercise every parameter: LayerNorm/LayerScale near 1, fan-in scaled matrices."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith(("lambda1",)) or (p.ndim == 1 and "norm" in name and name.endswith("weight")):
                p.copy_(1.0 + 0.2 * torch.randn(p.shape, generator=g))
            elif p.ndim == 1 or name.endswith(("cls_token", "mask_token")):
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
            elif name.endswith("position_embeddings"):
                p.copy_(0.5 * torch.randn(p.shape, generator=g))
            else:
                fan_in = p[0].numel()
                p.copy_(torch.randn(p.shape, generator=g) * (1.5 / fan_in) ** 0.5)


def main() -> None:
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    modeling_dinov2.Dinov2Embeddings.interpolate_pos_encoding = official_interpolate_pos_encoding
    index = {}
    for k, case in enumerate(CASES):
        _, depth, _, _, _, _, _, _, _, sizes, batch = CASES[case]
        model = build(CASES[case])
        randomise(model, seed=k)
        official = hf_to_official(model.state_dict(), depth)
        torch.save(official, out / f"{case}.pth")
        arrays = {}
        g = torch.Generator().manual_seed(100 + k)
        for h, w in sizes:
            x = torch.randn((batch, 3, h, w), generator=g)
            with torch.no_grad():
                depth_out = model(pixel_values=x).predicted_depth
                feats = model.backbone(x).feature_maps
                fused = model.neck(list(feats), h // 14, w // 14)
            tag = f"{h}x{w}"
            arrays[f"input_{tag}"] = x.permute(0, 2, 3, 1).numpy()
            arrays[f"depth_{tag}"] = depth_out.numpy()
            for i, f in enumerate(feats, start=1):  # (N, 1 + h·w, D) after the final LayerNorm
                arrays[f"features_{i}_{tag}"] = f[:, 1:].reshape(batch, h // 14, w // 14, -1).numpy()
            for i, f in zip((4, 3, 2, 1), fused, strict=True):
                arrays[f"path_{i}_{tag}"] = f.permute(0, 2, 3, 1).numpy()
        np.savez(out / f"{case}.npz", **arrays)
        index[case] = {"sizes": [list(s) for s in sizes], "keys": len(official)}
    (out / "index.json").write_text(json.dumps(index))


if __name__ == "__main__":
    main()
