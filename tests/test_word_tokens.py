"""Word-level conditioning (`text_tokens: words`): the captions' per-word features as further
prefix keys; a model without them is exactly the model it was before."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from conftest import hash_encoder
from test_attention_recorder import tiny_models
from test_generation import TINY, text
from test_generator_tasks import REPO, overrides

from segmo.generation import SamplingOptions, generate_tokens
from segmo.models.attention_recorder import record_attention
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.pretrained import load_pretrained
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
from segmo.training.cli import main as cli_main


def inputs():
    sentence, segments, segment_mask = text(2)
    g = torch.Generator().manual_seed(3)
    indices = torch.randint(0, 16, (2, 10), generator=g)
    token_mask = torch.ones(2, 10, dtype=torch.bool)
    token_mask[1, 6:] = False
    return indices, token_mask, sentence, segments, segment_mask, g


def words(b: int = 2, length: int = 5, seed: int = 4):
    g = torch.Generator().manual_seed(seed)
    mask = torch.ones(b, length, dtype=torch.bool)
    mask[1, 3:] = False
    return torch.randn(b, length, TINY["text_dim"], generator=g), mask


# Logits of `tiny_models()` on `inputs()`, computed on main before word keys existed: a
# model without them must still compute these (float rounding aside).
MASK_LOGITS_ROW = [[3.8244898319244385, -2.9240610599517822, 4.126480579376221, 5.125144958496094, 1.6032657623291016],
                   [-0.3656159043312073, -5.4072794914245605, 3.8312976360321045, 4.483574867248535, -1.9620281457901]]
MASK_LOGITS_SUM, MASK_LOGITS_ABS = -87.66730514541268, 1595.9209885410964
RESIDUAL_LOGITS_ROW = [[-6.079143524169922, -3.6558046340942383, 8.553438186645508, -0.3893195688724518, 2.4926154613494873],
                       [0.3306374251842499, 6.679159164428711, 8.05394172668457, 3.3818130493164062, -3.147921323776245]]
RESIDUAL_LOGITS_SUM, RESIDUAL_LOGITS_ABS = 81.60692338785157, 1384.0146296904422


def test_a_model_without_word_keys_computes_what_it_computed_before():
    mask, residual = tiny_models()
    indices, token_mask, sentence, segments, segment_mask, _ = inputs()
    with torch.no_grad():
        logits = mask(indices, token_mask, sentence, segments, segment_mask).logits
        torch.testing.assert_close(logits[0, :2, :5], torch.tensor(MASK_LOGITS_ROW), atol=1e-4, rtol=1e-5)
        assert float(logits.double().sum()) == pytest.approx(MASK_LOGITS_SUM, abs=1e-2)
        assert float(logits.double().abs().sum()) == pytest.approx(MASK_LOGITS_ABS, rel=1e-5)
        codes = torch.randint(0, 16, (2, 10, 3), generator=torch.Generator().manual_seed(3))
        logits = residual(codes, 1, token_mask, sentence, segments, segment_mask).logits
        torch.testing.assert_close(logits[0, :2, :5], torch.tensor(RESIDUAL_LOGITS_ROW), atol=1e-4, rtol=1e-5)
        assert float(logits.double().sum()) == pytest.approx(RESIDUAL_LOGITS_SUM, abs=1e-2)
        assert float(logits.double().abs().sum()) == pytest.approx(RESIDUAL_LOGITS_ABS, rel=1e-5)
    assert not any("word" in name for name, _ in mask.named_parameters())
    # It ignores words it is given.
    with torch.no_grad():
        again = mask(indices, token_mask, sentence, segments, segment_mask, words=words()[0],
                     word_mask=words()[1]).logits
        assert torch.equal(again, mask(indices, token_mask, sentence, segments, segment_mask).logits)


def test_a_config_written_before_word_keys_loads_as_a_model_without_them(tmp_path):
    mask, _ = tiny_models()
    folder = mask.save_pretrained(tmp_path / "mask")
    payload = json.loads((folder / "config.json").read_text())
    assert payload["config"]["text_tokens"] == "none"
    payload["config"] = {k: v for k, v in payload["config"].items()
                         if k not in ("text_tokens", "max_words", "word_norm")}
    (folder / "config.json").write_text(json.dumps(payload))
    loaded = load_pretrained(folder)
    assert loaded.config.text_tokens == "none" and loaded.config.word_norm == "none"
    indices, token_mask, sentence, segments, segment_mask, _ = inputs()
    with torch.no_grad():
        torch.testing.assert_close(loaded.eval()(indices, token_mask, sentence, segments, segment_mask).logits,
                                   mask(indices, token_mask, sentence, segments, segment_mask).logits)


def word_models(word_attention: str = "prefix"):
    mask, residual = tiny_models(text_tokens="words", max_words=8, word_attention=word_attention)
    if word_attention == "cross":  # open the gates (0 at initialisation: words unread)
        for model in (mask, residual):
            for block in model.trunk.blocks:
                block.cross.gate.data.fill_(0.5)
    return mask, residual


@pytest.mark.parametrize("word_attention", ["prefix", "cross"])
def test_words_are_conditioning_and_padded_words_change_nothing(word_attention):
    mask, _ = word_models(word_attention)
    indices, token_mask, sentence, segments, segment_mask, _ = inputs()
    w, wm = words()
    with torch.no_grad():
        base = mask(indices, token_mask, sentence, segments, segment_mask, words=w, word_mask=wm).logits
        other = mask(indices, token_mask, sentence, segments, segment_mask, words=w.flip(1), word_mask=wm).logits
        assert (base - other).abs().max() > 1e-3  # the words are read
        padded = torch.cat([w, torch.full((2, 3, w.shape[2]), float("nan"))], dim=1)
        padded[1, 3:5] = 7.0  # padding inside the real length too
        pad_mask = torch.cat([wm, torch.zeros(2, 3, dtype=torch.bool)], dim=1)
        again = mask(indices, token_mask, sentence, segments, segment_mask, words=padded, word_mask=pad_mask).logits
        torch.testing.assert_close(again, base, atol=1e-5, rtol=1e-5)
        # A dropped condition drops the words with it: the unconditional row reads none.
        drop = torch.ones(2, dtype=torch.bool)
        u1 = mask(indices, token_mask, sentence, segments, segment_mask, drop, words=w, word_mask=wm).logits
        u2 = mask(indices, token_mask, sentence, segments, segment_mask, drop, words=-w, word_mask=wm).logits
        torch.testing.assert_close(u1, u2)
    with pytest.raises(ValueError, match="conditions on words"):
        mask(indices, token_mask, sentence, segments, segment_mask)
    with pytest.raises(ValueError, match="max_words=8"):
        mask(indices, token_mask, sentence, segments, segment_mask, words=torch.zeros(2, 9, 8),
             word_mask=torch.ones(2, 9, dtype=torch.bool))


def test_unit_word_norm_reads_each_word_by_direction_alone(tmp_path):
    # MiniLM's per-token states are ~6 times longer than its unit sentence vectors; with
    # word_norm "unit" a word's length no longer weighs in, only where it points.
    indices, token_mask, sentence, segments, segment_mask, _ = inputs()
    w, wm = words()
    scale = torch.rand(2, 5, 1, generator=torch.Generator().manual_seed(5)) * 6 + 0.5
    by_norm = {}
    for word_norm in ("none", "unit"):
        mask, _ = tiny_models(text_tokens="words", max_words=8, word_norm=word_norm)
        with torch.no_grad():
            base = mask(indices, token_mask, sentence, segments, segment_mask, words=w, word_mask=wm).logits
            scaled = mask(indices, token_mask, sentence, segments, segment_mask, words=w * scale,
                          word_mask=wm).logits
            padded = torch.cat([w, torch.full((2, 3, w.shape[2]), float("nan"))], dim=1)
            pad_mask = torch.cat([wm, torch.zeros(2, 3, dtype=torch.bool)], dim=1)
            again = mask(indices, token_mask, sentence, segments, segment_mask, words=padded,
                         word_mask=pad_mask).logits
        torch.testing.assert_close(again, base, atol=1e-5, rtol=1e-5)  # padding changes nothing
        by_norm[word_norm] = float((base - scaled).abs().max())
    assert by_norm["unit"] < 1e-4 < 1e-2 < by_norm["none"]
    loaded = load_pretrained(mask.save_pretrained(tmp_path / "mask"))
    assert loaded.config.word_norm == "unit"
    with torch.no_grad():
        torch.testing.assert_close(loaded.eval()(indices, token_mask, sentence, segments, segment_mask,
                                                 words=w, word_mask=wm).logits, base)
    with pytest.raises(ValueError, match="word_norm must be one of none, unit"):
        tiny_models(text_tokens="words", word_norm="layer")


def test_generation_with_words_is_seeded_recorded_and_survives_export(tmp_path):
    mask, residual = word_models()
    w, wm = words()
    options = SamplingOptions(steps=3)

    def run(m, r, ws):
        return generate_tokens(m, r, *text(2), torch.tensor([40, 24]), options=options, words=ws, word_mask=wm,
                               generator=torch.Generator().manual_seed(0))

    first = run(mask, residual, w)
    with record_attention({"mask": mask}) as recording:
        assert torch.equal(run(mask, residual, w), first)
    labels = recording.of("mask")[0].key_labels
    assert labels[:4] == ["sentence", "segment 1", "segment 2", "segment 3"]
    assert labels[4:9] == [f"word {i}" for i in range(5)] and labels[9] == "motion 0"
    assert not bool(recording.of("mask")[0].key_valid[1, 4 + 3])  # row 1's padded word
    loaded = [load_pretrained(m.save_pretrained(tmp_path / name)).eval()
              for name, m in (("mask", mask), ("residual", residual))]
    assert loaded[0].config.text_tokens == "words" and torch.equal(run(*loaded, w), first)
    with pytest.raises(ValueError, match="conditions on words"):
        generate_tokens(mask, residual, *text(2), torch.tensor([40, 24]), options=options)


@pytest.mark.parametrize("stage, word_attention", [("mask", "prefix"), ("residual", "prefix"),
                                                   ("mask", "cross")])
def test_both_transformers_train_on_words(stage, word_attention, text_dataset, tokenizer_dir, tmp_path):
    config = REPO / f"configs/{stage}/synthetic.yaml"
    cli = cli_main(["fit", "--config", str(config), *overrides(config, text_dataset, tokenizer_dir, tmp_path / "runs"),
                    "--data.init_args.text_tokens=words", f"--model.init_args.word_attention={word_attention}",
                    "--trainer.fast_dev_run=true"])
    assert cli.trainer.state.finished and torch.isfinite(cli.trainer.callback_metrics["train/loss"])
    model = cli.model.model
    assert model.config.text_tokens == "words" and model.config.word_attention == word_attention
    batch = next(iter(cli.datamodule.train_dataloader()))
    assert batch["word_features"].shape[:2] == batch["word_mask"].shape and batch["word_mask"][:, 0].all()
    grads = [p.grad for name, p in model.named_parameters() if "word" in name]
    assert len(grads) == 2
    gates = [p for name, p in model.named_parameters() if name.endswith("cross.gate")]
    assert len(gates) == (len(model.trunk.blocks) if word_attention == "cross" else 0)
    # The gates leave 0 after the first step: the words start being read.
    assert all(float(g.detach().abs()) > 0 for g in gates)


def test_cross_attention_over_words_generates_seeded_and_survives_export(tmp_path):
    mask, residual = word_models("cross")
    w, wm = words()
    options = SamplingOptions(steps=3)

    def run(m, r, ws):
        return generate_tokens(m, r, *text(2), torch.tensor([40, 24]), options=options, words=ws, word_mask=wm,
                               generator=torch.Generator().manual_seed(0))

    # That the cross-attention reads the words is shown on logits (the test above); the
    # sampled tokens of a tiny random model may not move with them on every CPU.
    first = run(mask, residual, w)
    with record_attention({"mask": mask}) as recording:
        assert torch.equal(run(mask, residual, w), first)
    # The words are not keys of the self-attention: the recording has the text prefix alone.
    labels = recording.of("mask")[0].key_labels
    assert labels[:5] == ["sentence", "segment 1", "segment 2", "segment 3", "motion 0"]
    loaded = [load_pretrained(m.save_pretrained(tmp_path / name)).eval()
              for name, m in (("mask", mask), ("residual", residual))]
    assert loaded[0].config.word_attention == "cross" and torch.equal(run(*loaded, w), first)
    with pytest.raises(ValueError, match="cross-attention"):
        mask.trunk.encode_prefix(torch.zeros(2, 4, 32), torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="word_attention must be one of prefix, cross"):
        tiny_models(text_tokens="words", word_attention="gated")


@pytest.mark.parametrize("residual_tokens", ["words", "none"])
def test_a_bundle_with_words_generates_grounds_and_edits(residual_tokens, tmp_path, tokenizer_dir):
    # A words mask transformer may be paired with a residual transformer without words
    # (the built-in corpus's measurement shares one residual among all mask models).
    from test_pipeline import build_stages

    from segmo.models.tokenizer import RVQVAE
    from segmo.pipeline import SegMo
    from segmo.pipeline.segmo import SegMoConfig

    stages = build_stages(tmp_path, tokenizer_dir["t2m"])
    torch.manual_seed(1)
    config = dict(TINY, text_dim=8, max_segments=3, max_tokens=49, text_tokens="words")
    model = SegMo(RVQVAE.from_pretrained(stages["tokenizer"]), MaskTransformer(MaskTransformerConfig(**config)),
                  ResidualTransformer(ResidualTransformerConfig(
                      **dict(config, text_tokens=residual_tokens), num_quantizers=3)),
                  config=SegMoConfig(text_encoder="hash"), text_encoder=hash_encoder("hash", 8))
    assert model.uses_words
    out = model.generate(["a person walks forward, then waves."], 48, generator=torch.Generator().manual_seed(0))
    again = model.generate(["a person walks forward, then waves."], 48, generator=torch.Generator().manual_seed(0))
    assert torch.equal(out.tokens, again.tokens)
    found = model.ground("a person walks forward, then waves.", out.motion(0), method="attention")
    assert len(found.best_spans_frames) == 2
    edited = model.edit(out, (8, 24), "a person jumps", generator=torch.Generator().manual_seed(1))
    assert torch.equal(edited.tokens[0, :2], out.tokens[0, :2])
    saved = model.save_pretrained(tmp_path / "bundle")
    loaded = SegMo.from_pretrained(saved, text_encoder=hash_encoder("hash", 8))
    assert loaded.uses_words and torch.equal(
        loaded.generate(["a person walks forward, then waves."], 48, generator=torch.Generator().manual_seed(0)).tokens,
        out.tokens)
    assert Path(saved, "mask", "config.json").is_file()
    # The text of each word key, in the recording's "word w" order; a long text is cut at
    # the model's max_words.
    texts = ["a person walks forward, then waves.", "one two three four five six seven eight"]
    assert model.word_texts(texts)[0] == ["a", "person", "walks", "forward,", "then", "waves."]
    model.mask.config.max_words = 5
    assert model.word_texts(texts)[1] == ["one", "two", "three", "four", "five"]
    # Word features are cached per text like sentences, and forgotten with the encoder.
    before, _ = model.word_condition(texts[:1])
    doubled = hash_encoder("hash", 8)
    plain = doubled.encode
    doubled.encode = lambda texts, batch_size=64: dataclasses.replace(
        plain(texts), tokens=2 * plain(texts).tokens)
    model.text_encoder = doubled
    after, _ = model.word_condition(texts[:1])
    assert torch.equal(after, 2 * before)


def test_a_residual_with_words_needs_a_mask_transformer_with_words(tmp_path, tokenizer_dir):
    from test_pipeline import build_stages

    from segmo.errors import SegmoError
    from segmo.models.tokenizer import RVQVAE
    from segmo.pipeline import SegMo

    stages = build_stages(tmp_path, tokenizer_dir["t2m"])
    config = dict(TINY, text_dim=8, max_segments=3, max_tokens=49)
    residual = ResidualTransformer(ResidualTransformerConfig(**config, text_tokens="words", num_quantizers=3))
    with pytest.raises(SegmoError, match="disagree on text_tokens: none vs words"):
        SegMo(RVQVAE.from_pretrained(stages["tokenizer"]), MaskTransformer(MaskTransformerConfig(**config)),
              residual)


def test_reweighting_a_word_needs_word_keys():
    from segmo.errors import SegmoError
    from segmo.pipeline.editing import weight_labels

    assert weight_labels({"word 2": 2.0}, ["walks"], 3) == {"word 2": 2.0}
    with pytest.raises(SegmoError, match="no word keys.*cross-attention"):
        weight_labels({"word 2": 2.0}, ["walks"], None)
    # A word number is checked against the caption's word keys and read as a number.
    assert weight_labels({"word 02": 2.0}, ["walks"], 3) == {"word 2": 2.0}
    with pytest.raises(SegmoError, match=r"'word 3': the caption has 3 word keys \(word 0 to word 2"):
        weight_labels({"word 3": 2.0}, ["walks"], 3)


def test_word_keys_can_read_the_segments_in_execution_order(tmp_path, tokenizer_dir, monkeypatch):
    # "before jumping, a man walks" names the last action first: word keys read from the
    # caption carry that mention order; read from the segments they carry the execution
    # order that the segment keys carry (`SamplingOptions.word_text`).
    from dataclasses import replace

    from test_pipeline import build_stages

    from segmo.errors import SegmoError
    from segmo.models.tokenizer import RVQVAE
    from segmo.pipeline import SegMo
    from segmo.pipeline.conditioning import TextConditioning
    from segmo.pipeline.segmo import SegMoConfig
    from segmo.text.extract import ordered_text

    stages = build_stages(tmp_path, tokenizer_dir["t2m"])
    torch.manual_seed(1)
    config = dict(TINY, text_dim=8, max_segments=3, max_tokens=49, text_tokens="words")
    model = SegMo(RVQVAE.from_pretrained(stages["tokenizer"]), MaskTransformer(MaskTransformerConfig(**config)),
                  ResidualTransformer(ResidualTransformerConfig(**config, num_quantizers=3)),
                  config=SegMoConfig(text_encoder="hash"), text_encoder=hash_encoder("hash", 8))
    caption = "before jumping, a man walks forward."
    assert model.segment_texts([caption]) == [["a man walks forward", "a man jumps"]]
    assert model.sampling.word_text == "caption"  # the default: today's word keys
    assert model.word_sources([caption]) == [caption]
    assert model.word_sources([caption], word_text="segments") == ["a man walks forward, then a man jumps"]
    assert model.word_sources([caption], [["a man waves"]], "segments") == ["a man waves"]
    words, mask = model.word_condition([caption], word_text="segments")
    same, same_mask = model.word_condition(["a man walks forward, then a man jumps"])
    assert torch.equal(words, same) and torch.equal(mask, same_mask)
    assert model.word_texts([caption], word_text="segments")[0] == \
        ["a", "man", "walks", "forward,", "then", "a", "man", "jumps"]
    assert ordered_text(["one"]) == "one"

    # generate, edit and the bundle's default pass the option on, with the segments used
    read: list[list[str]] = []
    sources = TextConditioning.word_sources
    monkeypatch.setattr(TextConditioning, "word_sources",
                        lambda self, *a, **k: read.append(sources(self, *a, **k)) or read[-1])
    options = replace(model.sampling, word_text="segments")
    out = model.generate([caption], 48, sampling=options, generator=torch.Generator().manual_seed(0))
    assert out.sampling.word_text == "segments" and read[-1] == ["a man walks forward, then a man jumps"]
    model.generate([caption], 48, segments=[["a man runs", "a man sits"]], sampling=options,
                   generator=torch.Generator().manual_seed(0))
    assert read[-1] == ["a man runs, then a man sits"]
    model.edit(out, (8, 24), "a person kicks", generator=torch.Generator().manual_seed(1))
    assert read[-1] == ["a person kicks"]  # the bundle's default: the caption
    model.config.word_text = "segments"
    saved = model.save_pretrained(tmp_path / "bundle")
    assert json.loads(Path(saved, "segmo.json").read_text())["word_text"] == "segments"
    loaded = SegMo.from_pretrained(saved, text_encoder=hash_encoder("hash", 8))
    assert loaded.sampling.word_text == "segments"
    assert torch.equal(loaded.generate([caption], 48, generator=torch.Generator().manual_seed(0)).tokens,
                       out.tokens)
    # `segmo generate --word-text` overrides the bundle's default for that run
    import segmo.text.encoders
    from segmo.pipeline.cli import generate_main

    monkeypatch.setattr(segmo.text.encoders, "get_text_encoder", lambda name, device="cpu": hash_encoder(name, 8))
    generate_main(["--model", str(saved), "--text", caption, "--length", "48", "--formats", "npy",
                   "--word-text", "caption", "--out", str(tmp_path / "cli")])
    assert read[-1] == [caption]
    generate_main(["--model", str(saved), "--text", caption, "--length", "48", "--formats", "npy",
                   "--out", str(tmp_path / "cli_default")])
    assert read[-1] == ["a man walks forward, then a man jumps"]
    with pytest.raises(SegmoError, match="word_text must be 'caption' or 'segments', got 'words'"):
        SamplingOptions(word_text="words")
    with pytest.raises(SegmoError, match="word_text must be 'caption' or 'segments'"):
        model.word_sources([caption], word_text="sentence")
