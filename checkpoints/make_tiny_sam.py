#!/usr/bin/env python3
"""Build the tiny Segment Anything parity fixture in checkpoints/tiny-sam/.

Run by hand once (CI needs no Python):

    python3 -m venv /tmp/samvenv && /tmp/samvenv/bin/pip install torch transformers safetensors
    /tmp/samvenv/bin/python checkpoints/make_tiny_sam.py

It builds a random transformers `SamModel` with the real architecture (ViT image encoder with windowed and
global attention and decomposed relative positions, the neck, the prompt encoder with its random-Fourier
positional embedding, the two-way-transformer mask decoder) but tiny widths: 64x64 images in 8-px patches
(an 8x8 grid), width 32, 2 layers (the first windowed with window 3, so that the 8x8 grid is padded to 9x9 as
SAM's 64x64 grid is padded to 70x70 by its window 14; the second global), 16 output channels. Every parameter
is randomised, also those transformers initialises to zeros (relative and absolute positions), so that each
of them shows in the outputs. The model directory is written with `save_pretrained` (config.json,
model.safetensors in f32). Reference outputs computed by transformers go to reference.safetensors; the Rust
tests (tests/suite/sam.rs) compare against them.
"""
import os

import torch
import torch.nn.functional as F
from safetensors.torch import save_file
from transformers import SamConfig, SamMaskDecoderConfig, SamModel, SamPromptEncoderConfig, SamVisionConfig

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tiny-sam")
SEED = 11


def randomise(model):
    """Every parameter random, at scales that keep the activations O(1)."""
    g = torch.Generator().manual_seed(SEED)
    with torch.no_grad():
        for name, p in model.named_parameters():
            n = torch.randn(p.shape, generator=g)
            if name.endswith("positional_embedding"):
                v = n  # std 1: Fourier features of a few cycles across the image
            elif "rel_pos" in name or name.endswith("pos_embed"):
                v = 0.5 * n
            elif p.ndim >= 2:
                fan_in = p[0].numel() if "upscale_conv" not in name else p.shape[0]
                v = n / fan_in**0.5
            elif "layer_norm" in name and name.endswith("weight"):
                v = 1.0 + 0.2 * n
            else:
                v = 0.2 * n
            p.copy_(v)


def main():
    torch.manual_seed(SEED)
    vision = SamVisionConfig(
        hidden_size=32,
        output_channels=16,
        num_hidden_layers=2,
        num_attention_heads=2,
        image_size=64,
        patch_size=8,
        mlp_dim=64,
        window_size=3,
        global_attn_indexes=[1],
        use_rel_pos=True,
        num_pos_feats=8,
    )
    # mask_input_channels 8, not 4: the first mask conv has mask_input_channels / 4 channels, and a layer norm
    # over 1 channel would hide it (its output is its bias)
    prompt = SamPromptEncoderConfig(hidden_size=16, image_size=64, patch_size=8, mask_input_channels=8)
    decoder = SamMaskDecoderConfig(
        hidden_size=16, mlp_dim=32, num_hidden_layers=2, num_attention_heads=2, iou_head_hidden_dim=16
    )
    config = SamConfig(
        vision_config=vision.to_dict(), prompt_encoder_config=prompt.to_dict(), mask_decoder_config=decoder.to_dict()
    )
    config._attn_implementation = "eager"
    model = SamModel(config)
    randomise(model)
    # The prompt encoder's positional embedding is tied to the model's shared one.
    a = model.shared_image_embedding.positional_embedding
    b = model.prompt_encoder.shared_embedding.positional_embedding
    assert a.data_ptr() == b.data_ptr(), "the shared positional embedding is not tied"
    model.eval()
    os.makedirs(OUT, exist_ok=True)
    model.save_pretrained(OUT, safe_serialization=True)

    g = torch.Generator().manual_seed(SEED + 1)
    pixel_values = torch.randn((1, 3, 64, 64), generator=g)
    input_points = torch.tensor([[[[10.0, 20.0], [41.5, 35.0]]]])  # [B, point batch, points, (x, y)]
    input_labels = torch.tensor([[[1, 0]]])
    input_boxes = torch.tensor([[[5.0, 8.0, 50.0, 60.0]]])  # [B, boxes, (x1, y1, x2, y2)]
    input_masks = torch.randn((1, 1, 32, 32), generator=g)
    ref = {"pixel_values": pixel_values, "input_points": input_points, "input_labels": input_labels.float(),
           "input_boxes": input_boxes, "input_masks": input_masks}
    with torch.no_grad():
        emb = model.get_image_embeddings(pixel_values)
        ref["image_embeddings"] = emb
        ref["image_positional_embeddings"] = model.get_image_wide_positional_embeddings()
        # 2 points and a box
        sparse, dense = model.get_prompt_embeddings(input_points, input_labels, input_boxes)
        ref["sparse_embeddings"], ref["dense_embeddings"] = sparse, dense.contiguous()
        out = model(image_embeddings=emb, input_points=input_points, input_labels=input_labels,
                    input_boxes=input_boxes, multimask_output=True)
        ref["pred_masks"], ref["iou_scores"] = out.pred_masks, out.iou_scores
        # the points alone: a padding point (label -1) is appended
        sparse_p, _ = model.get_prompt_embeddings(input_points, input_labels)
        ref["points_sparse_embeddings"] = sparse_p
        out = model(image_embeddings=emb, input_points=input_points, input_labels=input_labels,
                    multimask_output=True)
        ref["points_pred_masks"], ref["points_iou_scores"] = out.pred_masks, out.iou_scores
        # a mask prompt: the dense embedding through the mask-embedding convs
        _, dense_m = model.get_prompt_embeddings(input_points, input_labels, input_boxes, input_masks)
        ref["mask_dense_embeddings"] = dense_m
        # relative positions at another size than stored (linear interpolation) and for q != k sizes
        attn = model.vision_encoder.layers[0].attn
        ref["rel_pos"] = attn.rel_pos_h.detach().clone()
        ref["rel_pos_4_4"] = attn.get_rel_pos(4, 4, attn.rel_pos_h)
        ref["rel_pos_2_5"] = attn.get_rel_pos(2, 5, attn.rel_pos_h)
        ref["rel_pos_5_3"] = attn.get_rel_pos(5, 3, attn.rel_pos_h)
        # cross-check: the resize is torch's linear interpolation with align_corners=False
        rs = F.interpolate(attn.rel_pos_h.T[None], size=7, mode="linear")[0].T
        assert torch.allclose(rs[torch.arange(4)[:, None] - torch.arange(4)[None] + 3], ref["rel_pos_4_4"])
    ref = {k: v.detach().float().contiguous() for k, v in ref.items()}
    save_file(ref, os.path.join(OUT, "reference.safetensors"))
    for k, v in ref.items():
        print(f"{k:28s} {list(v.shape)}  max |x| {v.abs().max():.4g}")


if __name__ == "__main__":
    main()
