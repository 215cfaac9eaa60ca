"""Text-feature cache and `segmo encode-texts`, with the packaged MiniLM encoder."""

from __future__ import annotations

import copy
import pickle
from pathlib import Path

import pytest
import torch

from segmo.errors import SegmoError
from segmo.text.cache import TextFeatureCache, main, normalise_text, update_cache
from segmo.text.encoders import get_text_encoder

CAPTIONS = {
    "000": ["a person walks forward#a/DET person/NOUN walk/VERB#0.0#0.0",
            "someone  waves with the left hand #someone/PRON#0.0#0.0"],
    "001": ["a man jumps twice then sits down#a/DET#0.0#0.0",
            "a person walks forward#a/DET#1.0#2.5"],  # duplicate caption, time-tagged
}
SEGMENTS = {
    "000": ["a person walks forward", "someone waves with the left hand"],
    "001": ["a man jumps twice#sits down", "a person walks forward"],
}
DISTINCT = ["a person walks forward", "someone waves with the left hand",
            "a man jumps twice then sits down", "a man jumps twice", "sits down"]


def make_dataset(root: Path) -> Path:
    (root / "texts").mkdir(parents=True)
    (root / "text_segments" / "rule").mkdir(parents=True)
    for mid, lines in CAPTIONS.items():
        (root / "texts" / f"{mid}.txt").write_text("\n".join(lines) + "\n")
        (root / "text_segments" / "rule" / f"{mid}.txt").write_text("\n".join(SEGMENTS[mid]))
    return root


class Counter:
    """Wraps an encoder's `encode`, counting the texts it is asked to encode."""

    def __init__(self, encoder, fail_on_call: int | None = None):
        self.encoder, self.texts, self.calls, self.fail_on_call = encoder, 0, 0, fail_on_call

    def __call__(self, texts, batch_size=64):
        self.calls += 1
        if self.calls == self.fail_on_call:
            raise RuntimeError("simulated crash")
        self.texts += len(texts)
        return self.encoder.encode(texts, batch_size=batch_size)


def counted(encoder, **kwargs):
    wrapped = copy.copy(encoder)  # same model, own `encode` attribute
    wrapped.encode = Counter(encoder, **kwargs)
    return wrapped, wrapped.encode


@pytest.fixture(scope="module")
def minilm():
    return get_text_encoder("minilm")


@pytest.fixture
def built(tmp_path, minilm):
    root = make_dataset(tmp_path / "data")
    summary = update_cache(root, minilm, progress=False)
    return root, summary


def test_build_and_lookups_match_direct_encoding(built, minilm):
    root, summary = built
    assert (summary.total, summary.new, summary.reused) == (5, 5, 0)
    assert summary.bytes_on_disk > 5 * 384 * 2
    cache = TextFeatureCache.open(root, "minilm")
    assert len(cache) == 5 and cache.dim == 384
    assert all(t in cache for t in DISTINCT) and "a person walks backward" not in cache
    assert " someone waves  with the left hand" in cache  # whitespace-normalised keys
    direct = minilm.encode(DISTINCT)
    got = cache.sentence(DISTINCT)
    assert got.dtype == torch.float32 and got.shape == (5, 384)
    torch.testing.assert_close(got, direct.sentence, atol=2e-3, rtol=0)  # float16 storage
    assert torch.nn.functional.cosine_similarity(got, direct.sentence).min() > 0.9999
    for i in (0, 1, 2):  # captions keep their token features
        tokens = cache.tokens(DISTINCT[i])
        ref = direct.tokens[i][direct.token_mask[i]]
        assert tokens.shape == ref.shape
        torch.testing.assert_close(tokens, ref, atol=1e-2, rtol=1e-2)


def test_missing_text_raises_key_error_naming_it(built):
    cache = TextFeatureCache.open(built[0], "minilm")
    with pytest.raises(KeyError, match="a person walks backward"):
        cache.sentence(["a person walks forward", "a person walks backward"])
    with pytest.raises(KeyError, match="segment only"):
        cache.tokens("sits down")


