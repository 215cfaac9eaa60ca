"""Text encoders: a tiny random CLIP built offline, and the packaged all-MiniLM-L6-v2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from segmo.text.encoders import (
    ClipTextEncoder,
    MeanPoolTextEncoder,
    TextEncoding,
    encoder_folder_name,
    get_text_encoder,
)

TEXTS = [
    "a person walks forward",
    "someone waves with the left hand, then sits down on a chair",
    "jump",
    "a man does a cartwheel and then walks in a circle slowly",
    "the person crouches",
]


def _byte_symbols() -> list[str]:
    """The 256 printable symbols byte-level BPE uses for bytes (GPT-2 / CLIP mapping)."""
    keep = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) \
        + list(range(ord("®"), ord("ÿ") + 1))
    symbols, extra = [], 0
    for b in range(256):
        if b in keep:
            symbols.append(chr(b))
        else:
            symbols.append(chr(256 + extra))
            extra += 1
    return symbols


def make_tiny_clip(directory: Path, full_clip: bool = False) -> str:
    """Save a randomly initialised tiny CLIP (text tower + projection, or a whole CLIPModel)
    and a character-level CLIP tokenizer to `directory`; nothing is downloaded."""
    from transformers import (
        CLIPConfig,
        CLIPModel,
        CLIPTextConfig,
        CLIPTextModelWithProjection,
        CLIPTokenizer,
    )

    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for sym in _byte_symbols():
        vocab[sym] = len(vocab)
        vocab[sym + "</w>"] = len(vocab)
    merges = ["w a", "l k</w>", "wa lk</w>"]
    for merged in ("wa", "lk</w>", "walk</w>"):
        vocab[merged] = len(vocab)
    # vocab.json + merges.txt is the layout every transformers version reads
    (directory / "vocab.json").write_text(json.dumps(vocab))
    (directory / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n")
    tokenizer = CLIPTokenizer.from_pretrained(directory, model_max_length=77)
    text = dict(vocab_size=len(vocab), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                num_attention_heads=4, max_position_embeddings=77, projection_dim=24,
                bos_token_id=0, eos_token_id=1, pad_token_id=1)
    torch.manual_seed(0)  # tests only: the tiny model's random weights
    if full_clip:
        vision = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                      num_attention_heads=2, image_size=32, patch_size=16)
        model = CLIPModel(CLIPConfig(text_config=text, vision_config=vision, projection_dim=24))
    else:
        model = CLIPTextModelWithProjection(CLIPTextConfig(**text))
    model.save_pretrained(directory)
    tokenizer.save_pretrained(directory)
    return str(directory)


def make_tiny_roberta(directory: Path, tokenizer_max: int | None = None) -> str:
    """Save a randomly initialised one-layer RoBERTa (514 position rows, of which the first
    pad_token_id + 1 are never used: 513 usable with pad id 0) with MiniLM's word-piece
    tokenizer; tokenizer_config.json gives model_max_length `tokenizer_max` (None: none)."""
    from transformers import AutoTokenizer, RobertaConfig, RobertaModel

    from segmo.text.encoders import encoder_source

    tokenizer = AutoTokenizer.from_pretrained(encoder_source("minilm"))
    config = RobertaConfig(vocab_size=tokenizer.vocab_size, hidden_size=32, num_hidden_layers=1,
                           num_attention_heads=2, intermediate_size=64, type_vocab_size=1,
                           max_position_embeddings=514, pad_token_id=tokenizer.pad_token_id)
    torch.manual_seed(0)  # tests only: the tiny model's random weights
    RobertaModel(config).save_pretrained(directory)
    tokenizer.save_pretrained(directory)
    settings = json.loads((directory / "tokenizer_config.json").read_text())
    settings.pop("model_max_length", None)
    if tokenizer_max is not None:
        settings["model_max_length"] = tokenizer_max
    (directory / "tokenizer_config.json").write_text(json.dumps(settings))
    return str(directory)


def fake_hub_cache(cache: Path, repo: str, revision: str) -> Path:
    """The folder of `repo` at `revision` in a Hugging Face cache, as a download leaves it
    (refs/main names the snapshot); the caller saves the model files into it."""
    entry = cache / f"models--{repo.replace('/', '--')}"
    (entry / "refs").mkdir(parents=True, exist_ok=True)
    (entry / "refs" / "main").write_text(revision)
    folder = entry / "snapshots" / revision
    folder.mkdir(parents=True)
    return folder


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    return get_text_encoder(make_tiny_clip(tmp_path_factory.mktemp("tiny_clip")))


@pytest.fixture(scope="module")
def minilm():
    return get_text_encoder("minilm")


def test_clip_shapes_and_masks(tiny_clip):
    assert isinstance(tiny_clip, ClipTextEncoder) and tiny_clip.dim == 24
    out = tiny_clip.encode(TEXTS, batch_size=2)
    assert isinstance(out, TextEncoding)
    n, length, d = out.tokens.shape
    assert (n, d) == (len(TEXTS), 24) and out.sentence.shape == (n, 24)
    assert out.sentence.dtype == torch.float32 and out.token_mask.dtype == torch.bool
    lengths = out.token_mask.sum(1)
    # character-level tokens + start/end: the longest text sets the length, "jump" is 4 + 2
    assert length == int(lengths.max()) and int(lengths[2]) == 6
    assert torch.all(out.tokens[~out.token_mask] == 0)
    # the end-of-text token's projected feature is the sentence vector
    last = out.tokens[torch.arange(n), lengths - 1]
    torch.testing.assert_close(last, out.sentence, atol=1e-5, rtol=1e-5)


def test_a_float64_default_dtype_encodes_in_float32(tiny_clip):
    expected = tiny_clip.encode(TEXTS)
    torch.set_default_dtype(torch.float64)  # as scientific notebooks do
    try:
        out, empty = tiny_clip.encode(TEXTS), tiny_clip.encode([])
    finally:
        torch.set_default_dtype(torch.float32)
    assert torch.equal(out.sentence, expected.sentence) and torch.equal(out.tokens, expected.tokens)
    assert empty.sentence.dtype == empty.tokens.dtype == torch.float32


def test_clip_truncates_to_77_tokens(tiny_clip):
    out = tiny_clip.encode(["a" * 300, "b"])
    assert out.tokens.shape[1] == 77 and int(out.token_mask[0].sum()) == 77


def test_clip_deterministic_and_batch_size_invariant(tiny_clip):
    a = tiny_clip.encode(TEXTS, batch_size=1)
    b = tiny_clip.encode(TEXTS, batch_size=64)
    c = tiny_clip.encode(TEXTS, batch_size=64)
    assert torch.equal(b.sentence, c.sentence) and torch.equal(b.tokens, c.tokens)
    torch.testing.assert_close(a.sentence, b.sentence, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(a.tokens, b.tokens, atol=1e-5, rtol=1e-5)
    assert torch.equal(a.token_mask, b.token_mask)
    # order is preserved: encoding a permutation permutes the rows
    p = tiny_clip.encode(TEXTS[::-1], batch_size=3)
    torch.testing.assert_close(p.sentence, a.sentence.flip(0), atol=1e-5, rtol=1e-5)


def test_clip_from_full_checkpoint(tmp_path):
    """A whole CLIPModel directory (the layout of openai/clip-vit-base-patch32) loads its
    text tower and projection, giving the same features as CLIPModel.get_text_features."""
    from transformers import AutoTokenizer, CLIPModel

    path = make_tiny_clip(tmp_path, full_clip=True)
    enc = get_text_encoder(path)
    assert isinstance(enc, ClipTextEncoder)
    full = CLIPModel.from_pretrained(path).eval()
    inputs = AutoTokenizer.from_pretrained(path)(TEXTS[:2], padding=True, return_tensors="pt")
    with torch.no_grad():
        ref = full.get_text_features(**inputs)
    ref = ref if torch.is_tensor(ref) else ref.pooler_output
    torch.testing.assert_close(enc.encode(TEXTS[:2]).sentence, ref, atol=1e-5, rtol=1e-5)


def test_missing_hub_weights_error_is_clear(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(OSError, match="not available.*pass the directory"):
        get_text_encoder("someone/clip-model-that-is-not-cached")
    with pytest.raises(FileNotFoundError, match="not a model directory"):
        get_text_encoder("./no/such/dir")
    with pytest.raises(FileNotFoundError, match="no config.json"):
        get_text_encoder(str(tmp_path))


def test_folder_names(tmp_path):
    assert encoder_folder_name("minilm") == "minilm" and encoder_folder_name("clip") == "clip"
    assert encoder_folder_name("openai/clip-vit-base-patch32") == "openai--clip-vit-base-patch32"
    (tmp_path / "my model").mkdir()
    assert encoder_folder_name(str(tmp_path / "my model")) == "my_model"


def test_bad_arguments(tiny_clip):
    with pytest.raises(TypeError):
        tiny_clip.encode("a string, not a list")
    with pytest.raises(ValueError, match="batch_size"):
        tiny_clip.encode(TEXTS, batch_size=0)
    empty = tiny_clip.encode([])
    assert empty.sentence.shape == (0, 24)


def test_minilm_shapes_and_normalisation(minilm):
    assert isinstance(minilm, MeanPoolTextEncoder) and minilm.dim == 384
    out = minilm.encode(TEXTS, batch_size=2)
    assert out.sentence.shape == (5, 384) and out.tokens.shape[2] == 384
    torch.testing.assert_close(out.sentence.norm(dim=1), torch.ones(5))
    # sentence = normalised masked mean of the returned tokens
    mean = (out.tokens * out.token_mask[..., None]).sum(1) / out.token_mask.sum(1, keepdim=True)
    torch.testing.assert_close(torch.nn.functional.normalize(mean, dim=1), out.sentence,
                               atol=1e-5, rtol=1e-5)
    one = minilm.encode(TEXTS, batch_size=5)
    torch.testing.assert_close(one.sentence, out.sentence, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("anchor, paraphrase, unrelated", [
    ("a person walks forward", "someone is walking forwards", "a man does a cartwheel"),
    ("a man jumps up and down", "a person hops in place repeatedly", "someone sits on a chair"),
    ("the person waves with the right hand", "a man waves his right arm", "a person crawls on the floor"),
    ("someone runs in a circle", "a person jogs around in a circle", "the person picks up a box"),
])
def test_minilm_paraphrases_are_closer(minilm, anchor, paraphrase, unrelated):
    s = minilm.encode([anchor, paraphrase, unrelated]).sentence
    assert float(s[0] @ s[1]) > float(s[0] @ s[2]) + 0.1


def test_token_texts_name_each_token_feature(minilm, tiny_clip):
    texts = ["a person walks forward, then jumps twice", "someone waves"]
    pieces = minilm.token_texts(texts)
    assert pieces[1] == ["[CLS]", "someone", "waves", "[SEP]"]
    assert pieces[0][:4] == ["[CLS]", "a", "person", "walks"] and "," in pieces[0]
    for encoder in (minilm, tiny_clip):
        counts = encoder.encode(texts).token_mask.sum(1).tolist()
        assert [len(p) for p in encoder.token_texts(texts)] == counts  # one text per feature
    clip = tiny_clip.token_texts(["walks"])[0]
    assert len(clip) >= 3 and not any(p.endswith("</w>") for p in clip[1:-1])


def test_a_long_text_is_cut_to_the_positions_a_roberta_can_use(tmp_path):
    """RoBERTa's position ids start after its padding id: max_position_embeddings 514 holds
    512 (here 513) usable positions, and a text cut to 514 tokens raised IndexError."""
    encoder = get_text_encoder(make_tiny_roberta(tmp_path))
    assert encoder.max_length == 513
    out = encoder.encode(["a person walks forward " * 200, "jump"])
    assert out.token_mask.sum(1).tolist() == [513, 3]


def test_the_tokenizer_limit_counts_when_it_is_lower(tmp_path):
    assert get_text_encoder(make_tiny_roberta(tmp_path, tokenizer_max=100)).max_length == 100


def test_a_hub_name_truncates_like_its_folder(tmp_path, hub_cache):
    """sentence_bert_config.json was read for a folder only: by hub name the same model
    cut texts at 512 tokens, by folder at its max_seq_length."""
    folder = fake_hub_cache(hub_cache, "someone/tiny-roberta", "a" * 40)
    make_tiny_roberta(folder)
    (folder / "sentence_bert_config.json").write_text('{"max_seq_length": 64}')
    by_name = get_text_encoder("someone/tiny-roberta")
    assert by_name.max_length == get_text_encoder(str(folder)).max_length == 64
    assert by_name.encode(["a person walks forward " * 20]).token_mask.sum().item() == 64
