"""The tiny CLIP BPE vocabulary of our RGB<->X-family prior: built here, byte for byte.

`write_prior_tokenizer(folder)` writes the tokenizer folder `scripts/train_rgbx.py` trains with
and ships (jaxdistill/models/rgbx_rooms/tokenizer/, byte for byte); `write_tiny_clip_tokenizer`
also writes the other pad token and the legacy file style (the tokenizer's tests read both).

The vocabulary follows CLIP's layout: the 256 byte-level symbols (ids 0-255, so "!" is id 0 as
in the real vocabulary), their `</w>` word-final forms (256-511), one token per merge, then
`<|startoftext|>` and `<|endoftext|>`. The merges come from a small greedy BPE training on a
fixed word list, so the RGB<->X prompt words and a few common words become single tokens.
"""

from __future__ import annotations

import json
from pathlib import Path

from jaxdistill.models.tokenizer import BOS, EOS

# lowercase words that get whole-word tokens (the MAP_PROMPTS words first)
WORDS = ("albedo", "diffuse", "basecolor", "camera", "space", "normal", "roughness", "metallicness",
         "irradiance", "lighting", "a", "an", "the", "of", "in", "on", "and", "with", "photo", "room",
         "wall", "floor", "bed", "wooden", "table", "lamp", "window", "light", "red", "blue", "it",
         "is", "isn", "don", "café", "'s", "'t", "'re", "'ll", "...", "!!")


def byte_symbols() -> list[str]:
    """The 256 byte-level symbols in CLIP's order: printable Latin-1 bytes map to themselves,
    the other bytes to code points 256, 257, ... in increasing byte order."""
    printable = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1),
                 *range(ord("®"), ord("ÿ") + 1)]
    others = [b for b in range(256) if b not in printable]
    return [chr(b) for b in printable] + [chr(256 + i) for i in range(len(others))]


def _byte_map() -> dict[int, str]:
    """Byte value -> its byte-level symbol."""
    printable = [ord(s) for s in byte_symbols()[:188]]
    others = [b for b in range(256) if b not in printable]
    return {**{b: chr(b) for b in printable}, **{b: chr(256 + i) for i, b in enumerate(others)}}


def _word_symbols(word: str) -> list[str]:
    """`word` as byte-level symbols, the last one with the `</w>` word end."""
    symbols = [_byte_map()[b] for b in word.encode("utf-8")]
    symbols[-1] += "</w>"
    return symbols


def word_token(word: str) -> str:
    """The vocabulary entry of a whole word: its byte-level symbols plus `</w>`."""
    return "".join(_word_symbols(word))


def _merge_pair(symbols: list[str], pair: tuple[str, str]) -> list[str]:
    """`symbols` with every (left-to-right, non-overlapping) occurrence of `pair` joined."""
    out, i = [], 0
    while i < len(symbols):
        if i + 1 < len(symbols) and (symbols[i], symbols[i + 1]) == pair:
            out.append(symbols[i] + symbols[i + 1])
            i += 2
        else:
            out.append(symbols[i])
            i += 1
    return out


def train_merges(words) -> list[tuple[str, str]]:
    """Greedy BPE training until every word is one token: each step merges the most frequent
    adjacent pair (ties: the smallest pair). Encoding a training word replays these merges, so
    every word in `words` becomes a single `</w>` token."""
    segmented = [_word_symbols(w) for w in words]
    merges: list[tuple[str, str]] = []
    while True:
        counts: dict[tuple[str, str], int] = {}
        for symbols in segmented:
            for pair in zip(symbols, symbols[1:]):
                counts[pair] = counts.get(pair, 0) + 1
        if not counts:
            return merges
        best = min(counts, key=lambda pair: (-counts[pair], pair))
        merges.append(best)
        segmented = [_merge_pair(symbols, best) for symbols in segmented]


def tiny_vocab_and_merges() -> tuple[dict[str, int], list[tuple[str, str]]]:
    """(token -> id, merges in rank order); deterministic."""
    symbols = byte_symbols()
    merges = train_merges(WORDS)
    tokens = symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges] + [BOS, EOS]
    vocab: dict[str, int] = {}
    for t in tokens:
        vocab.setdefault(t, len(vocab))
    return vocab, merges


def _special(content: str) -> dict:
    """A special token entry as legacy (transformers 4.x) Stable Diffusion folders store it."""
    return {"content": content, "lstrip": False, "normalized": True, "rstrip": False,
            "single_word": False}


def write_tiny_clip_tokenizer(folder, pad_token: str = "!", *, style: str = "legacy") -> Path:
    """Writes vocab.json, merges.txt, special_tokens_map.json and tokenizer_config.json to `folder`.

    `pad_token` "!" is Stable Diffusion 2.x's, "<|endoftext|>" SD 1.x's. `style` "legacy" writes
    the JSON files as the Stable Diffusion hub folders have them (transformers 4.x before
    `added_tokens_decoder`; the pad token is only right in special_tokens_map.json, as in SD 2.x),
    "modern" as transformers >= 4.34 `save_pretrained` writes them (with `added_tokens_decoder`,
    which makes transformers ignore special_tokens_map.json). Returns the folder.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    vocab, merges = tiny_vocab_and_merges()
    (folder / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False, indent=2) + "\n",
                                       encoding="utf-8")
    (folder / "merges.txt").write_text(
        "#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in merges), encoding="utf-8")
    if style == "legacy":
        special_map = {"bos_token": _special(BOS), "eos_token": _special(EOS), "pad_token": pad_token,
                       "unk_token": _special(EOS)}
        config = {"add_prefix_space": False, "bos_token": {"__type": "AddedToken", **_special(BOS)},
                  "do_lower_case": True, "eos_token": {"__type": "AddedToken", **_special(EOS)},
                  "errors": "replace", "model_max_length": 77, "name_or_path": "tiny-clip",
                  "pad_token": EOS, "special_tokens_map_file": "./special_tokens_map.json",
                  "tokenizer_class": "CLIPTokenizer",
                  "unk_token": {"__type": "AddedToken", **_special(EOS)}}
    elif style == "modern":
        decoder = {str(vocab[t]): {**_special(t), "normalized": False, "special": True}
                   for t in sorted({BOS, EOS, pad_token}, key=vocab.__getitem__)}
        special_map = {"bos_token": BOS, "eos_token": EOS, "pad_token": pad_token, "unk_token": EOS}
        config = {"add_prefix_space": False, "added_tokens_decoder": decoder, "bos_token": BOS,
                  "clean_up_tokenization_spaces": True, "do_lower_case": True, "eos_token": EOS,
                  "errors": "replace", "model_max_length": 77, "pad_token": pad_token,
                  "tokenizer_class": "CLIPTokenizer", "unk_token": EOS}
    else:
        raise ValueError(f"style must be 'legacy' or 'modern', got {style!r}")
    for name, data in (("special_tokens_map.json", special_map), ("tokenizer_config.json", config)):
        (folder / name).write_text(json.dumps(data, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return folder


def write_prior_tokenizer(folder) -> Path:
    """The tokenizer folder of our prior (pad "!", files as transformers >= 4.34 writes them): the
    one `scripts/train_rgbx.py` trains with and exports. Returns the folder."""
    return write_tiny_clip_tokenizer(folder, pad_token="!", style="modern")
