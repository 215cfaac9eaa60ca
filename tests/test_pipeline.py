"""The `SegMo` inference pipeline and `segmo generate/ground/bundle` on a tiny random bundle.

No training: the stages are randomly initialised (sharpened so that the text matters)
and the text encoder is the deterministic hash encoder of conftest.py.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import cli_failure, hash_encoder

from segmo.errors import SegmoError
from segmo.evaluation.grounding import grounding_accuracy
from segmo.generation import SamplingOptions
from segmo.models.alignment import AlignmentConfig
from segmo.models.length_estimator import LengthEstimator, LengthEstimatorConfig
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
from segmo.models.tokenizer import RVQVAE
from segmo.pipeline import GenerationOutput, SegMo, edit_drift
from segmo.pipeline.cli import bundle_main, generate_main, ground_main
from segmo.pipeline.grounding import best_span, plot_similarity_map, sliding_windows
from segmo.pipeline.retrieval import pair_scores

TEXT_DIM = 8
TINY = dict(codebook_size=16, text_dim=TEXT_DIM, max_segments=3, max_tokens=49, dim=32,
            depth=2, heads=2, ff_dim=64, dropout=0.1)
PROMPTS = ["a person walks forward, then waves.", "someone jumps twice and then sits down."]


def build_stages(root, tokenizer, text_dim=TEXT_DIM, encoder="hash", alignment=True,
                 segment_timing=False):
    """A tokenizer with random codebooks (the fixture's are all zero, so every token would
    decode alike) and random mask/residual/length stages; returns their directories."""
    torch.manual_seed(0)
    rvq = RVQVAE.from_pretrained(tokenizer)
    rvq.quantizer.codebooks.normal_()
    rvq.quantizer.initialised.fill_(True)
    tokenizer = rvq.save_pretrained(root / "tokenizer")
    config = dict(TINY, text_dim=text_dim)
    mask = MaskTransformer(MaskTransformerConfig(
        **config, alignment=AlignmentConfig(out_dim=16) if alignment else None,
        segment_timing=segment_timing))
    residual = ResidualTransformer(ResidualTransformerConfig(**config, num_quantizers=3))
    length = LengthEstimator(LengthEstimatorConfig(text_dim=text_dim, hidden=16, max_tokens=49))
    with torch.no_grad():  # sharper than the 0.02-std initialisation, so the text matters
        mask.classifier.weight.mul_(50)
        residual.code_embeddings.mul_(50)
        if segment_timing:  # and the timing
            mask.timing.index.mul_(50)
    meta = {"text_encoder": encoder, "tokenizer": str(tokenizer)}
    dirs = {"tokenizer": tokenizer}
    for name, model in (("mask", mask), ("residual", residual), ("length", length)):
        dirs[name] = model.save_pretrained(root / name, meta=meta)
    return dirs


@pytest.fixture(scope="module")
def stages(tmp_path_factory, tokenizer_dir):
    return build_stages(tmp_path_factory.mktemp("stages"), tokenizer_dir["t2m"])


@pytest.fixture(scope="module")
def bundle(stages, tmp_path_factory):
    """A bundle directory written by `segmo bundle` (through the `segmo` dispatcher)."""
    from segmo.cli import main

    out = tmp_path_factory.mktemp("bundle") / "model"
    main(["bundle", "--tokenizer", str(stages["tokenizer"]), "--mask", str(stages["mask"]),
                 "--residual", str(stages["residual"]), "--length", str(stages["length"]),
                 "--out", str(out)])
    return out


@pytest.fixture(scope="module")
def model(bundle):
    return SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))


def seeded(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.fixture(scope="module")
def generated(model):
    return model.generate(PROMPTS, [48, 32], generator=seeded())


def test_bundle_layout_and_config(bundle, model):
    payload = json.loads((bundle / "segmo.json").read_text())
    assert payload["format"] == 1 and payload["text_encoder"] == "hash"
    assert payload["skeleton"] == "t2m" and payload["fps"] == 20.0
    assert payload["guidance_scale"] == 4.0 and payload["text_segmenter"] == "rule"
    for stage in ("tokenizer", "mask", "residual", "length"):
        assert (bundle / stage / "config.json").is_file()
    assert model.max_frames == 196 and model.text_encoder_name == "hash"
    assert model.skeleton.name == "t2m" and model.fps == 20.0


def test_generation_shapes_and_padding(model, generated):
    out = generated
    assert out.features.shape == (2, 48, 263) and out.joints.shape == (2, 48, 22, 3)
    assert out.tokens.shape == (2, 12, 3) and out.lengths.tolist() == [48, 32]
    assert out.segments[0] == ["a person walks forward", "a person waves"]
    assert bool((out.features[1, 32:] == 0).all()) and bool((out.joints[1, 32:] == 0).all())
    assert bool((out.tokens[1, 8:] == -1).all()) and bool((out.tokens[:, :8] >= 0).all())
    # features are de-normalised: tokenizer std 0.1, so z-scored values shrink tenfold
    z = model.tokenizer.normalize(out.features[0])
    assert torch.allclose(model.tokenizer.denormalize(z), out.features[0], atol=1e-5)
    assert out.motion(1).shape == (32, 263)


def test_seeded_generation_is_reproducible(model, generated):
    again = model.generate(PROMPTS, [48, 32], generator=seeded())
    assert torch.equal(again.tokens, generated.tokens)
    assert torch.equal(again.features, generated.features)
    other = model.generate(PROMPTS, [48, 32], generator=seeded(1))
    assert not torch.equal(other.tokens, generated.tokens)


def test_recording_attention_changes_no_generation_or_edit(model, generated):
    from segmo.evaluation.attention import motion_attention, sink_ratio

    with model.record_attention() as recording:
        again = model.generate(PROMPTS, [48, 32], generator=seeded())
    assert torch.equal(again.tokens, generated.tokens)
    steps = model.sampling.steps
    assert recording.steps("mask") == steps and recording.steps("residual") >= 1
    assert 0.0 <= sink_ratio(recording.of("mask"))["mean"] <= 1.0
    plain = model.edit(generated, (8, 24), "a person jumps", generator=seeded(2))
    with model.record_attention() as recording:
        edited = model.edit(generated, (8, 24), "a person jumps", generator=seeded(2))
    assert torch.equal(plain.tokens, edited.tokens) and recording.steps("mask") >= 1
    maps = motion_attention(model, PROMPTS, generated.segments,
                            [generated.motion(0), generated.motion(1)])
    assert len(maps) == len(model.mask.trunk.blocks) and maps[0].rows.tolist() == [0, 1]


@pytest.mark.parametrize("search", ["ordered", "spans", "window"])
def test_attention_grounding_finds_a_span_per_segment(model, generated, search):
    motion = generated.motion(0)
    out = model.ground(PROMPTS[0], motion, search=search, method="attention")
    assert out.method == "attention" and out.search == search and len(out.best_spans_frames) == 2
    assert out.similarity.shape == (2, len(out.windows)) and float(out.similarity.min()) >= 0.0
    assert all(0 <= s < e <= len(motion) for s, e in out.best_spans_frames)
    if search == "ordered":  # a cut: contiguous, in order, covering the motion
        (s0, e0), (s1, e1) = out.best_spans_frames
        assert s0 == 0 and e0 == s1 and e1 == len(motion)
    assert " att " in str(out)


def test_attention_grounding_follows_the_attention(model, generated, monkeypatch):
    """Tokens 0-3 attend to segment 2 and the rest to segment 1: the ordered cut cannot
    follow (segment 1 comes first), the free spans do."""
    import segmo.pipeline.grounding as grounding_module

    real = grounding_module.segment_profile

    def fake(m, row):
        profile = real(m, row)
        profile[:] = 0.0
        profile[1, :4], profile[0, 4:] = 1.0, 1.0
        return profile

    monkeypatch.setattr(grounding_module, "segment_profile", fake)
    out = model.ground(PROMPTS[0], generated.motion(0), search="spans", method="attention")
    assert out.best_spans_frames == [(16, 48), (0, 16)]
    with pytest.raises(SegmoError, match="method='heat'; choose from similarity, attention"):
        model.ground(PROMPTS[0], generated.motion(0), method="heat")


def test_bundle_round_trip_gives_identical_generations(model, generated, tmp_path):
    model.save_pretrained(tmp_path / "copy")
    loaded = SegMo.from_pretrained(tmp_path / "copy", text_encoder=hash_encoder("hash", 8))
    again = loaded.generate(PROMPTS, [48, 32], generator=seeded())
    assert torch.equal(again.tokens, generated.tokens)
    assert torch.equal(again.features, generated.features)


def _hub_cache(cache: Path, repo_id: str, folder: Path, commit: str = "0" * 40) -> None:
    """Put `folder` into a Hugging Face cache as repository `repo_id` at `commit` (the
    cache layout huggingface_hub documents: refs/main names the snapshot)."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    shutil.copytree(folder, repo / "snapshots" / commit)
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)