def test_rerun_encodes_nothing(built, minilm):
    root, _ = built
    wrapped, counter = counted(minilm)
    summary = update_cache(root, wrapped, progress=False)
    assert (summary.total, summary.new, summary.reused) == (5, 0, 5)
    assert counter.calls == 0


def test_new_caption_encodes_exactly_it(built, minilm):
    root, _ = built
    (root / "texts" / "002.txt").write_text("a person crawls on the floor#x#0#0\n"
                                            "a man jumps twice then sits down#x#0#0\n")
    wrapped, counter = counted(minilm)
    summary = update_cache(root, wrapped, progress=False)
    assert (summary.new, counter.texts) == (1, 1)
    cache = TextFeatureCache.open(root, "minilm")
    assert len(cache) == 6 and cache.tokens("a person crawls on the floor").shape[1] == 384
    torch.testing.assert_close(cache.sentence(["a person crawls on the floor"]),
                               minilm.encode(["a person crawls on the floor"]).sentence,
                               atol=2e-3, rtol=0)


def test_segment_becoming_a_caption_gains_tokens(built, minilm):
    root, _ = built
    (root / "texts" / "003.txt").write_text("sits down#x#0#0\n")
    summary = update_cache(root, minilm, progress=False)
    cache = TextFeatureCache.open(root, "minilm")
    assert summary.new == 1 and len(cache) == 5 and cache.has_tokens("sits down")
    assert cache.tokens("sits down").shape == (4, 384)  # [CLS] sits down [SEP]


def test_crash_mid_run_leaves_a_valid_cache(tmp_path, minilm):
    root = make_dataset(tmp_path / "data")
    wrapped, _ = counted(minilm, fail_on_call=2)
    with pytest.raises(RuntimeError, match="simulated crash"):
        update_cache(root, wrapped, shard_size=2, progress=False)
    cache = TextFeatureCache.open(root, "minilm")
    assert len(cache) == 2  # the first shard was committed, the second never was
    (cache.folder / "shard-00001.sentence.npy").write_bytes(b"half-written garbage")
    wrapped, counter = counted(minilm)
    summary = update_cache(root, wrapped, shard_size=2, progress=False)
    assert (summary.new, counter.texts) == (3, 3)
    cache = TextFeatureCache.open(root, "minilm")
    assert len(cache) == 5 and cache.sentence(DISTINCT).shape == (5, 384)


def test_open_missing_cache_names_folder_and_command(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"text_features/minilm.*segmo encode-texts"):
        TextFeatureCache.open(tmp_path, "minilm")


def test_cache_pickles_for_dataloader_workers(built):
    cache = TextFeatureCache.open(built[0], "minilm")
    clone = pickle.loads(pickle.dumps(cache))
    assert torch.equal(clone.sentence(DISTINCT), cache.sentence(DISTINCT))


def test_normalise_text():
    assert normalise_text("  a  person\twalks\n") == "a person walks"


def test_command_summary_and_errors(tmp_path, capsys):
    root = make_dataset(tmp_path / "data")
    main(["--data", str(root), "--encoder", "minilm", "--segments", "rule"])
    out = capsys.readouterr().out
    assert "5 distinct texts, 5 new, 0 reused" in out and "MiB on disk" in out
    main(["--data", str(root)])
    assert "0 new, 5 reused" in capsys.readouterr().out
    with pytest.raises(SegmoError, match=r"--data .*nowhere: no such folder"):
        main(["--data", str(tmp_path / "nowhere")])
    with pytest.raises(SegmoError, match=r"--segments llm: no text-segment folder .*text_segments/llm.*present: rule"):
        main(["--data", str(root), "--segments", "llm"])


