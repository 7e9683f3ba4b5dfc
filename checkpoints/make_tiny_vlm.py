#!/usr/bin/env python3
"""Build the tiny LLaVA-OneVision parity fixture in checkpoints/tiny-llava-ov/.

Run by hand once (CI needs no Python):

    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install torch==2.13.0 torchvision==0.28.0 transformers safetensors tokenizers pillow
    /tmp/venv/bin/python checkpoints/make_tiny_vlm.py

It builds a random LlavaOnevisionForConditionalGeneration with the real architecture (SigLIP vision tower at
384x384 / patch 14 -> 27x27 tokens, linear-GELU-linear projector, Qwen2 decoder with GQA, q/k/v bias, tied
embeddings) but tiny widths, a small byte-level BPE tokenizer with the Qwen2 pre-tokenizer and special tokens,
and the LLaVA-OneVision chat template. The model directory is written the way Hugging Face writes real ones
(config.json, bf16 weights sharded with model.safetensors.index.json, tokenizer.json, preprocessor_config.json,
chat_template.json). Reference outputs computed by transformers go to reference.safetensors and
reference.json; the Rust tests compare against them.
"""
import json
import os
import shutil
import sys

import numpy as np
import torch
from PIL import Image
from safetensors.torch import save_file
from tokenizers import Tokenizer, Regex, decoders, models, normalizers, pre_tokenizers, trainers
from transformers import (
    LlavaOnevisionConfig,
    LlavaOnevisionForConditionalGeneration,
    LlavaOnevisionProcessor,
    LlavaOnevisionVideoProcessor,
    PreTrainedTokenizerFast,
    Qwen2Config,
    SiglipVisionConfig,
)
from transformers.models.llava_onevision.image_processing_pil_llava_onevision import (
    LlavaOnevisionImageProcessorPil,
)

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tiny-llava-ov")
SEED = 7
# Real LLaVA-OneVision chat template (llava-hf conversion script).
CHAT_TEMPLATE = (
    "{% for message in messages %}{{'<|im_start|>' + message['role'] + '\\n'}}"
    "{# Render all images first #}{% for content in message['content'] | selectattr('type', 'equalto', 'image') %}"
    "{{ '<image>\\n' }}{% endfor %}"
    "{# Render all video then #}{% for content in message['content'] | selectattr('type', 'equalto', 'video') %}"
    "{{ '<video>\\n' }}{% endfor %}"
    "{# Render all text next #}{% if message['role'] != 'assistant' %}"
    "{% for content in message['content'] | selectattr('type', 'equalto', 'text') %}{{ content['text'] }}{% endfor %}"
    "{% else %}{% for content in message['content'] | selectattr('type', 'equalto', 'text') %}"
    "{% generation %}{{ content['text'] }}{% endgeneration %}{% endfor %}{% endif %}"
    "{{'<|im_end|>' + '\\n'}}{% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\\n' }}{% endif %}"
)
SPECIALS = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<image>", "<video>"]
# Qwen2's pre-tokenizer split pattern.
QWEN_PATTERN = (
    r"(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+"
)
CORPUS = [
    "What is on the table? A red sphere next to a blue box and a green cylinder.",
    "Describe the scene in detail. The wooden table holds a yellow cone, a white mug and a small plant.",
    "Which object is closest to the camera? The orange box is closest; the purple sphere is behind it.",
    "How many objects are there? There are five objects: two spheres, one box, one cone and one cylinder.",
    "What colour is the object I clicked? It is a shiny metallic teapot with a curved spout.",
    "user assistant system image view scene object left right front back top bottom near far",
    "0123456789 The quick brown fox jumps over the lazy dog. Where is the lamp? On the shelf.",
]


def build_tokenizer():
    tok = Tokenizer(models.BPE(unk_token=None, byte_fallback=False))
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN_PATTERN), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=320,
        special_tokens=SPECIALS,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(CORPUS * 4, trainer=trainer)
    return PreTrainedTokenizerFast(
        tokenizer_object=tok,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
        extra_special_tokens={"image_token": "<image>", "video_token": "<video>"},
    )


def make_image(h, w, seed):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack(
        [
            (xx * 255 / max(w - 1, 1)),
            (yy * 255 / max(h - 1, 1)),
            128 + 100 * np.sin(xx / 9.0) * np.cos(yy / 13.0),
        ],
        axis=-1,
    )
    img += rng.normal(0, 12, img.shape)  # texture so resampling details matter
    return Image.fromarray(np.clip(img, 0, 255).astype(np.uint8), "RGB")


