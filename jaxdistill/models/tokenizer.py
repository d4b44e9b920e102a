"""CLIP byte-level BPE tokenizer on the `tokenizers` library (no transformers at run time).

`load_tokenizer(folder)` reads a diffusers `tokenizer/` folder (vocab.json, merges.txt and the
optional special_tokens_map.json / tokenizer_config.json; or, as transformers 5's
`save_pretrained` writes it, tokenizer.json + tokenizer_config.json, where tokenizer.json is
loaded as it is by the `tokenizers` library) and returns a `ClipTokenizer` whose
`encode` gives the ids of transformers' `CLIPTokenizer(prompts, padding="max_length",
max_length=77, truncation=True)`: NFC, whitespace runs -> one space, lowercase, CLIP's split
regex, byte-level symbols, BPE with `</w>` word ends, `<|startoftext|> ... <|endoftext|>`, then
right-truncation (the end token stays last) and right-padding with the folder's pad token
("!" = id 0 for Stable Diffusion 2.x, "<|endoftext|>" for 1.x).

As in transformers, the special tokens (bos, eos, unk, pad) are also matched literally inside
prompt text; with pad "!" every "!" in a prompt therefore becomes id 0, not the word-final "!</w>".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tokenizers import AddedToken, Regex, Tokenizer, normalizers, pre_tokenizers, processors
from tokenizers.models import BPE

from jaxdistill.errors import InputError, read_json

BOS = "<|startoftext|>"
EOS = "<|endoftext|>"
WORD_END = "</w>"
DEFAULT_MAX_LENGTH = 77
TOKENIZER_JSON = "tokenizer.json"   # the `tokenizers` library's own file (transformers 5 writes only it)

# CLIP's word split: the two special tokens, English contractions, letter runs, single digits,
# runs of other non-space characters (applied to lowercased text).
_SPLIT = (r"<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d"
          r"|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+")
# special-token fields in the order transformers registers them (a later duplicate's flags win)
_SPECIAL_FIELDS = ("bos_token", "eos_token", "unk_token", "sep_token", "pad_token", "cls_token",
                   "mask_token")
_DEFAULT_SPECIALS = {"bos_token": BOS, "eos_token": EOS, "unk_token": EOS, "pad_token": EOS}
_FLAGS = ("lstrip", "rstrip", "single_word", "normalized")

# The RGB<->X prompts that select which intrinsic map the RGB->X model predicts.
MAP_PROMPTS: dict[str, str] = {
    "albedo": "Albedo (diffuse basecolor)",
    "normal": "Camera-space Normal",
    "roughness": "Roughness",
    "metallic": "Metallicness",
    "irradiance": "Irradiance (diffuse lighting)",
}


@dataclasses.dataclass(frozen=True)
class ClipTokenizer:
    """A loaded CLIP tokenizer; `encode` pads and truncates to `max_length`."""

    backend: Tokenizer  # normaliser, pre-tokeniser, BPE, bos/eos template, truncation, padding
    max_length: int
    bos_id: int
    eos_id: int
    pad_id: int
    pad_token: str
    folder: str

    def encode(self, prompts: Sequence[str]) -> np.ndarray:
        """(N, max_length) int32 ids for N prompts: bos, tokens, eos, then pad ids."""
        if isinstance(prompts, str) or not all(isinstance(p, str) for p in prompts):
            raise TypeError("encode expects a sequence of strings (wrap a single prompt in a list)")
        ids = [e.ids for e in self.backend.encode_batch(list(prompts))]
        return np.asarray(ids, np.int32).reshape(len(ids), self.max_length)


# ----------------------------------------------------------------------------- file reading


def _read_json(path: Path, required: bool):
    """The parsed JSON file, or None when an optional file is absent; InputError if unreadable."""
    if not path.is_file() and not required:
        return None
    return read_json(path, f"missing: a CLIP tokenizer folder needs vocab.json and merges.txt, or {TOKENIZER_JSON} "
                     "(copy the model's tokenizer/ folder completely)")


def _read_vocab(path: Path) -> dict[str, int]:
    """vocab.json as {token: id}; InputError unless it maps strings to distinct ids >= 0."""
    vocab = _read_json(path, required=True)
    if not isinstance(vocab, dict) or not vocab:
        raise InputError.single(path, "(root)", "must be a non-empty JSON object {token: id}")
    bad = [k for k, v in vocab.items() if isinstance(v, bool) or not isinstance(v, int) or v < 0]
    if bad:
        raise InputError.single(path, repr(bad[0]), "ids must be integers >= 0")
    if len(set(vocab.values())) != len(vocab):
        raise InputError.single(path, "(root)", "two tokens share one id")
    return vocab


def _read_merges(path: Path, vocab: dict[str, int]) -> list[tuple[str, str]]:
    """merges.txt as (left, right) pairs in rank order; InputError naming a bad line."""
    if not path.is_file():
        raise InputError.single(path, "(file)", "missing: a CLIP tokenizer folder needs merges.txt "
                                "(copy the model's tokenizer/ folder completely)")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError.single(path, "(file)", f"not readable UTF-8 text ({err})") from err
    merges = []
    for number, line in enumerate(lines, start=1):
        if line.startswith("#version") or (not line and number == len(lines)):
            continue
        parts = line.split(" ")
        if len(parts) != 2 or not all(parts):
            raise InputError.single(path, f"line {number}", f"expected two tokens separated by one "
                                    f"space, got {line!r}")
        missing = [t for t in (*parts, "".join(parts)) if t not in vocab]
        if missing:
            raise InputError.single(path, f"line {number}", f"token {missing[0]!r} is not in "
                                    f"vocab.json (vocab.json and merges.txt must match)")
        merges.append((parts[0], parts[1]))
    return merges


def _added_token(value, file: Path, field: str, *, from_map: bool) -> AddedToken:
    """A special token entry (string or {content, lstrip, ...}) as transformers reads it.

    Strings and special_tokens_map.json entries default to normalized=False, tokenizer_config.json
    entries ({"__type": "AddedToken", ...}) to normalized=True.
    """
    if isinstance(value, str) and value:
        return AddedToken(value, special=True)
    if not (isinstance(value, dict) and isinstance(value.get("content"), str) and value["content"]):
        raise InputError.single(file, field, f"expected a token string or an object with a "
                                f"non-empty 'content', got {value!r}")
    flags = {k: value[k] for k in _FLAGS if k in value}
    bad = [k for k, v in flags.items() if not isinstance(v, bool)]
    if bad:
        raise InputError.single(file, f"{field}.{bad[0]}", "must be true or false")
    flags.setdefault("normalized", not from_map)
    return AddedToken(value["content"], special=True, **flags)


def _special_tokens(folder: Path, config: dict,
                    special_map: dict | None) -> dict[str, tuple[AddedToken, Path]]:
    """{field: (token, file it came from)} for the special tokens, with transformers' precedence.

    With `added_tokens_decoder` in tokenizer_config.json (transformers >= 4.34) the config
    decides and special_tokens_map.json is ignored; otherwise (older folders, e.g. Stable
    Diffusion 2.x, whose config says pad "<|endoftext|>" but whose map says "!") the map's
    entries override the config's.
    """
    config_file, map_file = folder / "tokenizer_config.json", folder / "special_tokens_map.json"
    for file, data in ((config_file, config), (map_file, special_map or {})):
        if data.get("additional_special_tokens") or data.get("extra_special_tokens"):
            raise InputError.single(file, "additional_special_tokens", "extra special tokens are not "
                                    "supported by this CLIP tokenizer; remove them")
    tokens = {f: (AddedToken(v, special=True), config_file) for f, v in _DEFAULT_SPECIALS.items()}
    tokens |= {f: (_added_token(config[f], config_file, f, from_map=False), config_file)
               for f in _SPECIAL_FIELDS if config.get(f) is not None}
    if "added_tokens_decoder" not in config and special_map is not None:
        tokens |= {f: (_added_token(special_map[f], map_file, f, from_map=True), map_file)
                   for f in _SPECIAL_FIELDS if special_map.get(f) is not None}
    return {f: tokens[f] for f in _SPECIAL_FIELDS if f in tokens}


def _decoder_tokens(config_file: Path, config: dict, vocab: dict[str, int]) -> list[AddedToken]:
    """The `added_tokens_decoder` entries of tokenizer_config.json in id order (all in vocab)."""
    decoder = config.get("added_tokens_decoder") or {}
    if not isinstance(decoder, dict):
        raise InputError.single(config_file, "added_tokens_decoder", "must be an object {id: token}")
    tokens = []
    for key in sorted(decoder, key=lambda k: int(k) if str(k).isdigit() else -1):
        field = f"added_tokens_decoder.{key}"
        if not isinstance(decoder[key], dict):
            raise InputError.single(config_file, field, "must be an object with 'content'")
        token = _added_token(decoder[key], config_file, field, from_map=True)
        if vocab.get(token.content) != (int(key) if str(key).isdigit() else None):
            raise InputError.single(config_file, field, f"{token.content!r} must be in vocab.json with "
                                    f"id {key}; tokens added beyond vocab.json are not supported")
        tokens.append(AddedToken(token.content, special=bool(decoder[key].get("special", True)),
                                 **{k: getattr(token, k) for k in _FLAGS}))
    return tokens


def _max_length(config_file: Path, config: dict) -> int:
    """`model_max_length` from tokenizer_config.json (77 when absent)."""
    value = config.get("model_max_length", DEFAULT_MAX_LENGTH)
    if isinstance(value, bool) or not isinstance(value, int) or not 3 <= value <= 4096:
        raise InputError.single(config_file, "model_max_length", f"must be an integer in [3, 4096] "
                                f"(77 for CLIP), got {value!r}")
    return value


# ----------------------------------------------------------------------------- assembly


def _backend(vocab: dict[str, int], merges: list[tuple[str, str]], unk: str) -> Tokenizer:
    """The BPE model with CLIP's normaliser and pre-tokeniser (no special tokens yet)."""
    tok = Tokenizer(BPE(vocab=vocab, merges=merges, unk_token=unk, continuing_subword_prefix="",
                        end_of_word_suffix=WORD_END, fuse_unk=False, dropout=None))
    tok.normalizer = normalizers.Sequence(
        [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()])
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [pre_tokenizers.Split(Regex(_SPLIT), behavior="removed", invert=True),
         pre_tokenizers.ByteLevel(add_prefix_space=False)])  # also splits with GPT-2's regex
    return tok


