#!/usr/bin/env python3
"""Make the text-tower parity fixture (tests/fixtures/idarb/text/) with the official stack.

What it writes, numbers only:
  tokenizer/            a CLIPTokenizer folder saved by transformers (vocab.json, merges.txt,
                        special_tokens_map.json, tokenizer_config.json) holding the *subset* of the
                        real CLIP BPE vocabulary and merges that the test strings use, with their
                        original ids and ranks; SD-2.x's settings: pad token "!", 77 tokens
  tokenizer_cases.json  every test string (IDArb's five prompts first) with its padded ids from the
                        tokenizer built on the *full* vocabulary
  text_encoder/         a tiny random CLIPTextModel (official key names, real vocabulary size,
                        SD-2.1's exact-GELU activation), saved by transformers as model.fp16.safetensors
  text_case.safetensors input_ids [5, 77] of the five prompts and the model's last_hidden_state
                        [5, 77, hidden] (float32)

The vocabulary comes from the OpenAI CLIP BPE file that PyPI packages ship (MIT licence), e.g. the
open_clip_torch wheel's open_clip/bpe_simple_vocab_16e6.txt.gz; no hub download. SD-2.1's
`tokenizer/` folder is a CLIPTokenizer over that vocabulary (same vocab.json / merges.txt as OpenAI's
CLIP) with pad_token "!" (id 0) and model_max_length 77.

The subset is exact: BPE merges the lowest-ranked adjacent pair present, so keeping every merge the
full table applies to these strings (in their original order) reproduces the same symbols; the
script checks this by tokenizing every string with both tokenizers.

Usage: python3 tools/idarb/make_text_fixture.py OUT_DIR --bpe PATH
  PATH: bpe_simple_vocab_16e6.txt.gz, or an open_clip_torch wheel that contains it
  (pip download open_clip_torch --no-deps).
Needs: pip install torch transformers safetensors"""
import argparse
import gzip
import io
import json
import tempfile
import zipfile
from pathlib import Path

import torch
import transformers
from safetensors.torch import save_file
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer
from transformers.models.clip.tokenization_clip import bytes_to_unicode, whitespace_clean

# official IDArb `prepare_text_embeddings` (pipeline_idarbdiffusion.py, train.py), in this order
TASK_PROMPTS = ["albedo", "normal", "metallic and roughness", "metallic", "roughness"]
# more strings for the tokenizer: case, whitespace, digits, punctuation, contractions, truncation
EXTRA_STRINGS = [
    "Metallic  AND\tRoughness",
    "a photo of the object's base colour, 512x512 px!",
    "it's (roughness) = 0.25; normal-map  ...",
    " ".join(["albedo normal metallic roughness"] * 20),
]
MAX_LENGTH = 77
PAD_TOKEN = "!"
SEED = 17


def read_bpe(path: Path) -> list[str]:
    if path.suffix == ".whl":
        with zipfile.ZipFile(path) as z:
            name = next(n for n in z.namelist() if n.endswith("bpe_simple_vocab_16e6.txt.gz"))
            data = z.read(name)
    else:
        data = path.read_bytes()
    return gzip.open(io.BytesIO(data)).read().decode("utf-8").split("\n")


def full_vocabulary(lines: list[str]):
    """OpenAI CLIP's vocabulary: 256 byte symbols, the same with </w>, one symbol per merge, and the
    two special tokens (49408 in all); the merges are lines 1..48894 of the BPE file."""
    merges = [tuple(line.split()) for line in lines[1:49152 - 256 - 2 + 1]]
    symbols = list(bytes_to_unicode().values())
    vocab = symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    return {s: i for i, s in enumerate(vocab)}, merges


def write_tokenizer_files(folder: Path, vocab: dict, merges: list) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "\n".join(" ".join(m) for m in merges) + "\n")


def bpe_with_trace(word: str, ranks: dict) -> tuple[list[str], set]:
    """BPE of one byte-encoded pre-token, recording the merges applied."""
    symbols = list(word[:-1]) + [word[-1] + "</w>"]
    used = set()
    while len(symbols) > 1:
        pairs = {(a, b) for a, b in zip(symbols, symbols[1:]) if (a, b) in ranks}
        if not pairs:
            break
        best = min(pairs, key=ranks.get)
        used.add(best)
        out, i = [], 0
        while i < len(symbols):
            if i + 1 < len(symbols) and (symbols[i], symbols[i + 1]) == best:
                out.append(best[0] + best[1])
                i += 2
            else:
                out.append(symbols[i])
                i += 1
        symbols = out
    return symbols, used


def make_tokenizer(folder: Path) -> CLIPTokenizer:
    return CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), pad_token=PAD_TOKEN,
                         model_max_length=MAX_LENGTH)


def padded_ids(tok: CLIPTokenizer, texts: list[str]) -> list[list[int]]:
    # as the official pipeline calls it
    return tok(texts, max_length=tok.model_max_length, padding="max_length", truncation=True).input_ids


