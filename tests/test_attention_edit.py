"""Editing by attention (SALAD's zero-shot edits): `segmo.models.attention_control`,
`segmo.generation.attention_edit` and `SegMo.edit_text`, on tiny random models."""

from __future__ import annotations

import dataclasses
import functools
import re

import numpy as np
import pytest
import torch
from conftest import hash_encoder
from test_pipeline import TEXT_DIM, build_stages

from segmo.errors import SegmoError
from segmo.generation import SamplingOptions, generate_tokens
from segmo.generation.attention_edit import (
    INJECT_UNTIL,
    TextSide,
    attention_edit_tokens,
    inject,
    segment_counterparts,
    source_attention,
)
from segmo.models.attention_control import AttentionControl, Site, Stored
from segmo.models.cpu_inference import use_cpu_kernels
from segmo.models.mask_transformer import MaskTransformer, MaskTransformerConfig
from segmo.models.residual_transformer import ResidualTransformer, ResidualTransformerConfig
from segmo.pipeline import SegMo

TINY = dict(codebook_size=16, text_dim=8, max_segments=3, max_tokens=12, dim=32, depth=2,
            heads=2, ff_dim=64, dropout=0.1)


@pytest.fixture(scope="module")
def models():
    torch.manual_seed(0)
    mask = use_cpu_kernels(MaskTransformer(MaskTransformerConfig(**TINY)))
    residual = use_cpu_kernels(ResidualTransformer(ResidualTransformerConfig(**TINY,
                                                                             num_quantizers=3)))
    with torch.no_grad():  # sharper logits, a stronger text prefix and peaked attention,
        mask.classifier.weight.mul_(10)  # so that the text and the attention weights matter
        residual.code_embeddings.mul_(10)
        for model in (mask, residual):
            model.prefix.project.weight.mul_(50)
            for block in model.trunk.blocks:
                block.attention.qkv.weight.mul_(4)
    return mask, residual


def side(seed: int, b: int = 2) -> TextSide:
    g = torch.Generator().manual_seed(seed)
    segment_mask = torch.ones(b, 3, dtype=torch.bool)
    segment_mask[0, 2] = False
    return TextSide(torch.randn(b, 8, generator=g), torch.randn(b, 3, 8, generator=g),
                    segment_mask)


LENGTHS = torch.tensor([48, 36])
STATE = torch.Generator().manual_seed(7).get_state()


def plain(models, text: TextSide, steps: int = 10) -> torch.Tensor:
    mask, residual = models
    return generate_tokens(mask, residual, text.sentence, text.segments, text.segment_mask,
                           LENGTHS, options=SamplingOptions(steps=steps),
                           generator=torch.Generator().set_state(STATE))


def edited(models, source, target, **kwargs):
    return attention_edit_tokens(*models, source, target, LENGTHS, generator_state=STATE,
                                 **kwargs)[0]


def test_the_same_text_reproduces_the_source_bit_for_bit(models):
    source = side(1)
    for until in (0.0, 0.5, 1.0):
        assert torch.equal(edited(models, source, source, inject_until=until),
                           plain(models, source))


def test_inject_until_zero_is_plain_generation_from_the_target(models):
    source, target = side(1), side(2)
    assert torch.equal(edited(models, source, target, inject_until=0.0), plain(models, target))


def test_injection_changes_the_target(models):
    source, target = side(1), side(2)
    src, tgt = plain(models, source), plain(models, target)
    assert not torch.equal(src, tgt)
    # The source's weights with the target's values: neither the source nor the target.
    full = edited(models, source, target, inject_until=1.0)
    assert not torch.equal(full, tgt) and not torch.equal(full, src)


def test_reweight_by_one_changes_nothing_and_by_four_changes_tokens(models):
    source = side(1)
    base = plain(models, source)
    one = edited(models, source, source, mode="reweight", reweight=[{"segment 1": 1.0}] * 2)
    assert torch.equal(one, base)
    four = edited(models, source, source, mode="reweight", reweight=[{"segment 1": 4.0}] * 2)
    assert not torch.equal(four, base)
    with pytest.raises(ValueError, match="inject_until is for modes"):  # it would be ignored
        edited(models, source, source, mode="reweight", reweight=[{"segment 1": 4.0}] * 2,
               inject_until=0.5)


