#!/usr/bin/env python3
"""Cross-check for the Rust text tower: the prompt embeddings as PyTorch computes them.

IDArb conditions each domain on the CLIP text encoder's `last_hidden_state` of a fixed prompt
('albedo', 'normal', 'metallic and roughness'). The Rust tool computes these itself from the
folder's tokenizer/ and text_encoder/ (src/prior/idarb/text_embeddings.rs) and does not need this
script; with its output in the folder, `IDARB_WEIGHTS=DIR cargo test --release --test idarb_text`
compares the two.

Usage: python3 tools/idarb/make_text_embeddings.py WEIGHTS_DIR
  WEIGHTS_DIR is the official pipeline checkpoint folder (with text_encoder/ and tokenizer/).
Writes WEIGHTS_DIR/text_embeddings.safetensors with tensor `text_embeddings` [3, 77, 1024] (f32).
Needs: pip install torch transformers safetensors"""
import sys
from pathlib import Path

import torch
from safetensors.torch import save_file
from transformers import CLIPTextModel, CLIPTokenizer

PROMPTS = ["albedo", "normal", "metallic and roughness"]  # domain order: rows 3v+0, 3v+1, 3v+2


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    root = Path(sys.argv[1])
    for sub in ("text_encoder", "tokenizer"):
        if not (root / sub).is_dir():
            sys.exit(f"{root / sub} not found: pass the official IDArb checkpoint folder")
    tokenizer = CLIPTokenizer.from_pretrained(root, subfolder="tokenizer")
    encoder = CLIPTextModel.from_pretrained(root, subfolder="text_encoder", torch_dtype=torch.float32).eval()
    # as the official pipeline's prepare_text_embeddings: pad to max length, take last_hidden_state
    ids = tokenizer(PROMPTS, max_length=tokenizer.model_max_length, padding="max_length",
                    truncation=True, return_tensors="pt").input_ids
    with torch.no_grad():
        emb = encoder(ids, return_dict=False)[0].float().contiguous()
    out = root / "text_embeddings.safetensors"
    save_file({"text_embeddings": emb}, str(out), metadata={"prompts": "|".join(PROMPTS)})
    print(f"wrote {out} {tuple(emb.shape)}")


if __name__ == "__main__":
    main()