def tiny_text_encoder() -> CLIPTextModel:
    config = CLIPTextConfig(vocab_size=49408, hidden_size=16, intermediate_size=32, num_hidden_layers=2,
                            num_attention_heads=2, max_position_embeddings=MAX_LENGTH, hidden_act="gelu",
                            layer_norm_eps=1e-5, projection_dim=8, bos_token_id=0, eos_token_id=2, pad_token_id=1)
    model = CLIPTextModel(config).eval()
    g = torch.Generator().manual_seed(SEED)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "layer_norm" in name and name.endswith("weight"):
                p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
            elif name.endswith("bias"):
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
            elif "embedding" in name:
                p.copy_(torch.randn(p.shape, generator=g))
            else:  # Linear weights [out, in]: unit-variance outputs
                p.copy_(torch.randn(p.shape, generator=g) / p.shape[1] ** 0.5)
            p.copy_(p.half().float())  # the values the fp16 file holds
    return model


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--bpe", type=Path, required=True)
    args = ap.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    texts = TASK_PROMPTS + EXTRA_STRINGS

    vocab, merges = full_vocabulary(read_bpe(args.bpe))
    assert len(vocab) == 49408 and vocab[PAD_TOKEN] == 0 and vocab["<|endoftext|>"] == 49407
    with tempfile.TemporaryDirectory() as tmp:
        full_dir = Path(tmp) / "full"
        write_tokenizer_files(full_dir, vocab, merges)
        full = make_tokenizer(full_dir)
        ids = padded_ids(full, texts)

        # the subset: every merge and final symbol the strings use, plus the special tokens
        ranks = {m: r for r, m in enumerate(merges)}
        used_merges, used_symbols = set(), {"<|startoftext|>", "<|endoftext|>", PAD_TOKEN}
        for text in texts:
            # CLIPTokenizer._tokenize's cleanup, then its pre-tokens
            clean = " ".join(full.nlp.tokenize(text)) if full.fix_text is None else whitespace_clean(full.fix_text(text)).lower()
            for token in full.pat.findall(clean):
                encoded = "".join(full.byte_encoder[b] for b in token.encode("utf-8"))
                symbols, used = bpe_with_trace(encoded, ranks)
                assert " ".join(symbols) == full.bpe(encoded), (token, symbols)
                used_merges |= used
                used_symbols |= set(symbols)
        sub_merges = [m for m in merges if m in used_merges]
        sub_vocab = {s: i for s, i in vocab.items() if s in used_symbols}
        sub_dir = Path(tmp) / "subset"
        write_tokenizer_files(sub_dir, sub_vocab, sub_merges)
        subset = make_tokenizer(sub_dir)
        assert padded_ids(subset, texts) == ids, "the subset vocabulary changes the ids"
        subset.save_pretrained(out / "tokenizer")
    # the saved folder must load back and agree too
    saved = CLIPTokenizer.from_pretrained(out / "tokenizer")
    assert saved.pad_token == PAD_TOKEN and saved.model_max_length == MAX_LENGTH
    assert padded_ids(saved, texts) == ids
    (out / "tokenizer_cases.json").write_text(json.dumps(
        {"max_length": MAX_LENGTH, "pad_token": PAD_TOKEN,
         "cases": [{"text": t, "input_ids": i} for t, i in zip(texts, ids)]}, indent=1, ensure_ascii=False) + "\n")

    model = tiny_text_encoder()
    model.half().save_pretrained(out / "text_encoder", variant="fp16", safe_serialization=True)
    model = CLIPTextModel.from_pretrained(out / "text_encoder", variant="fp16", torch_dtype=torch.float32).eval()
    input_ids = torch.tensor(ids[:len(TASK_PROMPTS)], dtype=torch.int64)
    with torch.no_grad():
        hidden = model(input_ids, return_dict=False)[0].float().contiguous()  # as prepare_text_embeddings
        eager = CLIPTextModel.from_pretrained(out / "text_encoder", variant="fp16", torch_dtype=torch.float32,
                                              attn_implementation="eager").eval()
        spread = (eager(input_ids, return_dict=False)[0] - hidden).abs().max().item()
    save_file({"input_ids": input_ids, "last_hidden_state": hidden}, str(out / "text_case.safetensors"),
              metadata={"prompts": "|".join(TASK_PROMPTS), "torch": torch.__version__,
                        "transformers": transformers.__version__,
                        "attn_implementation": model.config._attn_implementation})
    print(f"wrote {out}: {len(sub_vocab)} of {len(vocab)} symbols, {len(sub_merges)} of {len(merges)} merges; "
          f"hidden {tuple(hidden.shape)} max |x| {hidden.abs().max().item():.3f}; "
          f"eager vs {model.config._attn_implementation} attention {spread:.2e}")


if __name__ == "__main__":
    main()