def test_editing_weights_reach_the_attention(models):
    # The edit function's weights are what the values are multiplied by.
    mask, residual = models
    control = AttentionControl({"mask": mask, "residual": residual})
    seen: list[Site] = []

    def zero_motion(site, weights, stored):
        seen.append(site)
        keep = torch.tensor([not label.startswith("motion ") for label in site.labels])
        return weights * keep
    with control.editing(zero_motion):
        a = plain(models, side(1), steps=4)
    assert {s.stage for s in seen} == {"mask", "residual"}
    # 4 mask steps and 2 residual layers, 2 blocks each: one pass per step while controlled.
    assert sorted({(s.stage, s.step) for s in seen}) == [
        ("mask", 0), ("mask", 1), ("mask", 2), ("mask", 3), ("residual", 0), ("residual", 1)]
    assert not torch.equal(a, plain(models, side(1), steps=4))
    assert "forward_motion" not in mask.trunk.__dict__  # unwrapped afterwards


def test_inject_takes_source_weights_only_where_there_is_a_counterpart():
    c, heads, n = 1, 1, 3
    labels = ["sentence", "segment 1", "segment 2", *(f"motion {i}" for i in range(n))]
    target = torch.full((2, heads, n, len(labels)), 0.5)
    stored = Stored(weights=torch.full((c, heads, n, 4), 0.25),
                    queries=None, key_valid=torch.tensor([[True, True, False, True]]),
                    labels=["sentence", "segment 1", "segment 2", "motion 0"])
    key_index = torch.tensor([[0, 1, 2, 3, -1, -1]])  # motions 1, 2: no counterpart
    site = Site("mask", 0, 0, labels, None, conditional=c)
    out = inject(site, target, stored, key_index)
    assert torch.equal(out[0, 0, :, [0, 1, 3]], torch.full((n, 3), 0.25))
    assert torch.equal(out[0, 0, :, [2, 4, 5]], torch.full((n, 3), 0.5))  # invalid, none
    assert torch.equal(out[1], target[1])  # unconditional rows keep their own


def test_segment_counterparts():
    assert segment_counterparts(["walk", "jump"], ["walk", "kick"], "swap") == {1: 1, 2: 2}
    # An added segment has no counterpart; the kept ones keep theirs.
    assert segment_counterparts(["walk", "jump"], ["walk", "wave", "jump"], "add") == {1: 1, 3: 2}
    # A refined text is the one in its place.
    assert segment_counterparts(["walk", "jump"], ["walk quickly", "jump"], "refine") == {1: 1, 2: 2}


@pytest.fixture(scope="module")
def segmo_model(tmp_path_factory, tokenizer_dir):
    stages = build_stages(tmp_path_factory.mktemp("edit"), tokenizer_dir["t2m"])
    model = SegMo.from_stages(stages["tokenizer"], stages["mask"], stages["residual"],
                              stages["length"], text_encoder=hash_encoder("hash", TEXT_DIM))
    with torch.no_grad():  # a stronger text prefix and peaked attention: the text matters
        for transformer in (model.mask, model.residual):
            transformer.prefix.project.weight.mul_(50)
            for block in transformer.trunk.blocks:
                block.attention.qkv.weight.mul_(4)
    return model


def test_edit_text_through_the_pipeline(segmo_model):
    model = segmo_model
    g = torch.Generator().manual_seed(3)
    source = model.generate(["a person walks forward, then jumps.", "someone waves, then sits"],
                            [48, 40], generator=g)
    same = model.edit_text(source, list(source.texts))
    assert torch.equal(same.tokens, source.tokens)
    one = model.edit_text(source, mode="reweight", weights={1: 1.0})
    assert torch.equal(one.tokens, source.tokens)
    swapped = model.edit_text(source, "a person walks forward, then kicks.")
    assert swapped.texts[0] == "a person walks forward, then kicks."
    assert swapped.tokens.shape == source.tokens.shape
    # keep_outside: tokens outside the segment's attended span stay the source's.
    kept = model.edit_text(source, ["a person walks forward, then kicks.",
                                    "someone claps, then sits"], keep_outside=True)
    changed = (kept.tokens != source.tokens).any(dim=2)
    assert changed.any()
    for row in range(2):
        where = torch.nonzero(changed[row]).flatten()
        if len(where):  # the changed tokens form one span
            assert int(where.max() - where.min()) + 1 <= int(source.lengths[row]) // 4