def main():
    torch.manual_seed(SEED)
    if os.path.exists(OUT):
        shutil.rmtree(OUT)
    os.makedirs(OUT)

    tokenizer = build_tokenizer()
    image_token_id = tokenizer.convert_tokens_to_ids("<image>")
    video_token_id = tokenizer.convert_tokens_to_ids("<video>")

    vision = SiglipVisionConfig(
        hidden_size=32, intermediate_size=64, num_hidden_layers=3, num_attention_heads=4,
        image_size=384, patch_size=14, hidden_act="gelu_pytorch_tanh", layer_norm_eps=1e-6,
        vision_use_head=False, initializer_range=0.2,
    )
    text = Qwen2Config(
        vocab_size=len(tokenizer), hidden_size=64, intermediate_size=128, num_hidden_layers=2,
        num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=4096,
        rope_parameters={"rope_type": "default", "rope_theta": 1000000.0}, rms_norm_eps=1e-6,
        tie_word_embeddings=True, initializer_range=0.25, hidden_act="silu",
        bos_token_id=None, eos_token_id=tokenizer.convert_tokens_to_ids("<|im_end|>"),
    )
    pinpoints = [[384, 384], [384, 768], [768, 384], [768, 768]]
    config = LlavaOnevisionConfig(
        vision_config=vision, text_config=text, image_token_index=image_token_id,
        video_token_index=video_token_id, vision_feature_layer=-1, vision_feature_select_strategy="full",
        image_grid_pinpoints=pinpoints, vision_aspect_ratio="anyres_max_1", tie_word_embeddings=True,
    )
    model = LlavaOnevisionForConditionalGeneration(config).eval()
    with torch.no_grad():  # give the projector and newline visible scale too
        for p in model.model.multi_modal_projector.parameters():
            p.normal_(0.0, 0.2)
        model.model.image_newline.normal_(0.0, 0.5)
    # Real checkpoints are bf16; round the weights to bf16 so the f32 reference equals what Rust loads.
    model = model.to(torch.bfloat16)
    model.save_pretrained(OUT, max_shard_size="120KB", safe_serialization=True)
    model = LlavaOnevisionForConditionalGeneration.from_pretrained(OUT, dtype=torch.float32).eval()

    image_processor = LlavaOnevisionImageProcessorPil(
        image_grid_pinpoints=pinpoints, image_mean=[0.5, 0.5, 0.5], image_std=[0.5, 0.5, 0.5],
        size={"height": 384, "width": 384},
    )
    processor = LlavaOnevisionProcessor(
        image_processor=image_processor, tokenizer=tokenizer, video_processor=LlavaOnevisionVideoProcessor(),
        num_image_tokens=729,
        vision_feature_select_strategy="full", chat_template=CHAT_TEMPLATE, vision_aspect_ratio="anyres_max_1",
    )
    processor.save_pretrained(OUT)

    img_wide = make_image(300, 700, 1)
    img_a = make_image(384, 384, 2)
    img_b = make_image(200, 260, 3)
    img_wide.save(os.path.join(OUT, "image_wide.png"))
    img_a.save(os.path.join(OUT, "image_a.png"))
    img_b.save(os.path.join(OUT, "image_b.png"))

    def conv(n_images, text):
        return [{"role": "user", "content": [{"type": "image"}] * n_images + [{"type": "text", "text": text}]}]

    q1 = "What is on the table?"
    prompt1 = processor.apply_chat_template(conv(1, q1), add_generation_prompt=True)
    q2 = "Which object is closest to the camera?"
    prompt2 = processor.apply_chat_template(conv(2, q2), add_generation_prompt=True)
    followup = conv(1, q1) + [
        {"role": "assistant", "content": [{"type": "text", "text": "A red sphere."}]},
        {"role": "user", "content": [{"type": "text", "text": "Where is it?"}]},
    ]
    prompt3 = processor.apply_chat_template(followup, add_generation_prompt=True)

    ref = {}
    with torch.no_grad():
        # --- single image, anyres path ---
        inputs = processor(images=[img_wide], text=prompt1, return_tensors="pt")
        pv = inputs["pixel_values"][0]  # [P,3,384,384]
        out = model.model.vision_tower(pv, output_hidden_states=True)
        feats = out.hidden_states[config.vision_feature_layer]
        proj = model.model.multi_modal_projector(feats)
        packed = model.model.get_image_features(
            pixel_values=inputs["pixel_values"], image_sizes=inputs["image_sizes"],
            vision_feature_layer=config.vision_feature_layer,
            vision_feature_select_strategy="full", batch_num_images=inputs["batch_num_images"],
        ).pooler_output[0]
        logits = model(**inputs).logits[0]
        # uint8 patches = the normalised pixels mapped back (mean=std=0.5 -> x*127.5+127.5 exactly)
        patches_u8 = torch.round(pv * 127.5 + 127.5).to(torch.uint8)
        assert torch.allclose(patches_u8.float() / 127.5 - 1.0, pv, atol=1e-6)
        gen = model.generate(**inputs, do_sample=False, max_new_tokens=12, min_new_tokens=12)
        new_ids = gen[0, inputs["input_ids"].shape[1]:]
        # argmax margins along the greedy path (parity needs them well above float noise)
        steps = model(input_ids=gen[:, :-1], pixel_values=inputs["pixel_values"],
                      image_sizes=inputs["image_sizes"], batch_num_images=inputs["batch_num_images"]).logits[0]
        tail = steps[inputs["input_ids"].shape[1] - 1:]
        top2 = torch.topk(tail, 2, dim=-1).values
        margin = float((top2[:, 0] - top2[:, 1]).min())
        ref["single_patches_u8"] = patches_u8.contiguous()
        ref["single_vision_features"] = feats.contiguous()
        ref["single_projected"] = proj.contiguous()
        ref["single_packed"] = packed.contiguous()
        ref["single_input_ids"] = inputs["input_ids"][0].to(torch.int64).contiguous()
        ref["single_logits"] = logits.contiguous()
        ref["single_greedy_ids"] = new_ids.to(torch.int64).contiguous()

        # --- two images in one prompt: base view only + newline each ---
        inputs2 = processor(images=[[img_a, img_b]], text=prompt2, return_tensors="pt")
        logits2 = model(**inputs2).logits[0]
        packed2 = model.model.get_image_features(
            pixel_values=inputs2["pixel_values"], image_sizes=inputs2["image_sizes"],
            vision_feature_layer=config.vision_feature_layer, vision_feature_select_strategy="full",
            batch_num_images=inputs2["batch_num_images"],
        ).pooler_output
        ref["multi_patches_u8"] = torch.round(inputs2["pixel_values"][0] * 127.5 + 127.5).to(torch.uint8).contiguous()
        ref["multi_packed"] = torch.cat(list(packed2), dim=0).contiguous()
        ref["multi_input_ids"] = inputs2["input_ids"][0].to(torch.int64).contiguous()
        ref["multi_logits_last"] = logits2[-4:].contiguous()

    save_file(ref, os.path.join(OUT, "reference.safetensors"))
    meta = {
        "generated_by": "checkpoints/make_tiny_vlm.py",
        "torch": torch.__version__,
        "transformers": __import__("transformers").__version__,
        "seed": SEED,
        "prompt_single": prompt1,
        "prompt_multi": prompt2,
        "prompt_followup": prompt3,
        "question_single": q1,
        "question_multi": q2,
        "single_image": "image_wide.png",
        "single_image_size_hw": [300, 700],
        "multi_images": ["image_a.png", "image_b.png"],
        "single_num_image_tokens": int((inputs["input_ids"][0] == image_token_id).sum()),
        "multi_num_image_tokens": int((inputs2["input_ids"][0] == image_token_id).sum()),
        "greedy_text": tokenizer.decode(new_ids, skip_special_tokens=False),
        "greedy_min_margin": margin,
        "image_token_id": image_token_id,
    }
    with open(os.path.join(OUT, "reference.json"), "w") as f:
        json.dump(meta, f, indent=2)
    print(json.dumps(meta, indent=2))
    total = sum(os.path.getsize(os.path.join(OUT, n)) for n in os.listdir(OUT))
    print(f"fixture: {OUT} ({total / 1e6:.2f} MB)")
    if margin < 1e-3:
        print("warning: greedy margin below 1e-3; pick another SEED", file=sys.stderr)


if __name__ == "__main__":
    main()
