#!/usr/bin/env python3
"""Time transformers on a random-weight LLaVA-OneVision of the published configuration, the
reference `vlm-bench --reference` prints beside chatsplat's figures (issue 12, item 1).

Run by hand (CI needs no Python), on the same machine and with the same thread count as the
Rust run; `eval/bench/vlm_vs_transformers.sh` runs both one after the other:

    pip install torch transformers
    python3 eval/bench/transformers_vlm.py --size 0.5b --threads 2 --prefill-tokens 2005 \
        --decode 16 --reps 1 --out /tmp/transformers_0.5b.json

`--device cuda` times the same on a GPU (`eval/gpu/run.sh` does, beside chatsplat's wgpu figures);
every timed region then ends with a device synchronisation.

It builds `LlavaOnevisionForConditionalGeneration` from the published llava-hf config values
(SigLIP 1152 x 26 at 384 / patch 14, Qwen2 896 x 24 or 3584 x 28, f32 weights, random init: speed
does not depend on the values) and times, after one warm-up each:
  - the vision tower on one 384x384 view (729 tokens, the layer LLaVA reads),
  - prefill of `--prefill-tokens` embeddings (the length of chatsplat's prompt in vlm-bench),
  - greedy decode of `--decode` tokens with the KV cache after that prompt (one token per step,
    as generate does), timed alone; the best of `--reps` + 1 runs.
The JSON it writes holds seconds and rates plus the versions and thread count used.
"""
import argparse
import json
import os
import platform
import resource
import sys
import time


def published(size):
    from transformers import LlavaOnevisionConfig, Qwen2Config, SiglipVisionConfig

    vision = SiglipVisionConfig(
        hidden_size=1152, intermediate_size=4304, num_hidden_layers=26, num_attention_heads=16,
        image_size=384, patch_size=14, layer_norm_eps=1e-6, hidden_act="gelu_pytorch_tanh",
    )
    if size == "0.5b":
        text = Qwen2Config(
            vocab_size=152000, hidden_size=896, intermediate_size=4864, num_hidden_layers=24,
            num_attention_heads=14, num_key_value_heads=2, rms_norm_eps=1e-6, rope_theta=1e6,
            max_position_embeddings=32768, tie_word_embeddings=True,
        )
    elif size == "7b":
        text = Qwen2Config(
            vocab_size=152128, hidden_size=3584, intermediate_size=18944, num_hidden_layers=28,
            num_attention_heads=28, num_key_value_heads=4, rms_norm_eps=1e-6, rope_theta=1e6,
            max_position_embeddings=32768, tie_word_embeddings=False,
        )
    else:
        sys.exit(f"error: --size {size}: expected 0.5b or 7b")
    return LlavaOnevisionConfig(
        vision_config=vision.to_dict(), text_config=text.to_dict(), image_token_index=151646,
        vision_feature_layer=-1, vision_feature_select_strategy="full",
        tie_word_embeddings=text.tie_word_embeddings,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="0.5b", choices=["0.5b", "7b"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--prefill-tokens", type=int, default=2005)
    ap.add_argument("--decode", type=int, default=16)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda")
    ap.add_argument("--out", required=True, help="JSON file to write (atomically)")
    a = ap.parse_args()
    if a.threads < 1 or a.prefill_tokens < 1 or a.decode < 1 or a.reps < 1:
        sys.exit("error: --threads, --prefill-tokens, --decode and --reps must be at least 1")

    import torch
    import transformers
    from transformers import LlavaOnevisionForConditionalGeneration

    if a.device.startswith("cuda") and not torch.cuda.is_available():
        sys.exit(f"error: --device {a.device}: torch {torch.__version__} sees no CUDA device")
    device = torch.device(a.device)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    t0 = time.perf_counter()
    with torch.device("cpu"):
        model = LlavaOnevisionForConditionalGeneration(published(a.size)).eval()
    model = model.to(device)
    build = time.perf_counter() - t0
    params = sum(p.numel() for p in model.parameters())
    print(f"built {a.size}: {params / 1e6:.1f} M parameters in {build:.0f} s", file=sys.stderr)

    def timed(f):
        f()  # warm-up
        sync()
        t = time.perf_counter()
        for _ in range(a.reps):
            f()
        sync()
        return (time.perf_counter() - t) / a.reps

    pixels = (torch.rand(1, 3, 384, 384) * 2 - 1).to(device)
    lm = model.model.language_model
    head = model.lm_head
    d = model.config.text_config.hidden_size
    embeds = (torch.randn(1, a.prefill_tokens, d) * 0.02).to(device)

    def vision():
        out = model.model.vision_tower(pixels, output_hidden_states=True)
        return out.hidden_states[-1]

    def prefill():
        out = lm(inputs_embeds=embeds, use_cache=True)
        return head(out.last_hidden_state[:, -1:]).argmax(-1), out.past_key_values

    def decode():
        # timed on its own: the prompt fills the KV cache first (not total minus prefill, whose
        # jitter would swamp the decode time)
        tok, cache = prefill()
        sync()
        t = time.perf_counter()
        for _ in range(a.decode):
            out = lm(input_ids=tok, past_key_values=cache, use_cache=True)
            cache = out.past_key_values
            tok = head(out.last_hidden_state[:, -1:]).argmax(-1)[:, -1:]
        sync()
        return time.perf_counter() - t

    with torch.inference_mode():
        vis = timed(vision)
        pre = timed(prefill)
        dec = min(decode() for _ in range(a.reps + 1))
    result = {
        "size": a.size,
        "threads": a.threads,
        "reps": a.reps,
        "parameters": params,
        "vision_s": vis,
        "prefill_tokens": a.prefill_tokens,
        "prefill_s": pre,
        "prefill_tokens_per_s": a.prefill_tokens / pre,
        "decode_tokens": a.decode,
        "decode_tokens_per_s": a.decode / dec,
        "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "peak_gpu_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else 0.0,
        "transformers": transformers.__version__,
        "torch": torch.__version__,
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
    }
    tmp = a.out + ".tmp"
    with open(tmp, "w") as f:
        json.dump(result, f, indent=1)
    os.replace(tmp, a.out)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
