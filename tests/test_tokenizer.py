"""CLIP tokenizer: ids identical to transformers' CLIPTokenizer, clear errors for bad folders."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdistill.errors import InputError
from jaxdistill.models.tokenizer import BOS, EOS, MAP_PROMPTS, load_tokenizer
from jaxdistill.models import shipped
from jaxdistill.models.training.vocabulary import (WORDS, tiny_vocab_and_merges, word_token, write_prior_tokenizer,
                                                     write_tiny_clip_tokenizer)

PROMPTS = [
    *MAP_PROMPTS.values(),
    "",
    "a photo of the room with a wooden table " * 12,  # far beyond 77 tokens
    "a " * 75, "a " * 76,  # exactly fills 77 with bos/eos; one token too many
    "ALBEDO Of The ROOM",
    "hello, world! (yes)... ?!? a-b_c;d",
    "room 12345 and 3.14",
    "a   room\n\nwith\t lamp  \r\n",
    "café Ångström naïve ß ﬁ e\u0301te\u0301",
    "it's the bed, isn't it? they're here, we'll go",
    "<|endoftext|> a <|ENDOFTEXT|> <|startoftext|>b<|StartOfText|>",
    "!!! wow!",
    "日本語 😀",
]
CASES = [(pad, style) for pad in ("!", EOS) for style in ("legacy", "modern")]


@pytest.fixture(scope="module", params=CASES, ids=lambda c: f"pad{c[0]!r}-{c[1]}")
def folder(request, tmp_path_factory):
    pad, style = request.param
    return write_tiny_clip_tokenizer(tmp_path_factory.mktemp("tok"), pad, style=style)


def test_ids_equal_transformers(folder):
    transformers = pytest.importorskip("transformers")
    ref = transformers.CLIPTokenizer.from_pretrained(str(folder))(
        PROMPTS, padding="max_length", max_length=77, truncation=True)["input_ids"]
    ids = load_tokenizer(folder).encode(PROMPTS)
    assert ids.dtype == np.int32 and ids.shape == (len(PROMPTS), 77)
    for prompt, want, got in zip(PROMPTS, ref, ids):
        assert got.tolist() == list(want), prompt


def test_pad_token_from_folder(tmp_path):
    vocab, _ = tiny_vocab_and_merges()
    sd2 = load_tokenizer(write_tiny_clip_tokenizer(tmp_path / "sd2", "!"))
    sd1 = load_tokenizer(write_tiny_clip_tokenizer(tmp_path / "sd1", EOS))
    assert (sd2.pad_id, sd1.pad_id, sd2.max_length) == (vocab["!"], vocab[EOS], 77)
    a, b = sd2.encode(["albedo"])[0], sd1.encode(["albedo"])[0]
    assert a[:3].tolist() == b[:3].tolist() == [vocab[BOS], vocab["albedo</w>"], vocab[EOS]]
    assert (a[3:] == vocab["!"]).all() and (b[3:] == vocab[EOS]).all()


def test_tiny_vocab_words_are_whole_tokens(folder):
    """The helper's vocabulary makes each listed word (prompt words included) one token."""
    tok = load_tokenizer(folder)
    vocab, _ = tiny_vocab_and_merges()
    words = [w for w in WORDS if "!" not in w]  # with pad "!" each "!" is the pad token itself
    want = [[tok.bos_id, vocab[word_token(w)], tok.eos_id] for w in words]
    assert tok.encode(words)[:, :3].tolist() == want


def test_the_builder_writes_the_shipped_tokenizer_byte_for_byte(tmp_path):
    """The shipped model stays reproducible by scripts/train_rgbx.py: its tokenizer folder is what
    the vocabulary builder writes, file for file and byte for byte."""
    folder = shipped.shipped_folder()
    assert folder is not None, "the package must ship jaxdistill/models/rgbx_rooms"
    built = write_prior_tokenizer(tmp_path / "tokenizer")
    names = sorted(p.name for p in (folder / "tokenizer").iterdir())
    assert names == sorted(p.name for p in built.iterdir())
    for name in names:
        assert (built / name).read_bytes() == (folder / "tokenizer" / name).read_bytes(), name


def test_truncation_keeps_eos_last(folder):
    tok = load_tokenizer(folder)
    ids = tok.encode(["room " * 100])[0]
    assert ids[0] == tok.bos_id and ids[-1] == tok.eos_id and len(ids) == 77


def test_encode_rejects_a_bare_string(folder):
    with pytest.raises(TypeError, match="sequence of strings"):
        load_tokenizer(folder).encode("albedo")
    assert load_tokenizer(folder).encode([]).shape == (0, 77)