def test_edit_text_replays_the_durations_of_its_source(tmp_path, tokenizer_dir):
    """A source generated with segment durations was replayed without them: the same text
    or a reweight by 1 gave a generation without durations, and keep_outside's span came
    from that generation's attention."""
    stages = build_stages(tmp_path, tokenizer_dir["t2m"], segment_timing=True)
    model = SegMo.from_stages(stages["tokenizer"], stages["mask"], stages["residual"],
                              text_encoder=hash_encoder("hash", TEXT_DIM))
    texts = ["a person walks forward, then jumps.", "someone waves, then sits"]

    def generate(texts, durations=None):
        return model.generate(texts, [64, 64], generator=torch.Generator().manual_seed(0),
                              durations=durations)

    source = generate(texts, [[1, 5], [5, 1]])
    assert not torch.equal(source.tokens, generate(texts).tokens)  # the durations matter
    assert torch.equal(model.edit_text(source, list(texts)).tokens, source.tokens)
    one = model.edit_text(source, mode="reweight", weights={1: 1.0})
    assert torch.equal(one.tokens, source.tokens)
    # A target with as many segments keeps the source's durations, one with a segment
    # added has its head's (inject_until=0 is plain generation from the target).
    swapped = ["a person walks forward, then kicks.", "someone waves, then sits, then bows"]
    plain = model.edit_text(source, swapped, inject_until=0.0)
    assert torch.equal(plain.tokens, generate(swapped, [[1, 5], None]).tokens)
    # keep_outside's span comes from the source's attention, replayed with its durations.
    side = TextSide(*model.text_condition(texts)[:3], durations=source.durations)
    replayed = source_attention(model.mask, model.residual, side, source.lengths,
                                options=source.sampling, generator_state=source.generator_state)
    control = AttentionControl({"mask": model.mask, "residual": model.residual})
    with control.storing():
        generate_tokens(model.mask, model.residual, side.sentence, side.segments,
                        side.segment_mask, source.lengths, options=source.sampling,
                        generator=torch.Generator().set_state(source.generator_state),
                        durations=source.durations)
    assert control.stored.keys() == replayed.stored.keys()
    assert all(torch.equal(control.stored[k].weights, replayed.stored[k].weights)
               for k in control.stored)


@pytest.mark.filterwarnings("ignore:bf16 on this CPU runs in torch's reference kernels")
def test_edit_text_replays_the_precision_of_its_source(segmo_model):
    """A bf16 source was replayed at edit_text's own "auto" (fp32 on a CPU without native
    bf16, and the other way round on one with it): the same text was not the source."""
    model = segmo_model
    texts = ["a person walks forward, then jumps.", "someone waves, then sits"]
    source = model.generate(texts, [48, 40], generator=torch.Generator().manual_seed(3),
                            precision="bf16")
    assert torch.equal(model.edit_text(source, texts).tokens, source.tokens)
    assert source.precision == "bf16"
    assert model.generate(texts, [48, 40], precision="fp32").precision == "fp32"
    # An explicit precision runs as asked.
    fp32 = model.generate(texts, [48, 40], generator=torch.Generator().manual_seed(3),
                          precision="fp32")
    assert not torch.equal(fp32.tokens, source.tokens)  # the precision matters here
    assert torch.equal(model.edit_text(source, texts, precision="fp32").tokens, fp32.tokens)


def test_edit_text_refuses_what_it_cannot_do(segmo_model):
    model = segmo_model
    source = model.generate(["a person walks, then jumps."], [40],
                            generator=torch.Generator().manual_seed(0))
    with pytest.raises(SegmoError, match="mode"):
        model.edit_text(source, "x", mode="mirror")
    with pytest.raises(SegmoError, match="needs a target_text"):
        model.edit_text(source, mode="swap")
    with pytest.raises(SegmoError, match="weights"):
        model.edit_text(source, mode="reweight")
    with pytest.raises(SegmoError, match="names no segment"):
        model.edit_text(source, mode="reweight", weights={"dances": 2.0})
    with pytest.raises(SegmoError, match="finite float32 number, got 1e"):
        model.edit_text(source, mode="reweight", weights={1: 1e308})  # inf in float32
    with pytest.raises(SegmoError, match="weights must be a dict .* got list"):
        model.edit_text(source, mode="reweight", weights=[(1, 2.0)])
    with pytest.raises(SegmoError, match="inject_until"):
        model.edit_text(source, "a person runs, then jumps.", inject_until=1.5)
    # Each was taken without a word: the last factor of a segment won, "no" was True, and
    # fp16 was a ValueError from the sampler.
    with pytest.raises(SegmoError, match=r"weights keys 1 and 'a person walks' both name segment 1"):
        model.edit_text(source, mode="reweight", weights={1: 2.0, "a person walks": 0.5})
    with pytest.raises(SegmoError, match="keep_outside must be True or False, got 'no'"):
        model.edit_text(source, "a person walks, then kicks.", keep_outside="no")
    with pytest.raises(SegmoError, match="precision must be 'auto', 'fp32' or 'bf16'"):
        model.edit_text(source, "a person walks, then kicks.", precision="fp16")
    edit = model.edit(source, (0, 8), "a person runs")
    with pytest.raises(SegmoError, match="generator state"):
        model.edit_text(edit, "a person runs, then jumps.")