def test_hub_id_loads_from_the_offline_cache_like_the_folder(model, generated, tmp_path, monkeypatch):
    import huggingface_hub.constants

    model.save_pretrained(tmp_path / "folder")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    _hub_cache(tmp_path / "cache", "someone/segmo-tiny", tmp_path / "folder")
    loaded = SegMo.from_pretrained("someone/segmo-tiny", text_encoder=hash_encoder("hash", TEXT_DIM))
    again = loaded.generate(PROMPTS, [48, 32], generator=seeded())
    assert torch.equal(again.tokens, generated.tokens) and torch.equal(again.features, generated.features)
    with pytest.raises(SegmoError, match="not in the Hugging Face cache"):
        SegMo.from_pretrained("someone/never-downloaded")


def test_push_to_hub_creates_the_repository_and_uploads_the_folder(model, tmp_path, monkeypatch):
    import huggingface_hub

    calls = []

    class FakeApi:  # nothing reaches a hub
        def __init__(self, **kwargs):
            calls.append(("init", kwargs.get("library_name")))

        def create_repo(self, repo_id, private=False, exist_ok=False):
            calls.append(("create", repo_id, private, exist_ok))

        def upload_folder(self, repo_id, folder_path, commit_message):
            calls.append(("upload", repo_id, sorted(p.name for p in Path(folder_path).iterdir())))

    monkeypatch.setattr(huggingface_hub, "HfApi", FakeApi)
    model.save_pretrained(tmp_path / "out", push_to_hub=True, repo_id="me/segmo-test", private=True)
    assert calls[0] == ("init", "segmo") and calls[1] == ("create", "me/segmo-test", True, True)
    assert calls[2] == ("upload", "me/segmo-test", ["README.md", "length", "mask", "residual",
                                                   "segmo.json", "tokenizer"])
    with pytest.raises(SegmoError, match="needs repo_id"):
        model.save_pretrained(tmp_path / "out2", push_to_hub=True)