@pytest.mark.parametrize("pad", ["!", EOS])
@pytest.mark.parametrize("kind", ["CLIPTokenizer", "CLIPTokenizerFast"])
def test_folder_saved_by_the_installed_transformers(tmp_path, kind, pad):
    """save_pretrained of transformers 5 writes tokenizer.json + tokenizer_config.json only; we read
    tokenizer.json and give transformers' own ids for the saved folder."""
    transformers = pytest.importorskip("transformers")
    cls = getattr(transformers, kind)
    cls.from_pretrained(str(write_tiny_clip_tokenizer(tmp_path / "src", pad))).save_pretrained(tmp_path / "saved")
    saved = tmp_path / "saved"
    for legacy in ("vocab.json", "merges.txt"):      # older transformers also write these: test tokenizer.json
        (saved / legacy).unlink(missing_ok=True)
    assert (saved / "tokenizer.json").is_file()
    ref = cls.from_pretrained(str(saved))(PROMPTS, padding="max_length", max_length=77, truncation=True)["input_ids"]
    tok = load_tokenizer(saved)
    ids = tok.encode(PROMPTS)
    assert ids.shape == (len(PROMPTS), 77) and tok.pad_token == pad
    for prompt, want, got in zip(PROMPTS, ref, ids):
        assert got.tolist() == list(want), prompt
    np.testing.assert_array_equal(ids, load_tokenizer(tmp_path / "src").encode(PROMPTS))   # same as vocab.json


def test_bad_tokenizer_json_is_named(tmp_path):
    transformers = pytest.importorskip("transformers")
    saved = tmp_path / "saved"
    transformers.CLIPTokenizerFast.from_pretrained(str(write_tiny_clip_tokenizer(tmp_path / "src"))).save_pretrained(saved)
    for legacy in ("vocab.json", "merges.txt"):
        (saved / legacy).unlink(missing_ok=True)
    doc = json.loads((saved / "tokenizer.json").read_text())
    (saved / "tokenizer.json").write_text(json.dumps(doc)[:200])
    with pytest.raises(InputError, match=r"tokenizer\.json: \(file\): the tokenizers library cannot read it"):
        load_tokenizer(saved)
    doc["model"] = {"type": "WordLevel", "vocab": {"a": 0, "!": 1}, "unk_token": "a"}
    (saved / "tokenizer.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"tokenizer\.json: model\.type: expected a CLIP BPE tokenizer"):
        load_tokenizer(saved)
    (saved / "tokenizer.json").unlink()
    with pytest.raises(InputError, match=r"vocab\.json: \(file\): missing: .*or tokenizer\.json"):
        load_tokenizer(saved)


# ----------------------------------------------------------------------------- errors


@pytest.fixture
def tiny(tmp_path):
    return write_tiny_clip_tokenizer(tmp_path / "tokenizer")


@pytest.mark.parametrize("name", ["merges.txt", "vocab.json"])
def test_missing_file_is_named(tiny, name):
    (tiny / name).unlink()
    with pytest.raises(InputError, match=name) as err:
        load_tokenizer(tiny)
    assert "missing" in str(err.value)


def test_missing_folder(tmp_path):
    with pytest.raises(InputError, match="tokenizer folder not found"):
        load_tokenizer(tmp_path / "nope")


def test_unreadable_json_is_named(tiny):
    (tiny / "tokenizer_config.json").write_text("{not json", encoding="utf-8")
    with pytest.raises(InputError, match="tokenizer_config.json.*not valid JSON"):
        load_tokenizer(tiny)


def test_optional_config_files(tiny):
    """Without the JSON files the CLIPTokenizer defaults apply: pad = <|endoftext|>, 77."""
    (tiny / "tokenizer_config.json").unlink()
    (tiny / "special_tokens_map.json").unlink()
    tok = load_tokenizer(tiny)
    assert tok.pad_token == EOS and tok.max_length == 77


def test_pad_token_not_in_vocab(tiny):
    data = json.loads((tiny / "special_tokens_map.json").read_text())
    data["pad_token"] = "<pad>"
    (tiny / "special_tokens_map.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"special_tokens_map.json: pad_token: '<pad>' is not in vocab"):
        load_tokenizer(tiny)


def test_merge_outside_vocab_names_line(tiny):
    with open(tiny / "merges.txt", "a", encoding="utf-8") as f:
        f.write("zz q\n")
    with pytest.raises(InputError, match=r"merges.txt: line \d+: token 'zz' is not in vocab.json"):
        load_tokenizer(tiny)


def test_malformed_merge_line(tiny):
    (tiny / "merges.txt").write_text("#version: 0.2\na b c\n", encoding="utf-8")
    with pytest.raises(InputError, match="line 2: expected two tokens"):
        load_tokenizer(tiny)


def test_bad_model_max_length(tiny):
    data = json.loads((tiny / "tokenizer_config.json").read_text())
    data["model_max_length"] = "77"
    (tiny / "tokenizer_config.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match="tokenizer_config.json: model_max_length"):
        load_tokenizer(tiny)