def test_reweight_refuses_what_it_would_ignore(segmo_model):
    """A reweight edits the source's own text in every pass: `inject_until` was ignored, and
    `edit_text(source, "other text", mode="reweight")` generated the other text's motion,
    both without a word."""
    model = segmo_model
    source = model.generate(["a person walks, then jumps."], [40],
                            generator=torch.Generator().manual_seed(0))
    reweight = functools.partial(model.edit_text, source, mode="reweight", weights={1: 4.0})
    with pytest.raises(SegmoError, match=re.escape(
            "inject_until is for modes 'swap', 'add' and 'refine'; 'reweight' edits every pass")):
        reweight(inject_until=0.2)
    with pytest.raises(SegmoError, match=re.escape(
            "mode 'reweight' edits the source's own text: target_text 'a person runs, then "
            "jumps.' is not 'a person walks, then jumps.'; leave it out")):
        reweight("a person runs, then jumps.")
    with pytest.raises(SegmoError, match=re.escape(
            "mode 'reweight' edits the source's own segments: target_segments "
            "[['a person runs', 'a person jumps']] are not [['a person walks', "
            "'a person jumps']]; leave them out")):
        reweight(target_segments=[["a person runs", "a person jumps"]])
    # The source's own text (and segments), given, is the same reweight.
    four = reweight()
    assert not torch.equal(four.tokens, source.tokens)
    assert torch.equal(reweight(source.texts[0], target_segments=source.segments).tokens,
                       four.tokens)
    # The other modes keep their documented default.
    kick = "a person walks, then kicks."
    assert torch.equal(model.edit_text(source, kick).tokens,
                       model.edit_text(source, kick, inject_until=INJECT_UNTIL).tokens)


def test_a_target_text_that_is_the_sources_keeps_its_segments(segmo_model):
    """A source generated with segments given: its own text was segmented anew by the rule
    segmenter, so the same text did not give the source back."""
    model = segmo_model
    texts = ["a person walks forward, then jumps.", "someone waves, then sits"]
    given = [["walking forward", "jumping high"], ["waving", "sitting", "resting"]]
    assert model.segment_texts(texts) != given
    source = model.generate(texts, [48, 40], segments=given,
                            generator=torch.Generator().manual_seed(3))
    same = model.edit_text(source, texts)
    assert same.segments == given and torch.equal(same.tokens, source.tokens)
    # A changed text is segmented; target_segments are taken as given.
    one = model.edit_text(source, [texts[0], "someone claps, then sits"])
    assert one.segments == [given[0], ["someone claps", "someone sits"]]
    other = [["walking", "jumping"], ["waving", "sitting"]]
    assert model.edit_text(source, texts, target_segments=other).segments == other


def test_reweight_key_labels_name_their_key_or_are_refused(segmo_model):
    """'segment 01' (or 'segment  1', 'segment +1') passed the range check but matched no
    key label ("segment 1"): the factor was ignored and the edit was the source; 'segment x'
    was a ValueError, 'segment ' an IndexError."""
    model = segmo_model
    source = model.generate(["a person walks, then jumps."], [40],
                            generator=torch.Generator().manual_seed(0))
    four = model.edit_text(source, mode="reweight", weights={1: 4.0})
    assert not torch.equal(four.tokens, source.tokens)
    leading_zero = model.edit_text(source, mode="reweight", weights={"segment 01": 4.0})
    assert torch.equal(leading_zero.tokens, four.tokens)
    for key in ("segment  1", "segment +1", "segment x", "segment ", "word 1.5"):
        with pytest.raises(SegmoError, match=re.escape(f"weights key {key!r} must be "
                                                       "'segment k' or 'word w'")):
            model.edit_text(source, mode="reweight", weights={key: 4.0})