def test_bundle_records_versions_and_writes_a_model_card(bundle, tmp_path):
    from segmo import __version__
    from segmo.cli import main

    for config in [bundle / "segmo.json"] + [bundle / s / "config.json" for s in
                                             ("tokenizer", "mask", "residual", "length")]:
        payload = json.loads(config.read_text())
        assert payload["format"] == 1 and payload["segmo_version"] == __version__, config
        assert (config.stat().st_mode & 0o777) == 0o666 & ~_umask(), config
    card = (bundle / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: segmo") and "| mask | mask |" in card
    assert "## Evaluation" not in card  # no metrics given
    metrics = tmp_path / "metrics.json"
    metrics.write_text(json.dumps({"generation": {"generated": {"top1": {"mean": 0.5}, "fid": 1.25}}}))
    main(["bundle", "--tokenizer", str(bundle / "tokenizer"), "--mask", str(bundle / "mask"),
          "--metrics", str(metrics), "--out", str(tmp_path / "with_metrics")])
    card = (tmp_path / "with_metrics" / "README.md").read_text()
    assert "## Evaluation" in card and "| 0.500 | 1.250 |" in card


def test_a_bundle_missing_a_stage_folder_it_records_is_refused(bundle, tmp_path):
    """A partial copy or download (no residual/) is refused, not loaded without the stage;
    a bundle written before the stages were recorded loads what it holds, as before."""
    copy = tmp_path / "copy"
    shutil.copytree(bundle, copy)
    payload = json.loads((copy / "segmo.json").read_text())
    assert payload["stages"] == ["tokenizer", "mask", "residual", "length"]
    shutil.rmtree(copy / "residual")
    with pytest.raises(SegmoError, match=r"copy/residual: missing, but segmo.json lists"):
        SegMo.from_pretrained(copy, text_encoder=hash_encoder("hash", TEXT_DIM))
    del payload["stages"]  # as a bundle of an earlier segmo
    (copy / "segmo.json").write_text(json.dumps(payload))
    old = SegMo.from_pretrained(copy, text_encoder=hash_encoder("hash", TEXT_DIM))
    assert old.residual is None and old.length is not None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_sampling_options_object_and_keywords_agree(model, generated):
    """`sampling=` takes a whole SamplingOptions; a keyword takes one option's place."""
    assert model.sampling == SamplingOptions(guidance_scale=4.0, residual_guidance_scale=5.0,
                                             steps=10, residual_guided_layers=None)
    same = model.generate(PROMPTS, [48, 32], sampling=model.sampling, generator=seeded())
    assert torch.equal(same.tokens, generated.tokens)
    greedy = model.generate(PROMPTS, [48, 32], temperature=0.0, steps=3, generator=seeded())
    replaced = model.generate(PROMPTS, [48, 32], generator=seeded(),
                              sampling=dataclasses.replace(model.sampling, temperature=0.0),
                              steps=3)
    assert torch.equal(greedy.tokens, replaced.tokens)
    with pytest.raises(SegmoError, match="steps"):
        SamplingOptions(steps=0)
    with pytest.raises(SegmoError, match="sampling must be a SamplingOptions"):
        model.generate(PROMPTS, [48, 32], sampling={"steps": 3})


def test_from_stages_equals_bundle(stages, generated):
    model = SegMo.from_stages(stages["tokenizer"], stages["mask"], stages["residual"],
                              stages["length"], text_encoder=hash_encoder("hash", TEXT_DIM))
    assert torch.equal(model.generate(PROMPTS, [48, 32], generator=seeded()).tokens,
                       generated.tokens)


def test_lengths_from_estimator_and_text_cache(model):
    out = model.generate(PROMPTS, generator=seeded(3))
    assert all(int(n) % 4 == 0 and 4 <= int(n) <= model.max_frames for n in out.lengths)
    # Each text is encoded once, then read from the cache; another encoder starts afresh.
    original, counting, seen = model.text_encoder, hash_encoder("hash", TEXT_DIM), []
    plain = counting.encode
    counting.encode = lambda texts, batch_size=64: seen.extend(texts) or plain(texts)
    model.text_encoder = counting
    try:
        first = model.encode_texts(PROMPTS[:1])
        assert torch.equal(model.encode_texts(PROMPTS), torch.cat([first, model.encode_texts(PROMPTS[1:])]))
        assert seen == PROMPTS
        assert torch.equal(first[0], hash_encoder("hash", TEXT_DIM).encode(PROMPTS[:1]).sentence[0])
    finally:
        model.text_encoder = original


@pytest.mark.parametrize("lengths", [[30, 48], [0, 48], [48, 200], [48], [48, 48, 48]])
def test_bad_lengths_are_refused(model, lengths):
    with pytest.raises(ValueError, match="lengths|texts"):
        model.generate(PROMPTS, lengths, generator=seeded())


def test_missing_length_estimator_and_bad_inputs(model):
    bare = SegMo(model.tokenizer, model.mask, model.residual, None, model.config,
                 text_encoder=model.text_encoder)
    with pytest.raises(ValueError, match="no length estimator"):
        bare.generate(PROMPTS)
    with pytest.raises(ValueError, match="segments"):
        model.generate(["x"], [16], segments=[["a", "b", "c", "d"]])
    with pytest.raises(ValueError, match=r"raw features \(t, 263\)"):
        model.ground("a person walks", np.zeros((40, 22, 3)))
    with pytest.raises(FileNotFoundError, match="no such model folder"):
        SegMo.from_pretrained("/nonexistent/segmo-model")


def test_edit_keeps_every_token_outside_the_span(model, generated, capsys):
    span = (16, 32)  # frames → tokens 4..8
    edited = model.edit(generated, span, "a person jumps", generator=seeded(5))
    outside = torch.ones(12, dtype=torch.bool)
    outside[4:8] = False
    assert torch.equal(edited.tokens[:, outside], generated.tokens[:, outside])  # all q layers
    assert not torch.equal(edited.tokens[:, 4:8], generated.tokens[:, 4:8])
    assert edited.texts == ["a person jumps"] * 2
    drift = edit_drift(generated.motion(0), edited.motion(0), span)
    print("edit drift (frames from span → mean |Δ feature|):",
          {d: round(v, 5) for d, v in drift.items()})
    assert set(drift) == set(range(1, 17))  # 16 frames before and 16 after the span
    assert all(math.isfinite(v) and v >= 0 for v in drift.values())
    # the convolutional decoder's reach is bounded: adjacent frames move at least as much
    assert drift[1] >= drift[16]
    # raw features are tokenized first; the span must lie inside the motion
    raw = model.edit(generated.motion(1), (0, 8), "someone waves", generator=seeded(6))
    assert raw.features.shape == (1, 32, 263)
    with pytest.raises(ValueError, match="span"):
        model.edit(generated, (40, 60), "x")


def test_edit_drift_is_by_distance():
    a = np.zeros((10, 2))
    b = a.copy()
    b[3] = 1.0  # distance 2 before span (5, 8)
    b[9] = 3.0  # distance 2 after
    assert edit_drift(a, b, (5, 8)) == {1: 0.0, 2: 2.0, 3: 0.0, 4: 0.0, 5: 0.0}


def test_grounding_shapes_and_best_span(model, generated):
    motion = np.concatenate([generated.motion(0), generated.motion(0)[:6]])  # 54 frames
    out = model.ground(PROMPTS[0], motion, window=5, stride=1)
    assert out.segments == ["a person walks forward", "a person waves"]
    assert out.num_frames == 54
    assert out.windows.shape == (13 - 5 + 1, 2)  # 13 tokens (52 frames used)
    assert out.similarity.shape == (2, 9)
    assert bool((out.similarity.abs() <= 1 + 1e-5).all())
    for (s, e), score, row in zip(out.best_spans_frames, out.best_scores, out.similarity):
        assert 0 <= s < e <= 54 and e - s == 20
        assert score == pytest.approx(float(row.max()))
        assert out.windows[int(row.argmax())].tolist() == [s // 4, e // 4]
    assert "frames" in str(out)
    ax = plot_similarity_map(out, truth=[(0, 24), (24, 54)])
    assert len(ax.get_yticklabels()) == 2 and len(ax.patches) == 2
    assert len(ax.collections) == 2  # one true-span underline per segment
    import matplotlib.pyplot as plt

    plt.close(ax.figure)
    multi = model.ground(PROMPTS[0], motion, window=[3, 6], stride=2, segments=["walk", "wave"])
    assert multi.segments == ["walk", "wave"] and multi.similarity.shape[0] == 2


def test_grounding_locates_segments_by_content_not_order(model, generated):
    """Grounding feeds the segments as a set: listing them in another order moves no span."""
    motion = generated.motion(0)
    forward = model.ground(PROMPTS[0], motion, window=5, segments=["walk", "wave", "jump"])
    shuffled = model.ground(PROMPTS[0], motion, window=5, segments=["jump", "walk", "wave"])
    torch.testing.assert_close(torch.as_tensor(shuffled.similarity)[[1, 2, 0]],
                               torch.as_tensor(forward.similarity), rtol=1e-5, atol=1e-5)
    assert shuffled.best_spans_frames[1:] + shuffled.best_spans_frames[:1] == forward.best_spans_frames


def test_window_search_is_the_papers_sliding_window(model, generated):
    """search="window" (a window given) is what grounding computed before the span searches:
    each segment's best sliding window of the segment space, ×4 frames."""
    motion = generated.motion(1)
    out = model.ground(PROMPTS[1], motion, window=5, stride=1)
    same = model.ground(PROMPTS[1], motion, search="window")  # the paper's 5 tokens
    assert out.search == "window" and same.best_spans_frames == out.best_spans_frames
    space = model.embed_segments([PROMPTS[1]], [motion])
    windows = sliding_windows(int(space.num_tokens[0]), 5, 1)
    similarity = space.similarity(torch.from_numpy(windows))[0].float()
    expected = best_span(similarity, windows) * 4
    assert out.best_spans_frames == [(int(s), int(min(e, len(motion)))) for s, e in expected]
    torch.testing.assert_close(out.similarity, similarity)


def test_ordered_search_cuts_the_motion_in_caption_order(model, generated):
    motion = np.concatenate([generated.motion(0), generated.motion(0)[:6]])  # 54 frames, 13 tokens
    out = model.ground(PROMPTS[0], motion, segments=["walk", "wave", "jump"])
    assert out.search == "ordered" and out.windows.shape == (78, 2)  # every span of ≥ 2 of 13 tokens
    spans = out.best_spans_frames
    assert spans[0][0] == 0 and spans[-1][1] == 52  # every valid token (52 frames used)
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))  # contiguous, in order
    assert all(e - s >= 8 for s, e in spans)  # ≥ 2 tokens each
    columns = {tuple(w): i for i, w in enumerate(out.windows.tolist())}
    for k, (score, (s, e)) in enumerate(zip(out.best_scores, spans)):
        assert score == pytest.approx(float(out.similarity[k, columns[(s // 4, -(-e // 4))]]))
    best = model.ground(PROMPTS[0], motion, search="spans", segments=["walk", "wave", "jump"])
    assert best.best_scores == pytest.approx(out.similarity.max(dim=1).values.tolist())
    ax = plot_similarity_map(out, truth=[(0, 16), (16, 40), (40, 54)])
    assert ax.get_images()[0].get_array().shape == (3, 13)  # segments × tokens
    assert len(ax.patches) == 3 and len(ax.collections) == 3
    import matplotlib.pyplot as plt

    plt.close(ax.figure)
    for kwargs, message in ((dict(search="best"), "search='best'"),
                            (dict(search="spans", window=5), "is for search='window'"),
                            (dict(window=0), "window=0"),
                            (dict(min_tokens=7), "3 segments in order need 21 tokens")):
        with pytest.raises(SegmoError, match=message):
            model.ground(PROMPTS[0], motion, segments=["walk", "wave", "jump"], **kwargs)


@pytest.mark.parametrize("method", ["similarity", "attention"])
def test_ground_refuses_options_its_search_does_not_use(model, generated, method):
    """A stride with the ordered search changed nothing, and min_tokens beyond the motion was
    cut to the whole motion by the spans search, both without a word."""
    motion = generated.motion(0)  # 48 frames, 12 tokens
    ground = functools.partial(model.ground, PROMPTS[0], motion, method=method)
    for kwargs, message in ((dict(stride=7), "stride=7 is for search='window', not 'ordered'"),
                            (dict(search="spans", stride=1), "stride=1 is for search='window', "
                                                              "not 'spans'"),
                            (dict(window=5, min_tokens=3), "min_tokens=3 is for search "
                                                           "'ordered' or 'spans', not 'window'"),
                            (dict(search="spans", min_tokens=13), "spans of at least "
                             "min_tokens=13 tokens; the motion has 12")):
        with pytest.raises(SegmoError, match=re.escape(message)):
            ground(**kwargs)
    assert ground(search="spans", min_tokens=12).best_spans_frames == [(0, 48), (0, 48)]
    assert ground(window=5, stride=2).windows.tolist() == [[0, 5], [2, 7], [4, 9], [6, 11],
                                                           [7, 12]]
    spans = ground(min_tokens=3).windows
    assert int((spans[:, 1] - spans[:, 0]).min()) == 3


def test_cli_ground_refuses_stride_and_min_tokens_its_search_does_not_use(
        bundle, generated, tmp_path, hash_text_encoder, capsys, monkeypatch):
    motion = tmp_path / "motion.npy"
    np.save(motion, generated.motion(0))
    ground = ["ground", "--model", str(bundle), "--text", PROMPTS[0], "--motion", str(motion)]
    monkeypatch.setattr(SegMo, "from_pretrained", lambda *a, **k: pytest.fail("model loaded"))
    for argv, message in (
            (["--stride", "7"], "--stride is for --search window, not --search ordered"),
            (["--search", "spans", "--stride", "1"], "--stride is for --search window, not "
                                                     "--search spans"),
            (["--window", "5", "--min-tokens", "3"], "--min-tokens is for --search ordered or "
                                                     "spans, not --search window"),
            (["--search", "window", "--min-tokens", "2"], "--min-tokens is for --search ordered "
                                                          "or spans, not --search window")):
        line = cli_failure([*ground, *argv], capsys)
        assert line.startswith(f"segmo ground: {message}"), line


def test_embed_pairs_spans(model, generated):
    motions = [generated.motion(0), generated.motion(1)]
    for spans in (None, "uniform", "cpd", "kmeans"):
        text, motion, mask = model.embed_pairs(PROMPTS, motions, spans)
        assert text.shape == motion.shape == (2, 2, 16)
        assert mask.tolist() == [[True, True], [True, True]]
    explicit = torch.tensor([[[0, 3], [3, 12]], [[0, 8], [0, 0]]])
    _, _, mask = model.embed_pairs(PROMPTS, motions, explicit)
    assert mask.tolist() == [[True, True], [True, False]]
    # a padded z-scored batch gives the same embeddings as the list of raw motions
    z = model.tokenizer.normalize(generated.features)
    t1, m1, _ = model.embed_pairs(PROMPTS, motions)
    t2, m2, _ = model.embed_pairs(PROMPTS, z, lengths=generated.lengths, normalized=True)
    assert torch.allclose(t1, t2, atol=1e-5) and torch.allclose(m1, m2, atol=1e-4)
    with pytest.raises(ValueError, match="explicit spans"):
        model.embed_pairs(PROMPTS, motions, torch.zeros(2, 3, 2, dtype=torch.long))


def test_retrieval_ranks(model, generated):
    candidates = PROMPTS + ["the figure claps three times.", "a woman kicks."]
    ranked = model.retrieve_texts(generated.motion(0), candidates, top_k=10)
    assert sorted(t for t, _ in ranked) == sorted(candidates)
    scores = [s for _, s in ranked]
    assert scores == sorted(scores, reverse=True)
    # the score is the mean paired cosine of embed_pairs
    pairs = model.embed_pairs([ranked[0][0]], [generated.motion(0)], "uniform")
    assert float(pair_scores(*pairs)[0]) == pytest.approx(scores[0], abs=1e-5)
    assert len(model.retrieve_texts(generated.motion(0), candidates, span=(8, 40), top_k=2)) == 2
    motions = [generated.motion(1), generated.motion(0), generated.motion(1)]
    ranked = model.retrieve_motions(PROMPTS[0], motions, top_k=3)
    assert sorted(i for i, _ in ranked) == [0, 1, 2]
    by_index = dict(ranked)
    assert by_index[0] == pytest.approx(by_index[2], abs=1e-5)  # same motion, same score
    assert [s for _, s in ranked] == sorted((s for _, s in ranked), reverse=True)


def test_a_motion_decodes_alike_alone_and_beside_a_longer_one(model, generated):
    """The decoder runs each sample at its own length: a longer batch-mate's padding
    (index -1, decoded as zero codes, then non-zero after the first convolution) no longer
    leaks into the last frames of the shorter motion."""
    n = int(generated.lengths[1]) // 4  # 32 frames beside a 48-frame motion
    alone = model.decode(generated.tokens[1:2, :n], generated.lengths[1:2], PROMPTS[1:],
                         generated.segments[1:])
    torch.testing.assert_close(generated.features[1], torch.cat(
        [alone.features[0], torch.zeros(16, alone.features.shape[2])]), rtol=0, atol=1e-6)
    torch.testing.assert_close(generated.joints[1, :32], alone.joints[0], rtol=0, atol=1e-6)


def test_a_motion_encodes_alike_alone_and_beside_a_longer_one(model, generated):
    """embed_segments (grounding, retrieval, the cpd/kmeans spans) encodes each motion at
    its own length: a longer motion in the batch changes none of its latents, motion
    features or retrieval scores."""
    short, long = generated.motion(1), np.concatenate([generated.motion(0), generated.motion(0)])
    alone = model.embed_segments(PROMPTS[1:], [short])
    batch = model.embed_segments([PROMPTS[1], PROMPTS[0]], [short, long])
    n = int(alone.num_tokens[0])
    torch.testing.assert_close(batch.latents[0, :n], alone.latents[0], rtol=0, atol=1e-6)
    assert bool((batch.latents[0, n:] == 0).all())
    torch.testing.assert_close(batch.features[0, :n], alone.features[0], rtol=0, atol=1e-5)
    score = dict(model.retrieve_motions(PROMPTS[1], [short], top_k=1))[0]
    beside = dict(model.retrieve_motions(PROMPTS[1], [short, long], top_k=2))[0]
    assert beside == pytest.approx(score, abs=1e-6)


def test_a_model_left_in_train_mode_grounds_and_retrieves_as_in_eval_mode(bundle, generated):
    """Grounding, retrieval and generation run without dropout whatever mode the caller left
    the stages in (fine-tuning in a notebook), and give the caller's mode back."""
    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    text, motion, candidates = PROMPTS[0], generated.motion(0), PROMPTS + ["a woman kicks."]

    def results():
        return (model.ground(text, motion).similarity,
                model.ground(text, motion, method="attention").similarity,
                model.retrieve_texts(motion, candidates, top_k=3),
                model.retrieve_motions(text, [motion, generated.motion(1)]),
                model.generate(PROMPTS, [48, 32], generator=seeded()).features)

    expected = results()
    for stage in model.modules():
        stage.train()
    for seed in (0, 1):  # dropout would draw from the global generator
        torch.manual_seed(seed)
        for got, want in zip(results(), expected):
            assert torch.equal(got, want) if isinstance(want, torch.Tensor) else got == want
    assert all(stage.training for stage in model.modules())


def test_a_float64_default_dtype_changes_no_result(model, generated, bundle):
    """torch.set_default_dtype(torch.float64), common in scientific notebooks, before or
    after loading: the pipeline builds its tensors in float32 itself (was a dtype
    RuntimeError from nn.Linear in generate, ground and edit_text)."""
    def results(m):
        return (m.generate(PROMPTS, [48, 32], generator=seeded()).features,
                m.generate(PROMPTS, [48, 32], guidance="sink_ctrl", sampler="gumbel",
                           generator=seeded()).tokens,
                m.ground(PROMPTS[0], generated.motion(0)).similarity,
                m.ground(PROMPTS[0], generated.motion(0), method="attention").similarity,
                m.edit_text(generated, "a person walks forward, then jumps.").features,
                m.compose([("walk", 40), ("run", 40)], generator=seeded()).features,
                m.embed_pairs(PROMPTS, [generated.motion(0), generated.motion(1)])[1])

    expected = results(model)
    torch.set_default_dtype(torch.float64)
    try:
        after = results(model)
        before = results(SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM)))
    finally:
        torch.set_default_dtype(torch.float32)
    for got in (after, before):
        for value, want in zip(got, expected):
            assert value.dtype == want.dtype and torch.equal(value, want)


def test_no_alignment_head_is_a_clear_error(tmp_path, tokenizer_dir, generated):
    dirs = build_stages(tmp_path, tokenizer_dir["t2m"], alignment=False)
    plain = SegMo.from_stages(dirs["tokenizer"], dirs["mask"],
                              text_encoder=hash_encoder("hash", TEXT_DIM))
    assert plain.generate(PROMPTS[:1], [16], generator=seeded()).tokens.shape == (1, 4, 1)
    with pytest.raises(ValueError, match="without segment alignment.*method='attention'"):
        plain.ground(PROMPTS[0], generated.motion(0))
    # Attention grounding needs only the mask transformer: one ordered span per segment.
    motion = generated.motion(0)
    found = plain.ground(PROMPTS[0], motion, method="attention", segments=["walks", "waves"])
    spans = found.best_spans_frames
    assert len(spans) == 2 and spans[0][0] == 0 and spans[0][1] == spans[1][0] and spans[1][1] <= len(motion)


def test_segment_durations_steer_a_timing_model(tmp_path, tokenizer_dir, model):
    """A mask transformer with segment timing generates from given durations, from its
    head's prediction or from none; durations that do not fit get one line naming them."""
    dirs = build_stages(tmp_path, tokenizer_dir["t2m"], segment_timing=True)
    timed = SegMo.from_stages(dirs["tokenizer"], dirs["mask"], dirs["residual"],
                              text_encoder=hash_encoder("hash", TEXT_DIM))
    assert timed.sampling.segment_timing == "predicted"
    lengths = [64, 64]

    def tokens(**options):
        return timed.generate(PROMPTS, lengths, generator=seeded(), **options).tokens

    first = tokens(durations=[[1, 5], [1, 5]])
    assert torch.equal(first, tokens(durations=[[2, 10], [0.5, 2.5]]))  # shares, not units
    even = tokens(durations=[[1, 1], [1, 1]])  # beyond float32 (3.4e38) they were other spans
    assert torch.equal(even, tokens(durations=[[3e38, 3e38], [1e39, 1e39]]))
    assert not torch.equal(first, tokens(durations=[[5, 1], [5, 1]]))
    predicted = tokens()
    spans = timed.mask.predict_spans(*timed.text_condition(PROMPTS)[1:3], torch.tensor([16, 16]))
    shares = (spans[..., 1] - spans[..., 0]).tolist()
    assert torch.equal(predicted, tokens(durations=shares))
    assert not torch.equal(predicted, tokens(sampling=dataclasses.replace(
        timed.sampling, segment_timing="none")))
    with pytest.raises(SegmoError, match=r"durations\[1\] has 3 values, text 1 has 2 segments"):
        tokens(durations=[[1, 1], [1, 1, 1]])
    with pytest.raises(SegmoError, match=r"durations\[0\] must be finite"):
        tokens(durations=[[-1, 2], [1, 1]])
    with pytest.raises(SegmoError, match="one list per text"):
        tokens(durations=[[1, 1]])
    with pytest.raises(SegmoError, match="trained with segment timing"):
        model.generate(PROMPTS, lengths, durations=[[1, 1], [1, 1]])
    with pytest.raises(SegmoError, match="segment_timing must be 'predicted' or 'none'"):
        SamplingOptions(segment_timing="truth")
    # A text given None takes the head's durations, the others theirs (rows are independent).
    mixed = tokens(durations=[[1, 5], None])
    assert torch.equal(mixed[0], first[0]) and torch.equal(mixed[1], predicted[1])
    assert torch.equal(tokens(durations=[None, None]), predicted)

    # compose: a part may name its durations; the others are predicted.
    def long(*parts):
        return timed.compose(list(parts), 16, generator=seeded()).tokens

    plain = long((PROMPTS[0], 64), (PROMPTS[1], 64))
    assert torch.equal(plain, long((PROMPTS[0], 64, shares[0]), (PROMPTS[1], 64)))
    assert not torch.equal(long((PROMPTS[0], 64, [1, 5]), (PROMPTS[1], 64)),
                           long((PROMPTS[0], 64, [5, 1]), (PROMPTS[1], 64)))
    with pytest.raises(SegmoError, match=r"durations\[1\] has 1 values, text 1 has 2"):
        long((PROMPTS[0], 64), (PROMPTS[1], 64, [3]))
    with pytest.raises(SegmoError, match=r"\(text, frames\) or \(text, frames, durations\)"):
        long((PROMPTS[0], 64, [1, 5], "extra"))
    with pytest.raises(SegmoError, match="trained with segment timing"):
        model.compose([(PROMPTS[0], 64, [1, 5]), (PROMPTS[1], 64)])


def test_grounding_accuracy_on_builtin_corpus(model, tmp_path_factory):
    from segmo.synth.corpus import build_corpus

    root = build_corpus(tmp_path_factory.mktemp("corpus") / "c", 6, progress=False)
    # All five train motions: in corpus version 2 (seed 0) the first three have one segment
    # or more than the tiny model's max_segments.
    metrics = grounding_accuracy(model, root, split="train", max_motions=5)
    assert metrics["segments"] >= 2
    assert 0 <= metrics["rate"] <= 1 and 0 <= metrics["mIoU"] <= 1
    assert 0 <= metrics["uniform/mIoU"] <= 1


@pytest.fixture
def hash_text_encoder(monkeypatch):
    """The CLI builds the encoder named in the bundle: serve the hash encoder for it."""
    import segmo.text.encoders

    monkeypatch.setattr(segmo.text.encoders, "get_text_encoder",
                        lambda name, device="cpu": hash_encoder(name, TEXT_DIM))


def test_cli_generate_writes_npy_gif_bvh(bundle, tmp_path, hash_text_encoder, capsys):
    out = tmp_path / "gen"
    generate_main(["--model", str(bundle), "--text", PROMPTS[0], "--text", PROMPTS[1],
                   "--length", "16", "--seed", "3", "--out", str(out)])
    printed = capsys.readouterr().out
    for i in range(2):
        assert np.load(out / f"sample_{i:02d}_features.npy").shape == (16, 263)
        assert np.load(out / f"sample_{i:02d}_joints.npy").shape == (16, 22, 3)
        assert (out / f"sample_{i:02d}.gif").stat().st_size > 0
        text = (out / f"sample_{i:02d}.bvh").read_text()
        # at the animation rate: the 16 frames at 20 fps span 0.75 s, 46 frames at 60 fps
        assert text.startswith("HIERARCHY") and "Frames: 46" in text and "Frame Time: 0.016667" in text
    index = json.loads((out / "prompts.json").read_text())
    assert [e["text"] for e in index] == PROMPTS and str(out / "sample_00.gif") in printed
    assert np.load(out / "sample_00_tokens.npy").shape == (4, 3)
    # the same command and seed give the same motions
    generate_main(["--model", str(bundle), "--text", PROMPTS[0], "--text", PROMPTS[1],
                   "--length", "16", "--seed", "3", "--out", str(tmp_path / "again"),
                   "--formats", "npy"])
    for i in range(2):
        for what in ("tokens", "features"):
            assert np.array_equal(np.load(tmp_path / "again" / f"sample_{i:02d}_{what}.npy"),
                                  np.load(out / f"sample_{i:02d}_{what}.npy"))
    assert not (tmp_path / "again" / "sample_00.gif").exists()
    # the BVH at the motion's own frame rate
    generate_main(["--model", str(bundle), "--text", PROMPTS[0], "--length", "16", "--seed", "3",
                   "--out", str(tmp_path / "fps"), "--formats", "bvh", "--bvh-fps", "20",
                   "--no-foot-lock"])
    text = (tmp_path / "fps" / "sample_00.bvh").read_text()
    assert "Frames: 16" in text and "Frame Time: 0.050000" in text


@pytest.mark.parametrize("command", ["generate --text walk", "edit --source-text walk "
                                     "--target-text run", "compose --text walk --length 40"])
@pytest.mark.parametrize("fps", ["1e7", "1e-9", "481", "11"])
def test_cli_bvh_fps_out_of_range_is_refused_at_parsing(bundle, tmp_path, capsys, monkeypatch,
                                                         command, fps):
    """1e7 fps asked for 28.8 GiB, 1e-9 fps wrote a one-frame BVH; now refused before the
    model is loaded."""
    monkeypatch.setattr(SegMo, "from_pretrained", lambda *a, **k: pytest.fail("model loaded"))
    line = cli_failure([*command.split(), "--model", str(bundle), "--out", str(tmp_path / "o"),
                        "--bvh-fps", fps], capsys)
    assert "argument --bvh-fps: expected a frame rate in [12, 480] fps" in line, line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("fps", [1e-9, 1000.0])
def test_generation_output_save_refuses_a_bvh_fps_out_of_range(generated, tmp_path, fps):
    with pytest.raises(SegmoError, match=r"GenerationOutput.save: bvh_fps: expected a frame rate"):
        generated.save(tmp_path / "out", formats=("npy", "bvh"), bvh_fps=fps)
    assert not (tmp_path / "out").exists()  # refused before any file is written


def test_cli_compose_writes_one_long_motion(bundle, tmp_path, hash_text_encoder, capsys):
    from segmo.pipeline.cli import compose_main

    out = tmp_path / "long"
    compose_main(["--model", str(bundle), "--text", PROMPTS[0], "--length", "160", "--text",
                  PROMPTS[1], "--length", "120", "--transition", "16", "--out", str(out),
                  "--formats", "npy,bvh"])
    assert np.load(out / "sample_00_features.npy").shape == (296, 263)
    assert "Frames: 886" in (out / "sample_00.bvh").read_text()  # 296 frames at 60 fps
    line = cli_failure(["compose", "--model", str(bundle), "--text", "walk", "--text", "jump",
                        "--length", "40", "--out", str(tmp_path / "bad")], capsys)
    assert "--length given 1 times for 2 --text" in line
    two = ["compose", "--model", str(bundle), "--text", "walk", "--length", "40", "--text",
           "jump", "--length", "40", "--out", str(tmp_path / "bad")]
    assert "--durations given 1 times for 2 --text" in cli_failure(
        [*two, "--durations", "1"], capsys)
    assert "--durations '1,x': expected numbers" in cli_failure(
        [*two, "--durations", "auto", "--durations", "1,x"], capsys)
    # 'auto' everywhere is no durations at all: fine for a model without segment timing
    compose_main([*two[1:-1], str(tmp_path / "auto"), "--durations", "auto", "--durations",
                  "auto", "--formats", "npy"])
    assert np.load(tmp_path / "auto" / "sample_00_features.npy").shape == (100, 263)
    assert "trained with segment timing" in cli_failure(
        [*two, "--durations", "auto", "--durations", "1"], capsys)


@pytest.mark.parametrize("length", [4, 12])
def test_cli_generate_writes_a_gif_of_a_motion_too_short_to_ground_each_segment(
        bundle, tmp_path, hash_text_encoder, capsys, length):
    """The GIF's segment labels ground each segment on at least two tokens: a --length
    under that (3 tokens for two segments) failed after the generation and wrote nothing."""
    generate_main(["--model", str(bundle), "--text", PROMPTS[1], "--length", str(length),
                   "--out", str(tmp_path)])
    [entry] = json.loads((tmp_path / "prompts.json").read_text())
    assert len(entry["segments"]) == 2 and entry["frames"] == length
    assert _frames_of(tmp_path / "sample_00.gif") == length
    assert (tmp_path / "sample_00.bvh").is_file()


def _frames_of(gif: Path) -> int:
    from PIL import Image

    with Image.open(gif) as image:
        return image.n_frames


def test_cli_edit_writes_source_and_edit(bundle, tmp_path, hash_text_encoder, capsys):
    from segmo.pipeline.cli import edit_main

    out = tmp_path / "edit"
    edit_main(["--model", str(bundle), "--source-text", PROMPTS[0], "--target-text",
               PROMPTS[0], "--length", "24", "--seed", "2", "--out", str(out), "--formats", "npy"])
    # The same text: the edit is the source, token for token.
    assert np.array_equal(np.load(out / "edit_00_tokens.npy"), np.load(out / "source_00_tokens.npy"))
    edit_main(["--model", str(bundle), "--source-text", PROMPTS[0], "--mode", "reweight",
               "--weight", "1=1", "--length", "24", "--seed", "2", "--out", str(tmp_path / "w"),
               "--formats", "npy"])
    assert np.array_equal(np.load(tmp_path / "w" / "edit_00_tokens.npy"),
                          np.load(out / "source_00_tokens.npy"))
    for argv, message in (
            (["--mode", "reweight"], "--weight"), (["--mode", "swap"], "--target-text"),
            (["--mode", "reweight", "--weight", "jumps"], "SEGMENT=FACTOR"),
            (["--target-text", "x", "--inject-until", "2"], "--inject-until"),
            # each was ignored without a word: a reweight edits the source's text, every pass
            (["--mode", "reweight", "--weight", "1=2", "--inject-until", "0.2"],
             "--inject-until is for --mode swap, add and refine; --mode reweight edits every "
             "pass"),
            (["--mode", "reweight", "--weight", "1=2", "--target-text", "run"],
             "--target-text is for --mode swap, add and refine; --mode reweight edits the "
             "--source-text")):
        line = cli_failure(["edit", "--model", str(bundle), "--source-text", "walk",
                            "--out", str(tmp_path / "bad"), *argv], capsys)
        assert message in line


def test_cli_edit_lists_source_and_edit_in_one_prompts_json(bundle, tmp_path, hash_text_encoder,
                                                            capsys):
    """The edit's save overwrote the source's prompts.json, and printed it twice."""
    from segmo.pipeline.cli import edit_main

    out = tmp_path / "edit"
    edit_main(["--model", str(bundle), "--source-text", PROMPTS[0], "--target-text", PROMPTS[1],
               "--length", "24", "--out", str(out), "--formats", "npy"])
    printed = capsys.readouterr().out.split()
    index = json.loads((out / "prompts.json").read_text())
    assert [(e["file"], e["text"]) for e in index] == [("source_00", PROMPTS[0]),
                                                      ("edit_00", PROMPTS[1])]
    assert sorted(printed) == sorted(set(printed)) == sorted(str(p) for p in out.iterdir())


def test_a_save_writes_all_of_it_or_nothing_and_keeps_earlier_entries(bundle, tmp_path, monkeypatch):
    """A prompt holding "$x^$" failed in matplotlib's formula parser while the GIF was drawn,
    after the npy files had replaced the user's, and prompts.json lost the entries of every
    file an earlier save had left in the folder."""
    import segmo.pipeline.outputs as outputs

    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    out = tmp_path / "out"
    first = model.generate(["walk $x^$, then jump $\\alpha^$", PROMPTS[1]], [16, 16],
                           generator=torch.Generator().manual_seed(0))
    (out / ".save.tmp-999999999").mkdir(parents=True)  # of a killed save: no such process
    first.save(out, formats=("npy", "gif"))  # plain text in the title and segment labels
    assert not (out / ".save.tmp-999999999").exists()
    assert (out / "sample_00.gif").stat().st_size > 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    second = model.generate([PROMPTS[0]], [16], generator=torch.Generator().manual_seed(1))

    def broken(*args, **kwargs):
        raise RuntimeError("the GIF could not be drawn")

    with monkeypatch.context() as patch:
        patch.setattr(outputs, "save_animation", broken)
        with pytest.raises(RuntimeError):
            second.save(out, formats=("npy", "gif"))
        with pytest.raises(RuntimeError):
            second.save(tmp_path / "new", formats=("npy", "gif"))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing replaced, no leftovers
    assert not (tmp_path / "new").exists()
    second.save(out, formats=("npy",))
    index = json.loads((out / "prompts.json").read_text())
    assert [(e["file"], e["text"]) for e in index] == [("sample_01", PROMPTS[1]),
                                                      ("sample_00", PROMPTS[0])]
    assert sorted(p.name for p in out.iterdir()) == sorted(before)  # sample_01's files stay
    # A move that fails half-way puts back every file it had replaced.
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    moves, real_replace = [], os.replace

    def failing_replace(source, target):
        moves.append(source)
        if len(moves) == 4:
            raise OSError("disk full")
        return real_replace(source, target)

    with monkeypatch.context() as patch:
        patch.setattr(outputs.os, "replace", failing_replace)
        with pytest.raises(OSError, match="disk full"):
            model.generate([PROMPTS[1]], [16]).save(out, formats=("npy",))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # A folder where a file goes is refused before any work (it failed after the first moves).
    (out / "sample_00.bvh").mkdir()
    with pytest.raises(SegmoError, match=r"sample_00\.bvh: a folder where the save writes a file"):
        second.save(out, formats=("npy", "bvh"))
    (out / "sample_00.bvh").rmdir()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    (out / "prompts.json").write_text('{"mine": true}')
    with pytest.raises(SegmoError, match=r"prompts\.json: not a prompts\.json written by segmo"):
        second.save(out, formats=("npy",))
    assert (out / "prompts.json").read_text() == '{"mine": true}'


KILLED_SAVE = """
import os, sys, torch
sys.path.insert(0, {tests!r})
from conftest import hash_encoder
import segmo.pipeline.outputs as outputs
from segmo.pipeline import SegMo
model = SegMo.from_pretrained({bundle!r}, text_encoder=hash_encoder("hash", {dim}))
output = model.generate(["a person jumps"], [16], generator=torch.Generator().manual_seed(5))
real, calls = os.replace, []
def replace(source, target):
    calls.append(source)
    if len(calls) == 5:  # prompts.json and the features moved in, the joints not
        os._exit(9)
    return real(source, target)
outputs.os.replace = replace
output.save({out!r}, formats=("npy",))
"""


def test_a_save_killed_while_moving_its_files_in_is_rolled_back(bundle, tmp_path):
    """A save killed between two moves left a prompts.json naming 'a person jumps' beside
    the files of the earlier motion; the next save now puts the earlier files back."""
    import subprocess
    import sys

    from segmo.pipeline.outputs import save_outputs

    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    out = tmp_path / "out"
    model.generate([PROMPTS[0]], [16], generator=seeded()).save(out, formats=("npy",))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    script = KILLED_SAVE.format(tests=str(Path(__file__).parent), bundle=str(bundle),
                                dim=TEXT_DIM, out=str(out))
    assert subprocess.run([sys.executable, "-c", script]).returncode == 9
    stage = [p for p in out.iterdir() if p.name.startswith(".save.tmp-")]
    assert len(stage) == 1 and (out / "sample_00_features.npy").read_bytes() != before[
        "sample_00_features.npy"]  # the half-done state the kill left
    other = model.generate([PROMPTS[1]], [16], generator=seeded())
    save_outputs(out, {"other": other}, formats=("npy",))
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {k: v for k, v in after.items() if k != "prompts.json" and not k.startswith("other")} \
        == {k: v for k, v in before.items() if k != "prompts.json"}
    index = json.loads((out / "prompts.json").read_text())
    assert [(e["file"], e["text"]) for e in index] == [("sample_00", PROMPTS[0]),
                                                      ("other_00", PROMPTS[1])]


def test_a_stopped_save_keeps_what_another_wrote_into_the_folder_it_made(bundle, tmp_path,
                                                                         monkeypatch):
    """Two `segmo generate` into one new --out: Ctrl-C of the first deleted the folder it
    had made, with the files the second had finished in it."""
    import segmo.pipeline.outputs as outputs

    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    out = tmp_path / "new"
    other = model.generate([PROMPTS[1]], [16], generator=seeded())

    def meanwhile(*args, **kwargs):
        outputs.save_outputs(out, {"other": other}, formats=("npy",))  # finishes first
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "save_animation", meanwhile)
    with pytest.raises(KeyboardInterrupt):
        model.generate([PROMPTS[0]], [16], generator=seeded()).save(out, formats=("npy", "gif"))
    assert sorted(p.name for p in out.iterdir()) == [
        "other_00_features.npy", "other_00_joints.npy", "other_00_tokens.npy", "prompts.json"]


def test_a_save_does_not_replace_a_file_no_save_wrote(bundle, tmp_path):
    """`segmo compose --out u` replaced the user's u/sample_00.bvh: only a prompts.json not
    segmo's was refused. A save replaces the files of the motions an earlier save listed."""
    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    out = tmp_path / "u"
    out.mkdir()
    (out / "sample_00.bvh").write_text("my notes")
    output = model.generate([PROMPTS[0]], [16], generator=torch.Generator().manual_seed(0))
    with pytest.raises(SegmoError, match=r"sample_00\.bvh: a file that segmo did not write"):
        output.save(out, formats=("npy", "bvh"))
    assert [p.name for p in out.iterdir()] == ["sample_00.bvh"]
    assert (out / "sample_00.bvh").read_text() == "my notes"
    (out / "sample_00.bvh").rename(out / "notes.bvh")
    output.save(out, formats=("npy", "bvh"))
    output.save(out, formats=("npy", "bvh"))  # its own files, listed: replaced
    assert (out / "notes.bvh").read_text() == "my notes"
    assert [e["file"] for e in json.loads((out / "prompts.json").read_text())] == ["sample_00"]


def test_a_save_owns_the_files_it_wrote_not_every_file_of_its_motions_name(bundle, tmp_path):
    """A save of the npy files listed 'sample_00', so a later save with BVH replaced the
    user's sample_00.bvh put there between the two; one that wrote no file claimed all."""
    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    output = model.generate([PROMPTS[0]], [16], generator=torch.Generator().manual_seed(0))
    out = tmp_path / "u"
    output.save(out, formats=("npy",))
    (out / "sample_00.bvh").write_text("my hand-edited take")
    with pytest.raises(SegmoError, match=r"sample_00\.bvh: a file that segmo did not write"):
        output.save(out, formats=("npy", "bvh"))
    assert (out / "sample_00.bvh").read_text() == "my hand-edited take"
    (out / "sample_00.bvh").unlink()
    output.save(out, formats=("bvh",))  # the npy files of the first save stay listed
    output.save(out, formats=("npy", "bvh"))
    [entry] = json.loads((out / "prompts.json").read_text())
    assert entry["files"] == ["sample_00.bvh", "sample_00_features.npy", "sample_00_joints.npy",
                              "sample_00_tokens.npy"]
    empty = tmp_path / "empty"
    output.save(empty, formats=())
    (empty / "sample_00.gif").write_text("mine")
    with pytest.raises(SegmoError, match=r"sample_00\.gif: a file that segmo did not write"):
        output.save(empty, formats=("gif",))


def test_a_save_before_files_were_listed_owns_every_format_of_its_motion(bundle, tmp_path):
    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    output = model.generate([PROMPTS[0]], [16], generator=torch.Generator().manual_seed(0))
    out = tmp_path / "old"
    output.save(out, formats=("bvh",))
    entries = json.loads((out / "prompts.json").read_text())
    (out / "prompts.json").write_text(json.dumps([{k: v for k, v in e.items() if k != "files"}
                                                  for e in entries]))
    output.save(out, formats=("bvh",))
    assert json.loads((out / "prompts.json").read_text())[0]["files"] == ["sample_00.bvh"]


@pytest.mark.parametrize("prefix", ["x/y", "../p", "a\\b", "nul\0"])
def test_a_save_refuses_a_prefix_that_is_no_part_of_a_file_name(bundle, tmp_path, prefix):
    """prefix "x/y" moved x/y_00.bvh over the user's DIR/y_00.bvh without the check;
    "../p" wrote outside the stage folder and failed with a FileNotFoundError."""
    model = SegMo.from_pretrained(bundle, text_encoder=hash_encoder("hash", TEXT_DIM))
    output = model.generate([PROMPTS[0]], [16], generator=torch.Generator().manual_seed(0))
    out = tmp_path / "dir" / "sub"
    out.mkdir(parents=True)
    (out / "y_00.bvh").write_text("mine")
    with pytest.raises(SegmoError, match=r"prefix .* must be part of a file name"):
        output.save(out, formats=("npy", "bvh"), prefix=prefix)
    assert [p.name for p in tmp_path.rglob("*")] == ["dir", "sub", "y_00.bvh"]


def test_cli_generate_help_names_the_bundle_for_the_defaults_it_records(capsys):
    """An unset sampling option takes the bundle's value (segmo.json), so its help must not
    promise SamplingOptions' default (--steps said "default 10"; the demo bundle has 4)."""
    with pytest.raises(SystemExit):
        generate_main(["--help"])
    helps: dict[str, str] = {}  # option → its help, continuation lines joined
    flag = None
    for line in capsys.readouterr().out.splitlines():
        if line.startswith("  -"):
            flag = line.split()[0]
            helps[flag] = line
        elif flag is not None and line.startswith("    "):
            helps[flag] += line
    for flag in ("--guidance", "--residual-guidance", "--guidance-mode", "--steps",
                 "--residual-guided-layers", "--word-text"):
        assert "bundle" in helps[flag], helps[flag]


@pytest.mark.parametrize("argv, message", [
    (["--model", "/nonexistent/model"], "--model /nonexistent/model: no such directory"),
    (["--length", "30"], "multiples of 4"),
    (["--formats", "npy,mp3"], "--formats"),
    (["--durations", "1,x"], "--durations '1,x': expected numbers >= 0"),
    (["--durations", "0,0"], "not all 0"),
    (["--durations", "1,4"], "durations need a mask transformer trained with segment timing"),
    (["--durations", "auto,1"], "--durations 'auto,1': expected numbers >= 0"),
])
def test_cli_generate_errors(bundle, tmp_path, hash_text_encoder, capsys, argv, message):
    base = {"--model": str(bundle), "--text": "a person walks", "--out": str(tmp_path)}
    for flag, value in zip(argv[::2], argv[1::2]):
        base[flag] = value
    line = cli_failure(["generate", *[x for kv in base.items() for x in kv]], capsys)
    assert line.startswith("segmo generate: ") and message in line


def test_cli_ground_prints_spans(bundle, generated, tmp_path, hash_text_encoder, capsys):
    motion = tmp_path / "motion.npy"
    np.save(motion, generated.motion(0))
    ground_main(["--model", str(bundle), "--text", PROMPTS[0], "--motion", str(motion),
                 "--window", "4", "--out", str(tmp_path / "map.png")])
    printed = capsys.readouterr().out
    assert "a person walks forward" in printed and "a person waves" in printed
    assert printed.count("frames ") == 2 and (tmp_path / "map.png").stat().st_size > 0
    ground_main(["--model", str(bundle), "--text", PROMPTS[0], "--motion", str(motion),
                 "--method", "attention", "--out", str(tmp_path / "attention.png")])
    printed = capsys.readouterr().out
    assert printed.count(" att ") == 2 and (tmp_path / "attention.png").stat().st_size > 0
    line = cli_failure(["ground", "--model", str(bundle), "--text", "x", "--motion", str(motion),
                        "--method", "heat"], capsys)
    assert "argument --method" in line
    np.save(tmp_path / "joints.npy", generated.motion_joints(0))
    line = cli_failure(["ground", "--model", str(bundle), "--text", "x", "--motion",
                        str(tmp_path / "joints.npy")], capsys)
    assert "joints" in line
    line = cli_failure(["ground", "--model", str(bundle), "--text", "x", "--motion", str(motion),
                        "--search", "spans", "--window", "5"], capsys)
    assert "--window is for --search window, not --search spans" in line


def test_cli_ground_checks_out_before_grounding(bundle, generated, tmp_path, hash_text_encoder,
                                                capsys, monkeypatch):
    """--out map.txt failed in matplotlib after the grounding; --out DIR wrote DIR.png and
    printed DIR."""
    motion = tmp_path / "motion.npy"
    np.save(motion, generated.motion(0))
    ground = ["ground", "--model", str(bundle), "--text", PROMPTS[0], "--motion", str(motion)]
    with monkeypatch.context() as patch:
        patch.setattr(SegMo, "from_pretrained", lambda *a, **k: pytest.fail("model loaded"))
        for out, problem in ((tmp_path / "map.txt", "name an image file ending in .png, .pdf"),
                             (tmp_path / "map", "name an image file ending in .png, .pdf"),
                             (tmp_path, "is a directory")):
            line = cli_failure([*ground, "--out", str(out)], capsys)
            assert line.startswith(f"segmo ground: --out {out}: {problem}"), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion.npy"]
    ground_main([*ground[1:], "--out", str(tmp_path / "maps" / "map.SVG")])
    assert f"similarity map: {tmp_path / 'maps' / 'map.SVG'}\n" in capsys.readouterr().out
    assert (tmp_path / "maps" / "map.SVG").read_text().lstrip().startswith("<?xml")


def test_cli_ground_never_writes_through_a_link_or_over_a_file(bundle, generated, tmp_path,
                                                               hash_text_encoder, capsys,
                                                               monkeypatch):
    """--out map.png, a link to the user's thesis.txt, turned the thesis into a PNG; an
    existing file was overwritten without a word, in place (a killed run left half an image).
    Both are refused before any work; with --overwrite the link itself is replaced."""
    motion = tmp_path / "motion.npy"
    np.save(motion, generated.motion(0))
    thesis = tmp_path / "thesis.txt"
    thesis.write_text("my thesis\n")
    (tmp_path / "map.png").symlink_to("thesis.txt")
    (tmp_path / "gone.png").symlink_to("nowhere.png")
    (tmp_path / "old.png").write_bytes(b"my old map")
    ground = ["ground", "--model", str(bundle), "--text", PROMPTS[0], "--motion", str(motion)]
    with monkeypatch.context() as patch:
        patch.setattr(SegMo, "from_pretrained", lambda *a, **k: pytest.fail("model loaded"))
        for name, problem in (("map.png", "a symbolic link to thesis.txt"),
                              ("gone.png", "a symbolic link to nowhere.png"),
                              ("old.png", "exists")):
            line = cli_failure([*ground, "--out", str(tmp_path / name)], capsys)
            assert line.startswith(f"segmo ground: --out {tmp_path / name}: {problem}; pass "
                                   "--overwrite to replace it"), line
    assert thesis.read_text() == "my thesis\n"
    assert (tmp_path / "old.png").read_bytes() == b"my old map"
    for name in ("map.png", "gone.png", "old.png"):
        ground_main([*ground[1:], "--out", str(tmp_path / name), "--overwrite"])
        assert not (tmp_path / name).is_symlink()
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    assert thesis.read_text() == "my thesis\n" and not (tmp_path / "nowhere.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [  # no temporary file left
        "gone.png", "map.png", "motion.npy", "old.png", "thesis.txt"]


def test_generation_output_save_rejects_unknown_format(generated, tmp_path):
    assert isinstance(generated, GenerationOutput)
    with pytest.raises(ValueError, match="unknown format"):
        generated.save(tmp_path, formats=("npy", "fbx"))


def test_cli_bundle_options_and_errors(stages, tmp_path, capsys):
    out = tmp_path / "b"
    bundle_main(["--tokenizer", str(stages["tokenizer"]), "--mask", str(stages["mask"]),
                 "--guidance", "2.5", "--steps", "6", "--residual-guided-layers", "2",
                 "--guidance-mode", "sink_ctrl", "--sink-ratio", "0.6", "--unconditional", "local",
                 "--word-text", "segments", "--ctrl-k-base", "0.25", "--ctrl-lambda", "3", "--ctrl-alpha", "0.5",
                 "--remasking", "segments", "--choice-temperature", "4.5", "--out", str(out)])
    payload = json.loads((out / "segmo.json").read_text())
    assert payload["guidance_scale"] == 2.5 and not (out / "residual").exists()
    assert payload["steps"] == 6 and payload["residual_guided_layers"] == 2
    loaded = SegMo.from_pretrained(out)
    assert (loaded.sampling.steps, loaded.sampling.residual_guided_layers) == (6, 2)
    assert (loaded.sampling.guidance, loaded.sampling.sink_ratio) == ("sink_ctrl", 0.6)
    assert (loaded.sampling.unconditional, loaded.sampling.word_text) == ("local", "segments")
    assert loaded.sampling.remasking == "segments"
    assert payload["choice_temperature"] == 4.5 and loaded.sampling.choice_temperature == 4.5
    assert (loaded.sampling.ctrl_k_base, loaded.sampling.ctrl_lambda,
            loaded.sampling.ctrl_alpha) == (0.25, 3.0, 0.5)
    assert "6 decoding steps" in (out / "README.md").read_text()
    line = cli_failure(["bundle", "--tokenizer", str(stages["tokenizer"]), "--mask",
                        str(stages["tokenizer"]), "--out", str(tmp_path / "c")], capsys)
    assert "holds a 'rvq' model" in line
    line = cli_failure(["bundle", "--tokenizer", str(tmp_path / "none"), "--mask",
                        str(stages["mask"]), "--out", str(tmp_path / "d")], capsys)
    assert "--tokenizer" in line and "no such directory" in line


def test_cli_bundle_refuses_a_tokenizer_other_than_the_stages_were_trained_with(
        stages, tmp_path, capsys):
    """A tokenizer of the same config but other codebooks made garbage motions: the stages
    record the digest of theirs, and `segmo bundle` compares it; stages exported before
    (no digest) are bundled as before."""
    from segmo.data.motion_tokens import tokenizer_digest
    from segmo.models.pretrained import load_pretrained

    tokenizer = load_pretrained(stages["tokenizer"])
    other = load_pretrained(stages["tokenizer"])
    with torch.no_grad():
        for parameter in other.parameters():
            parameter.add_(0.5)
    other.save_pretrained(tmp_path / "other_rvq")
    assert tokenizer_digest(other) != tokenizer_digest(tokenizer)
    for name in ("mask", "residual"):
        model = load_pretrained(stages[name])
        model.save_pretrained(tmp_path / name, meta={"tokenizer_digest": tokenizer_digest(tokenizer)})
    argv = ["bundle", "--mask", str(tmp_path / "mask"), "--residual", str(tmp_path / "residual")]
    line = cli_failure([*argv, "--tokenizer", str(tmp_path / "other_rvq"), "--out",
                        str(tmp_path / "b")], capsys)
    assert "mask stage was trained with the tokenizer" in line and str(stages["tokenizer"]) in line
    assert "other_rvq" in line and not (tmp_path / "b").exists()
    bundle_main([*argv[1:], "--tokenizer", str(stages["tokenizer"]), "--out", str(tmp_path / "b")])
    bundle_main(["--mask", str(stages["mask"]), "--tokenizer", str(tmp_path / "other_rvq"),
                 "--out", str(tmp_path / "old")])  # no digest recorded: as before
    assert SegMo.from_pretrained(tmp_path / "b").residual is not None


def test_cli_bundle_into_an_existing_folder(stages, tmp_path, capsys):
    """Writing the same bundle again works; a folder holding what the new bundle would not
    write back (an earlier bundle's stages, the user's files) is refused untouched without
    --overwrite, and replaced whole with it, so no stale stage is loaded."""
    out = tmp_path / "b"
    two = ["--tokenizer", str(stages["tokenizer"]), "--mask", str(stages["mask"]), "--out", str(out)]
    four = [*two, "--residual", str(stages["residual"]), "--length", str(stages["length"])]
    bundle_main(four)
    bundle_main(four)
    line = cli_failure(["bundle", *two], capsys)
    assert "holds another bundle and length, residual, which this bundle would delete" in line
    assert "--overwrite" in line and SegMo.from_pretrained(out).residual is not None
    bundle_main([*two, "--overwrite"])
    assert sorted(p.name for p in out.iterdir()) == ["README.md", "mask", "segmo.json", "tokenizer"]
    loaded = SegMo.from_pretrained(out)
    assert loaded.residual is None and loaded.length is None
    (out / "mask" / "notes.txt").write_text("mine\n")
    line = cli_failure(["bundle", *two], capsys)
    assert "mask/notes.txt" in line and (out / "mask" / "notes.txt").is_file()
    user = tmp_path / "user"
    user.mkdir()
    (user / "README.md").write_text("mine\n")
    line = cli_failure(["bundle", *two[:4], "--out", str(user)], capsys)
    assert "is not empty and holds no segmo.json" in line and "--overwrite" in line
    assert (user / "README.md").read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b", "user"]  # no temporary left


def test_cli_bundle_records_segment_guidance(stages, tmp_path, hash_text_encoder, capsys):
    out = tmp_path / "b"
    bundle_main(["--tokenizer", str(stages["tokenizer"]), "--mask", str(stages["mask"]),
                 "--segment-guidance", "1.5", "--out", str(out)])
    assert json.loads((out / "segmo.json").read_text())["segment_guidance"] == 1.5
    model = SegMo.from_pretrained(out)
    assert model.sampling.segment_guidance == 1.5
    assert model.generate(["a person walks forward, then waves"], [16]).tokens.shape[:2] == (1, 4)
    line = cli_failure(["bundle", "--tokenizer", str(stages["tokenizer"]), "--mask",
                        str(stages["mask"]), "--segment-guidance", "-1", "--out",
                        str(tmp_path / "c")], capsys)
    assert "--segment-guidance" in line and "expected a number >= 0" in line
    line = cli_failure(["bundle", "--tokenizer", str(stages["tokenizer"]), "--mask",
                        str(stages["mask"]), "--segment-guidance", "1", "--guidance-mode",
                        "sink_ctrl", "--out", str(tmp_path / "d")], capsys)
    assert "segment_guidance works with guidance 'cfg' only" in line


def test_ground_cli_finds_the_true_spans_of_a_corpus_caption(tmp_path):
    from segmo.pipeline.cli import _true_spans

    (tmp_path / "new_joint_vecs").mkdir()
    (tmp_path / "segments").mkdir()
    motion = tmp_path / "new_joint_vecs" / "000007.npy"
    np.save(motion, np.zeros((40, 263), np.float32))
    caption = {"text": "A man walks, then waves.", "segments": [
        {"text": "a man walks", "action": "walk", "start": 0, "end": 24},
        {"text": "a man waves", "action": "wave", "start": 24, "end": 40}]}
    (tmp_path / "segments" / "000007.json").write_text(json.dumps({"captions": [caption]}))
    assert _true_spans(motion, "a man walks,  then waves", ["a man walks", "a man waves"]) == [(0, 24), (24, 40)]
    assert _true_spans(motion, "a man runs", ["a man runs"]) is None  # another caption
    assert _true_spans(motion, "a man walks, then waves.", ["a man walks then waves"]) is None
    assert _true_spans(tmp_path / "elsewhere.npy", "a man walks, then waves.", ["a", "b"]) is None


def test_saved_joints_gif_and_bvh_are_one_skeleton(model, generated, tmp_path):
    """A random model's joints stretch their bones; the files of a sample show the fixed
    skeleton fitted to them, so a BVH reader's forward kinematics gives the joints file."""
    pybvh = pytest.importorskip("pybvh", reason="the `pybvh` reader (dev extra) is not installed")
    from segmo.motion import T2M

    generated.save(tmp_path / "fixed", formats=("npy", "bvh"))
    joints = np.load(tmp_path / "fixed" / "sample_00_joints.npy")
    mocap = pybvh.read_bvh_file(str(tmp_path / "fixed" / "sample_00.bvh"))
    names = list(mocap.joint_names)
    read = mocap.joint_positions()[:, [names.index(n) for n in T2M.joint_names]]
    assert len(read) == 3 * (len(joints) - 1) + 1  # written at 60 fps, the motion's frames kept
    assert np.linalg.norm(read[::3] - joints, axis=-1).max() < 0.001
    lengths = np.linalg.norm(joints[:, 1:] - joints[:, list(T2M.parents[1:])], axis=-1)
    assert np.allclose(lengths, np.asarray(T2M.reference_bone_lengths[1:]), atol=1e-5)
    generated.save(tmp_path / "raw", formats=("npy",), fixed_skeleton=False)
    assert np.array_equal(np.load(tmp_path / "raw" / "sample_00_joints.npy"), generated.motion_joints(0))