def load_tokenizer(folder, max_length: int | None = None) -> ClipTokenizer:
    """Loads a diffusers `tokenizer/` folder; `max_length` overrides `model_max_length` (77).

    vocab.json + merges.txt when the folder has them, else tokenizer.json (transformers 5)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError.single(folder, "(folder)", "tokenizer folder not found (expected the "
                                "model's tokenizer/ subfolder with vocab.json and merges.txt, or tokenizer.json)")
    config_file = folder / "tokenizer_config.json"
    config = _read_json(config_file, required=False) or {}
    special_map = _read_json(folder / "special_tokens_map.json", required=False)
    for file, data in ((config_file, config), (folder / "special_tokens_map.json", special_map)):
        if data is not None and not isinstance(data, dict):
            raise InputError.single(file, "(root)", "must be a JSON object")
    length = _max_length(config_file, config) if max_length is None else int(max_length)
    if length < 3:
        raise ValueError(f"max_length must be >= 3, got {max_length}")
    has_pair = (folder / "vocab.json").is_file() or (folder / "merges.txt").is_file()
    if not has_pair and (folder / TOKENIZER_JSON).is_file():
        tok, vocab, vocab_file = _backend_from_json(folder / TOKENIZER_JSON)
        specials = _special_tokens(folder, config, special_map)
        _check_specials(specials, vocab, vocab_file)
    else:
        vocab = _read_vocab(folder / "vocab.json")
        merges = _read_merges(folder / "merges.txt", vocab)
        specials = _special_tokens(folder, config, special_map)
        _check_specials(specials, vocab, "vocab.json")
        tok = _backend(vocab, merges, specials["unk_token"][0].content)
        decoder_tokens = _decoder_tokens(config_file, config, vocab)
        named = [t for t, _ in specials.values() if t.content not in {d.content for d in decoder_tokens}]
        tok.add_tokens(decoder_tokens + named)  # literal matches in text; a later duplicate's flags win
    bos, eos, pad = (specials[f][0].content for f in ("bos_token", "eos_token", "pad_token"))
    tok.post_processor = processors.TemplateProcessing(
        single=f"{bos}:0 $A:0 {eos}:0", special_tokens=[(bos, vocab[bos]), (eos, vocab[eos])])
    tok.enable_truncation(max_length=length, direction="right")
    tok.enable_padding(direction="right", pad_id=vocab[pad], pad_token=pad, length=length)
    return ClipTokenizer(backend=tok, max_length=length, bos_id=vocab[bos], eos_id=vocab[eos],
                         pad_id=vocab[pad], pad_token=pad, folder=str(folder))


def _check_specials(specials: dict[str, tuple[AddedToken, Path]], vocab: dict[str, int], vocab_name: str) -> None:
    """InputError naming the file and field of a special token that is not in the vocabulary."""
    for field, (token, file) in specials.items():
        if token.content not in vocab:
            raise InputError.single(file, field, f"{token.content!r} is not in {vocab_name}; use a "
                                    f"token of the vocabulary (Stable Diffusion uses '!' or "
                                    f"'<|endoftext|>')")


def _backend_from_json(path: Path) -> tuple[Tokenizer, dict[str, int], str]:
    """(tokenizer as the `tokenizers` library loads tokenizer.json, its vocabulary with added
    tokens, a name for messages); InputError unless it is a byte-level BPE tokenizer."""
    try:
        tok = Tokenizer.from_file(str(path))
    except Exception as err:  # the Rust library raises plain Exception for any malformed file
        raise InputError.single(path, "(file)", f"the tokenizers library cannot read it ({err}); copy the "
                                "model's tokenizer/ folder again") from None
    if not isinstance(tok.model, BPE):
        raise InputError.single(path, "model.type", f"expected a CLIP BPE tokenizer, got "
                                f"{type(tok.model).__name__}")
    return tok, tok.get_vocab(with_added_tokens=True), path.name