def test_an_output_of_another_model_is_refused(segmo_model, tmp_path, tokenizer_dir):
    """edit_text returned tokens of another shape than its source's, unrelated to it, for
    another bundle's output, and edit failed with torch's IndexError."""
    stages = build_stages(tmp_path, tokenizer_dir["t2m"])
    other = SegMo.from_stages(stages["tokenizer"], stages["mask"], stages["residual"],
                              stages["length"], text_encoder=hash_encoder("hash", TEXT_DIM))
    g = torch.Generator().manual_seed(0)
    theirs = other.generate(["a person walks, then jumps."], [40], generator=g)
    ours = segmo_model.generate(["a person walks, then jumps."], [40], generator=g)
    assert theirs.tokens.shape == ours.tokens.shape  # the same architecture, other weights
    with pytest.raises(SegmoError, match=r"SegMo.edit_text: the motion was generated by another"):
        segmo_model.edit_text(theirs, "a person walks, then kicks.")
    with pytest.raises(SegmoError, match=r"SegMo.edit: the motion was generated by another"):
        other.edit(ours, (0, 8), "a person runs")
    other.edit(theirs, (0, 8), "a person runs")  # its own output
    other.edit(ours.motion(0), (0, 8), "a person runs")  # features are encoded anew
    # An output that records no model (made by hand) is checked by its tokens' layout.
    one_layer = dataclasses.replace(theirs, tokens=theirs.tokens[..., :1], model=None)
    with pytest.raises(SegmoError, match=r"tokens of shape \(1, 10, 1\).* are not this model's "
                                         r"\(3 layers, codes below"):
        other.edit_text(one_layer, "a person walks, then kicks.")


def test_compose_of_one_part_is_generate(segmo_model):
    model = segmo_model
    one = model.compose([("a person walks forward, then jumps.", 48)],
                        generator=torch.Generator().manual_seed(4))
    plain = model.generate(["a person walks forward, then jumps."], [48],
                           generator=torch.Generator().manual_seed(4))
    assert torch.equal(one.tokens, plain.tokens) and torch.equal(one.features, plain.features)
    assert one.spans == [[(0, 48)]]


def test_compose_joins_parts_longer_than_a_clip(segmo_model):
    model = segmo_model
    parts = [("a person walks forward.", 160), ("someone jumps twice.", 120),
             ("a person sits down.", 140)]
    long = model.compose(parts, transition=20, generator=torch.Generator().manual_seed(5))
    total = 160 + 120 + 140 + 2 * 20
    assert long.features.shape[1] == total > model.max_frames
    assert long.tokens.shape[1] == total // 4 and int(long.lengths[0]) == total
    assert long.spans == [[(0, 160), (180, 300), (320, 460)]]
    assert long.segments == [[p[0] for p in parts]]
    # The root keeps going across parts: no jump between neighbouring frames larger than
    # the largest inside a part.
    root = long.joints[0, :, 0]
    steps = (root[1:] - root[:-1]).norm(dim=1)
    inside = torch.cat([steps[a:b - 1] for a, b in long.spans[0]])
    assert float(steps.max()) <= float(inside.max()) * 3 + 1e-6

    # Changing one part's text changes that part and its transitions, no other frame.
    changed = model.compose([parts[0], parts[1], ("a person waves.", 140)], transition=20,
                            generator=torch.Generator().manual_seed(5))
    differs = (changed.features[0] != long.features[0]).any(dim=1)
    start_of_transition = 300 - 8  # the fade into the second transition
    assert not differs[:start_of_transition].any() and differs[320:].any()


def test_compose_refuses_what_it_cannot_join(segmo_model):
    model = segmo_model
    with pytest.raises(SegmoError, match="parts"):
        model.compose([])
    with pytest.raises(SegmoError, match="transition"):
        model.compose([("walk", 40), ("jump", 40)], transition=10)
    with pytest.raises(SegmoError, match="at least"):
        model.compose([("walk", 12), ("jump", 40)])


def test_compose_checks_whole_float_frames_as_it_checks_ints(segmo_model, monkeypatch):
    """generate takes 60.0 frames as 60; compose's checks skipped any frames that were not an
    int: 4.0 frames met a tensor size mismatch instead of the shortest-part error, and 200
    parts of 196.0 frames passed the 20-minute limit."""
    model = segmo_model
    parts = [("walk", 40), ("jump", 40)]
    whole = model.compose(parts, 20, generator=torch.Generator().manual_seed(3))
    floats = model.compose([("walk", 40.0), ("jump", np.int64(40))], 20,
                           generator=torch.Generator().manual_seed(3))
    assert torch.equal(whole.tokens, floats.tokens) and floats.spans == whole.spans
    with monkeypatch.context() as patch:  # each is refused before any generation
        patch.setattr(model, "generate", lambda *a, **k: pytest.fail("generated"))
        with pytest.raises(SegmoError, match=r"at least 20 frames, got \[4, 40\]"):
            model.compose([("a person walks", 4.0), ("a person jumps", 40)], 20)
        with pytest.raises(SegmoError, match="200 parts make 43180 frames, more than 20 minutes"):
            model.compose([("a person walks", 196.0)] * 200)
        with pytest.raises(SegmoError, match="SegMo.compose: lengths must be whole numbers of "
                                             "frames, got 40.5"):
            model.compose([("walk", 40.5), ("jump", 40)])