def test_features_of_another_encoder_of_the_same_name_are_refused(tmp_path, capsys):
    """Two encoder directories both called "model": encode-texts with the second reused the
    first one's features ("0 new, 9 reused"), and training read them as its own."""
    from test_text_encoders import make_tiny_clip

    root = make_dataset(tmp_path / "data")
    first, second = (tmp_path / "a" / "model", tmp_path / "b" / "model")
    first.mkdir(parents=True)
    second.mkdir(parents=True)
    make_tiny_clip(first)
    make_tiny_clip(second, full_clip=True)  # other weights, the same kind and width
    main(["--data", str(root), "--encoder", str(first), "--quiet"])
    with pytest.raises(SegmoError, match=r"text_features/model: its features were encoded by "
                                         r"another 'model' encoder than .*b/model"):
        main(["--data", str(root), "--encoder", str(second), "--quiet"])
    with pytest.raises(SegmoError, match="the weights differ"):
        TextFeatureCache.open(root, str(second))
    assert len(TextFeatureCache.open(root, str(first))) == len(DISTINCT)
    assert TextFeatureCache.open(root, str(first)).meta["identity"] is not None


def test_an_encoder_identity_sees_a_change_in_the_middle_of_the_weights(tmp_path):
    """It read the first and last MiB of each weight file: one tensor in the middle of
    MiniLM's 90 MB scaled by 1.5 gave the same identity, and the cache was reused."""
    import shutil

    from segmo.text.encoders import encoder_identity, encoder_source

    copy = shutil.copytree(encoder_source("minilm"), tmp_path / "model")
    weights = copy / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one byte of one tensor, the size unchanged
    weights.write_bytes(bytes(data))
    assert encoder_identity(copy) != encoder_identity(encoder_source("minilm"))


def test_a_hub_name_whose_weights_changed_is_refused(tmp_path, hub_cache, capsys):
    """A hub name's cache recorded no identity (the name is no folder to hash), so after the
    hub's main moved to other weights encode-texts said "0 new, 5 reused" and training read
    the old weights' features."""
    from test_text_encoders import fake_hub_cache, make_tiny_clip

    root = make_dataset(tmp_path / "data")
    make_tiny_clip(fake_hub_cache(hub_cache, "someone/tiny-clip", "a" * 40))
    main(["--data", str(root), "--encoder", "someone/tiny-clip", "--quiet"])
    assert TextFeatureCache.open(root, "someone/tiny-clip").meta["identity"] is not None
    make_tiny_clip(fake_hub_cache(hub_cache, "someone/tiny-clip", "b" * 40), full_clip=True)
    with pytest.raises(SegmoError, match="the weights differ"):
        main(["--data", str(root), "--encoder", "someone/tiny-clip", "--quiet"])
    with pytest.raises(SegmoError, match="the weights differ"):
        TextFeatureCache.open(root, "someone/tiny-clip")


def test_features_cut_at_another_length_are_refused(tmp_path):
    """sentence_bert_config.json's max_seq_length changed: encode-texts reused features cut
    at the old length, which the live encoder no longer gives (cosine 0.85-0.9)."""
    from test_text_encoders import make_tiny_roberta

    root = make_dataset(tmp_path / "data")
    model = tmp_path / "model"
    model.mkdir()
    make_tiny_roberta(model)
    main(["--data", str(root), "--encoder", str(model), "--quiet"])
    assert TextFeatureCache.open(root, str(model)).meta["max_length"] == 513
    (model / "sentence_bert_config.json").write_text('{"max_seq_length": 4}')
    with pytest.raises(SegmoError, match=r"text_features/model: its features were cut at 513 "
                                         r"tokens, the encoder .*model now cuts at 4"):
        main(["--data", str(root), "--encoder", str(model), "--quiet"])
    with pytest.raises(SegmoError, match="now cuts at 4"):
        TextFeatureCache.open(root, str(model))
    with pytest.raises(SegmoError, match="now cuts at 4"):
        update_cache(root, get_text_encoder(str(model)), progress=False)
