"""`SegMo`: the inference pipeline, text → tokens → motion → joints (plus grounding/retrieval).

A `SegMo` holds the stages of a bundle directory (`segmo.pipeline.bundle` says what it
holds) and its text side (`segmo.pipeline.conditioning`: text encoder, text segmenter,
captions → condition tensors); the checks of what users pass live in
`segmo.pipeline.inputs`, the edits in `segmo.pipeline.editing`, long motions from parts in
`segmo.pipeline.compose`, grounding and retrieval in `segmo.pipeline.grounding` /
`retrieval` over the segment space of `segmo.pipeline.space`.

Example:
    >>> from segmo import SegMo
    >>> model = SegMo.from_pretrained("runs/demo/model")
    >>> out = model.generate(["a person walks forward, then waves"], lengths=[120],
    ...                      generator=torch.Generator().manual_seed(0))
    >>> out.features.shape, out.joints.shape          # (1, 120, 263), (1, 120, 22, 3)
    >>> model.ground("a person walks, then waves", out.motion(0)).best_spans_frames
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from segmo.errors import SegmoError
from segmo.generation.attention_edit import EditMode
from segmo.generation.generate import (
    Precision,
    check_models,
    decode_tokens,
    generate_tokens,
    inference,
    resolve_precision,
)
from segmo.generation.sampling import Sampler, SamplingOptions
from segmo.models.attention_recorder import AttentionRecording, record_attention
from segmo.models.cpu_inference import use_cpu_kernels
from segmo.models.length_estimator import LengthEstimator
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.residual_transformer import ResidualTransformer
from segmo.models.tokenizer import FRAMES_PER_TOKEN, RVQVAE
from segmo.motion.checks import check_motion_values, value_problem
from segmo.motion.features import features_to_joints
from segmo.motion.skeleton import SkeletonSpec, get_skeleton
from segmo.pipeline import compose, editing, grounding, retrieval
from segmo.pipeline.bundle import (
    KIT_GUIDANCE_SCALE,
    STAGES,
    SegMoConfig,
    check_tokenizer,
    load_stage,
    read_bundle,
    sampling_fields,
    write_bundle,
)
from segmo.pipeline.compose import COMPOSE_TRANSITION, Part
from segmo.pipeline.conditioning import TextConditioning
from segmo.pipeline.inputs import (
    check_generator,
    check_texts,
    frame_lengths,
    motion_array,
    motion_rows,
    resolve_device,
    segment_durations,
)
from segmo.pipeline.outputs import GenerationOutput, GroundingOutput, weights_fingerprint
from segmo.pipeline.space import SegmentEmbeddings, alignment_head, embed_segments


class SegMo:
    """Inference-only bundle of the exported stages (plain class holding `nn.Module`s).

    The text encoder named in the bundle is built on first use; tests and custom setups
    may inject any object with `.encode(texts).sentence` and `.dim` (`text_encoder=` or
    `model.text_encoder = obj`). Sentence vectors are cached in memory per text.
    """

    def __init__(self, tokenizer: RVQVAE, mask: MaskTransformer,
                 residual: ResidualTransformer | None = None,
                 length: LengthEstimator | None = None, config: SegMoConfig | None = None,
                 *, text_encoder: Any = None, text_segmenter: Any = None) -> None:
        if mask.config.codebook_size != tokenizer.codebook_size:
            raise SegmoError(f"SegMo: mask transformer codebook_size={mask.config.codebook_size}"
                             f" but the tokenizer has {tokenizer.codebook_size}")
        if residual is not None:
            if residual.config.num_quantizers > tokenizer.num_quantizers:
                raise SegmoError(f"SegMo: residual num_quantizers={residual.config.num_quantizers}"
                                 f" > tokenizer num_quantizers={tokenizer.num_quantizers}")
            try:
                check_models(mask, residual)
            except ValueError as error:
                raise SegmoError(f"SegMo: {error}") from None
        if length is not None and length.config.text_dim != mask.config.text_dim:
            raise SegmoError(f"SegMo: length estimator text_dim={length.config.text_dim}, mask "
                             f"transformer text_dim={mask.config.text_dim}")
        meta = getattr(tokenizer, "meta", {}) or {}
        if config is None:
            name = (getattr(mask, "meta", {}) or {}).get("text_encoder")
            if name is None and text_encoder is None:
                raise SegmoError("SegMo: the mask transformer's meta names no text_encoder; "
                                 "pass config=SegMoConfig(text_encoder=...) or text_encoder=")
            skeleton = meta.get("skeleton", "t2m")
            config = SegMoConfig(
                text_encoder=name or getattr(text_encoder, "name", "custom"),
                skeleton=skeleton, fps=float(meta.get("fps", get_skeleton(skeleton).fps)),
                guidance_scale=(KIT_GUIDANCE_SCALE if skeleton == "kit"
                                else SamplingOptions.guidance_scale))
        self.config = config
        self.tokenizer = tokenizer.eval()
        # Inference only: the CPU kernels (`segmo.models.cpu_inference`) are the faster
        # way to run the transformers, and the same arithmetic.
        self.mask = use_cpu_kernels(mask.eval())
        self.residual = use_cpu_kernels(residual.eval()) if residual is not None else None
        self.length = length.eval() if length is not None else None
        for module in self.modules():
            module.requires_grad_(False)
        self.skeleton: SkeletonSpec = get_skeleton(config.skeleton)
        if self.skeleton.feature_dim != tokenizer.config.feature_dim:
            raise SegmoError(f"SegMo: skeleton {config.skeleton!r} has {self.skeleton.feature_dim}"
                             f"-d features, the tokenizer {tokenizer.config.feature_dim}")
        self.text = TextConditioning(mask.config, config, self.device, text_encoder=text_encoder,
                                     text_segmenter=text_segmenter)

    # -- construction, saving --------------------------------------------------------------

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, device: str | torch.device = "cpu",
                        revision: str | None = None, **kwargs: Any) -> SegMo:
        """Load a bundle: a folder, or a Hugging Face hub id ("owner/name", from the hub's
        cache when ``HF_HUB_OFFLINE=1``; `revision`: branch, tag or commit). kwargs go to
        `__init__`."""
        device = resolve_device(device)
        config, stages = read_bundle(directory, revision)
        return cls(**stages, config=config, **kwargs).to(device)

    @classmethod
    def from_stages(cls, tokenizer: str | os.PathLike, mask: str | os.PathLike,
                    residual: str | os.PathLike | None = None,
                    length: str | os.PathLike | None = None, segmenter: str = "rule",
                    **kwargs: Any) -> SegMo:
        """Assemble from exported stage directories (`segmo export` outputs). The mask and
        residual stages must have been trained with `tokenizer` where they record its digest
        (meta "tokenizer_digest"; stages exported before it was recorded are not checked)."""
        stages = {"tokenizer": load_stage(tokenizer, "rvq"), "mask": load_stage(mask, "mask"),
                  "residual": load_stage(residual, "residual") if residual else None,
                  "length": load_stage(length, "length") if length else None}
        check_tokenizer(stages, tokenizer)
        names = {n: (getattr(m, "meta", {}) or {}).get("text_encoder")
                 for n, m in stages.items() if m is not None and n != "tokenizer"}
        if len({v for v in names.values() if v is not None}) > 1:
            raise SegmoError(f"SegMo.from_stages: the stages were trained with different text "
                             f"encoders: {names}")
        model = cls(**stages, **kwargs)
        model.config.text_segmenter = segmenter
        return model

    def save_pretrained(self, directory: str | os.PathLike, metrics: dict | None = None,
                        push_to_hub: bool = False, repo_id: str | None = None,
                        private: bool = False, overwrite: bool = False) -> Path:
        """Write the bundle (every stage, segmo.json and the model card README.md, with
        `metrics` from `segmo evaluate` when given) to `directory`, replacing it whole; with
        `push_to_hub`, upload it to the hub repository `repo_id` ("owner/name"). Returns
        `directory`. A non-empty `directory` that holds anything else than this bundle
        (another bundle's stages, the user's files) is refused unless `overwrite`."""
        return write_bundle(directory, self.config,
                            {name: getattr(self, name) for name in STAGES}, metrics=metrics,
                            push_to_hub=push_to_hub, repo_id=repo_id, private=private,
                            overwrite=overwrite)

    def modules(self) -> list[torch.nn.Module]:
        return [m for m in (self.tokenizer, self.mask, self.residual, self.length)
                if m is not None]

    def to(self, device: str | torch.device) -> SegMo:
        device = resolve_device(device)
        for module in self.modules():
            module.to(device)
        self.text.device = self.device
        return self

    @property
    def device(self) -> torch.device:
        return self.tokenizer.mean.device

    @property
    def fps(self) -> float:
        return self.config.fps

    @property
    def text_encoder_name(self) -> str:
        return self.config.text_encoder

    @property
    def max_frames(self) -> int:
        return FRAMES_PER_TOKEN * self.mask.config.max_tokens

    @property
    def max_segments(self) -> int:
        return self.mask.config.max_segments

    def __repr__(self) -> str:
        stages = ", ".join(n for n in STAGES if getattr(self, n) is not None)
        return (f"SegMo(stages=[{stages}], text_encoder={self.text_encoder_name!r}, "
                f"skeleton={self.skeleton.name!r}, max_frames={self.max_frames})")

    # -- text side (`segmo.pipeline.conditioning`) -------------------------------------------

    @property
    def text_encoder(self):
        """The bundle's text encoder, built on first use; assign another to replace it."""
        return self.text.encoder

    @text_encoder.setter
    def text_encoder(self, encoder) -> None:
        self.text.encoder = encoder

    @property
    def text_segmenter(self):
        """The bundle's text segmenter, built on first use; assign another to replace it."""
        return self.text.segmenter

    @text_segmenter.setter
    def text_segmenter(self, segmenter) -> None:
        self.text.segmenter = segmenter

    @property
    def uses_words(self) -> bool:
        """Whether the transformers condition on the captions' words (text_tokens "words")."""
        return self.text.uses_words

    @property
    def has_word_keys(self) -> bool:
        """Whether the words are keys of the mask transformer's self-attention (prefix
        words; `TextConditioning.has_word_keys`)."""
        return self.text.has_word_keys

    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        """texts → (n, text_dim) float32 sentence vectors on the model's device (a text
        without words, "" included, is encoded as the encoder reads it)."""
        return self.text.encode(check_texts(texts, words=False))

    def segment_texts(self, texts: list[str]) -> list[list[str]]:
        """Ordered text segments of each text (≤ max_segments), rule backend by default."""
        return self.text.segment(check_texts(texts))

    def text_condition(self, texts: list[str], segments: list[list[str]] | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[list[str]]]:
        """texts (b) [+ segments] → sentence (b, text_dim), segment vectors (b, a, text_dim),
        segment_mask (b, a) bool, and the segments used (a = most segments of the batch)."""
        return self.text.condition(texts, segments)

    def word_sources(self, texts: list[str], segments: list[list[str]] | None = None,
                     word_text: str | None = None) -> list[str]:
        """The text each row's word keys are read from (`SamplingOptions.word_text`; None:
        the bundle's): the text itself ("caption"), or its segments (default: the bundle's
        text segmenter's) joined in execution order ("segments", `ordered_text`)."""
        return self.text.word_sources(texts, segments, self._word_text(word_text))

    def word_condition(self, texts: list[str], segments: list[list[str]] | None = None,
                       word_text: str | None = None
                       ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """texts (b) → the per-word features (b, l, text_dim) of their word sources
        (`word_sources`: the text encoder's tokens, start and end tokens included, padded to
        the longest) and word_mask (b, l) bool, for transformers with word keys; (None,
        None) for the others. Cached in memory per text like the sentence vectors."""
        return self.text.words(texts, segments, self._word_text(word_text))

    def word_texts(self, texts: list[str], segments: list[list[str]] | None = None,
                   word_text: str | None = None) -> list[list[str]]:
        """texts (b) → the text of each word key the transformers see for each text (of its
        word source, `word_sources`; `TextEncoder.token_texts`: start and end tokens
        included, cut at the model's max_words), the labels "word 0", "word 1", … of a
        recording in that order (when they are prefix keys, `has_word_keys`); empty lists
        for transformers without words."""
        return self.text.word_texts(texts, segments, self._word_text(word_text))

    def _word_text(self, word_text: str | None) -> str:
        if word_text is None:
            return self.sampling.word_text
        SamplingOptions(word_text=word_text)  # one SegmoError for a value it does not know
        return word_text

    # -- motion side -------------------------------------------------------------------------

    def check_lengths(self, lengths: Any, b: int) -> torch.Tensor:
        """User lengths (int, list or tensor of frames) → (b,) long; raise on bad values."""
        return frame_lengths(lengths, b, self.max_frames, self.fps).to(self.device)

    def normalize_motion(self, motion: Any) -> tuple[torch.Tensor, int]:
        """Raw features (t, d) (numpy or torch) → z-scored (1, t', d) on the model's device
        with t' = t rounded down to a multiple of 4 (the tokenizer's unit), and t."""
        x, usable = motion_array(motion, self.tokenizer.config.feature_dim, self.max_frames,
                                 self.skeleton.name)
        t = x.shape[0]
        check_motion_values(x.cpu().numpy(), self.tokenizer.mean.cpu().numpy(),
                            self.tokenizer.std.cpu().numpy(), "SegMo: the motion")
        x = x[:usable].to(self.device)
        return self.tokenizer.normalize(x)[None], t

    def encode_motion(self, motion: Any) -> torch.Tensor:
        """Raw features (t, d) → tokens (1, t // 4, q) long (all tokenizer layers)."""
        with inference([self.tokenizer], "fp32", self.device):
            return self.tokenizer.encode(self.normalize_motion(motion)[0])

    def decode(self, tokens: torch.Tensor, lengths: torch.Tensor, texts: list[str],
               segments: list[list[str]], precision: Precision = "auto") -> GenerationOutput:
        """tokens (b, n, q) + lengths (b,) frames → GenerationOutput (raw features, joints).
        Each motion is decoded from its own tokens, as it would be alone (`decode_tokens`)."""
        with inference([self.tokenizer], "fp32", self.device):  # decode_tokens: bf16 itself
            z = decode_tokens(self.tokenizer, tokens, lengths, precision)
            features = self.tokenizer.denormalize(z)
        valid = (torch.arange(features.shape[1], device=features.device)
                 < lengths[:, None])[..., None]
        features = features * valid
        # Frames past a length cannot affect earlier ones (the recovery is a forward cumsum).
        joints = features_to_joints(features, self.skeleton).float() * valid[..., None]
        return GenerationOutput(features=features.float(), joints=joints, tokens=tokens,
                                lengths=lengths.long(), texts=list(texts), segments=segments,
                                skeleton=self.skeleton, fps=self.fps,
                                model=self.weights_fingerprint())

    def weights_fingerprint(self) -> str:
        """A digest of the weights of the stages that make tokens and motions (`outputs.
        weights_fingerprint`): outputs record it, and edits refuse another model's."""
        return weights_fingerprint([m for m in (self.tokenizer, self.mask, self.residual)
                                    if m is not None])

    # -- generation --------------------------------------------------------------------------

    def sample_lengths(self, texts: list[str], generator: torch.Generator | None = None
                       ) -> torch.Tensor:
        """(b,) frame lengths drawn from the bundled length estimator."""
        check_generator(generator, "SegMo.sample_lengths")
        if self.length is None:
            raise SegmoError("SegMo: no lengths given and the bundle has no length estimator; "
                             "pass lengths=[frames, ...]")
        with inference([self.length], "fp32", self.device):
            lengths = self.length.sample(self.encode_texts(check_texts(texts)), generator=generator)
        # The estimator may know longer motions than the mask transformer accepts.
        return lengths.clamp(FRAMES_PER_TOKEN, self.max_frames).long()

    @property
    def sampling(self) -> SamplingOptions:
        """The bundle's sampling options: its guidance scales (`segmo.json`) and the defaults
        of the other options. `dataclasses.replace(model.sampling, steps=20)` changes one."""
        return self._sampling(None)

    def _sampling(self, sampling: SamplingOptions | None, **given: Any) -> SamplingOptions:
        """`sampling` (None: the bundle's) with each option given by keyword (not None) in
        its place, built, and so checked, once."""
        if sampling is None:
            fields = sampling_fields(self.config)
        elif isinstance(sampling, SamplingOptions):
            fields = dataclasses.asdict(sampling)
        else:
            raise SegmoError(f"SegMo: sampling must be a SamplingOptions, got {sampling!r:.80}")
        return SamplingOptions(**{**fields, **{k: v for k, v in given.items() if v is not None}})

    def generate(self, texts: list[str], lengths: Any = None, *,
                 segments: list[list[str]] | None = None, sampling: SamplingOptions | None = None,
                 guidance_scale: float | None = None, residual_guidance_scale: float | None = None,
                 steps: int | None = None, residual_guided_layers: int | None = None,
                 guidance: str | None = None, temperature: float | None = None,
                 top_k_ratio: float | None = None, sampler: Sampler | None = None,
                 generator: torch.Generator | None = None, precision: Precision = "auto",
                 durations: list[list[float] | None] | None = None) -> GenerationOutput:
        """Text → motions. lengths: frames per text (multiples of 4 in [4, max_frames]), an
        int for all, or None to sample them from the length estimator. Tokens are drawn as
        `sampling` says (default `self.sampling`: the bundle's guidance scales), an option
        given by keyword (guidance_scale=..., steps=...) in its place. Reproducible for a
        seeded `generator`. durations: per text, how long each of its segments lasts (any
        unit, read as shares of the motion: [1, 3] = the second segment three times as
        long), for a mask transformer trained with segment timing; without them such a
        model predicts them (`SamplingOptions.segment_timing`), and so for a text whose
        entry is None (durations=[[1, 4], None]).

            >>> model.generate(["a person jumps, then walks forward"], [120], durations=[[1, 4]])
        """
        if isinstance(texts, str):
            texts = [texts]
        if isinstance(texts, (list, tuple)) and not texts:  # other types: text_condition says
            raise SegmoError("SegMo.generate: texts is empty")
        check_generator(generator, "SegMo.generate")
        options = self._sampling(
            sampling, guidance_scale=guidance_scale,
            residual_guidance_scale=residual_guidance_scale, steps=steps,
            residual_guided_layers=residual_guided_layers, guidance=guidance,
            temperature=temperature, top_k_ratio=top_k_ratio, sampler=sampler)
        sentence, vectors, segment_mask, segments = self.text_condition(texts, segments)
        if lengths is None:
            lengths = self.sample_lengths(texts, generator)
        lengths = self.check_lengths(lengths, len(texts))
        words, word_mask = self.word_condition(texts, segments, options.word_text)
        timing = None if durations is None else self.segment_durations(durations, segments)
        if generator is None:  # a generator of its own, so that the draws can be replayed
            seed = int(torch.randint(0, 2**62, (1,)))
            generator = torch.Generator(device=self.device).manual_seed(seed)
        state = generator.get_state()
        tokens = generate_tokens(self.mask, self.residual, sentence, vectors, segment_mask,
                                 lengths, options=options, generator=generator,
                                 precision=precision, words=words, word_mask=word_mask,
                                 durations=timing)
        out = self.decode(tokens, lengths, texts, segments, precision)
        out.sampling, out.generator_state, out.durations = options, state, timing
        out.precision = resolve_precision(precision, self.device)[0]
        return out

    def segment_durations(self, durations: Any, segments: list[list[str]]
                          ) -> torch.Tensor | None:
        """Per text, its segments' durations → (b, a) float32, 0 in empty slots, None when
        no text has any; one SegmoError naming the text whose durations do not fit."""
        none_given = isinstance(durations, (list, tuple)) and all(d is None for d in durations)
        if not self.mask.config.segment_timing and not none_given:
            raise SegmoError("SegMo.generate: durations need a mask transformer trained with "
                             "segment timing (segment_timing: truth or segmenter); this one has none")
        timing = segment_durations(durations, segments)
        return None if timing is None else timing.to(self.device)

    def edit(self, motion: GenerationOutput | Any, span: tuple[int, int], text: str, *,
             segments: list[str] | None = None, sampling: SamplingOptions | None = None,
             guidance_scale: float | None = None, residual_guidance_scale: float | None = None,
             steps: int | None = None, residual_guided_layers: int | None = None,
             guidance: str | None = None, temperature: float | None = None,
             top_k_ratio: float | None = None, sampler: Sampler | None = None,
             generator: torch.Generator | None = None, precision: Precision = "auto"
             ) -> GenerationOutput:
        """Regenerate frames [start, end) of a motion from `text` (temporal inpainting),
        drawing tokens as in `generate`.

        motion: a GenerationOutput (its tokens are edited, every sample with the same span)
        or raw features (t, d), tokenized first. The span is widened to whole tokens;
        base and residual tokens outside it are kept exactly (`edit_tokens`). Frames
        near the span may still change a little: the decoder is convolutional
        (`edit_drift` measures it).
        """
        options = self._sampling(
            sampling, guidance_scale=guidance_scale,
            residual_guidance_scale=residual_guidance_scale, steps=steps,
            residual_guided_layers=residual_guided_layers, guidance=guidance,
            temperature=temperature, top_k_ratio=top_k_ratio, sampler=sampler)
        check_generator(generator, "SegMo.edit")
        return editing.edit(self, motion, span, text, segments=segments, options=options,
                            generator=generator, precision=precision)

    def edit_text(self, source: GenerationOutput, target_text: str | list[str] | None = None,
                  mode: EditMode = "swap", *, target_segments: list[list[str]] | None = None,
                  weights: dict[str | int, float] | None = None,
                  inject_until: float | None = None, keep_outside: bool = False,
                  precision: Precision = "auto") -> GenerationOutput:
        """Edit generated motions by their attention (SALAD's zero-shot edits,
        `segmo.generation.attention_edit`): decode `target_text` (one for all samples or
        one per sample; None: the source's texts, for "reweight"; a target text that is its
        source's keeps the source's segments, others are segmented unless `target_segments`
        are given) from the source's own generator state while the attention is edited:

            out = model.generate(["a man walks forward, then jumps"], 120, generator=g)
            swapped = model.edit_text(out, "a man walks forward, then kicks")
            stronger = model.edit_text(out, mode="reweight", weights={"jumps": 2.0})

        mode "swap" (a segment's text replaced), "add" (a segment added), "refine" (a
        segment's text refined, e.g. a modifier added): the source's attention for the first
        `inject_until` share of the decoding steps (default `INJECT_UNTIL`, 0.5), on the keys
        with a counterpart (segments matched by `segment_counterparts`). "reweight": the
        source's own text decoded again with `weights`, which maps a segment (its number
        from 1, its text, or a key label "segment k" / "word w", k and w whole numbers, w
        from 0 in `word_texts` order) to the factor its attention is multiplied by in every
        pass; a key that names no key of the caption is refused, and so are an
        `inject_until` and a target text (or segments) other than the source's. keep_outside: decode only the tokens whose segment attention in the
        source went to a changed (or reweighted) segment, keeping every other token of the
        source (a span edit whose span comes from the attention). A source generated with
        `durations` is replayed with them, and a target with as many segments as the
        source's is decoded with them (one with a segment added, with its timing head's).
        precision "auto" replays at the precision the source was generated at (an explicit
        one runs as asked). The same text with any `inject_until`, or factors of 1, gives
        the source's tokens bit for bit.
        """
        return editing.edit_text(self, source, target_text, mode,
                                 target_segments=target_segments, weights=weights,
                                 inject_until=inject_until, keep_outside=keep_outside,
                                 precision=precision)

    def compose(self, parts: list[Part], transition: int = COMPOSE_TRANSITION, *,
                generator: torch.Generator | None = None, precision: Precision = "auto"
                ) -> GenerationOutput:
        """One motion longer than the model's clips from a list of (text, frames) parts:

            long = model.compose([("a man walks forward", 120), ("he jumps twice", 60),
                                  ("he sits down", 80)], transition=20)

        Each part is generated from its text (one batch, so changing one part's text changes
        no other part's tokens); between two parts, `transition` new frames (a multiple of
        4) are drawn by masked inpainting with the end of the one and the start of the next
        visible, conditioned on both texts as two ordered segments. Parts and transitions
        are decoded window by window and joined with an 8-frame cross-fade at the edges of
        each transition; the root trajectory runs on across parts (the features hold root
        velocities). → one sample of sum(frames) + (parts − 1)·transition frames, its
        segments the parts' texts and `spans` their frames; its tokens are the
        concatenated tokens of parts and transitions. One part is exactly `generate`.
        A part may name its segments' durations, (text, frames, [1, 3]), for a mask
        transformer trained with segment timing (`generate`'s durations; the parts without
        them are predicted).
        """
        check_generator(generator, "SegMo.compose")
        return compose.compose(self, parts, transition, generator=generator,
                               precision=precision)

    @contextmanager
    def record_attention(self) -> Iterator[AttentionRecording]:
        """Record what the transformers' motion queries attend to while the context is open
        (`segmo.models.attention_recorder`; diagnostics in `segmo.evaluation.attention`):

            with model.record_attention() as recording:
                out = model.generate(["a person walks forward, then jumps"], 120)
            recording.of("mask")[0].weights   # step 0, block 0: (rows, heads, queries, keys)

        Outputs are the same as without it. Edits and attention grounding may run inside
        it, and it records on after them; the passes of `edit_text` are counted among its
        steps but not recorded (the edit computes their attention itself)."""
        models = {"mask": self.mask}
        if self.residual is not None:
            models["residual"] = self.residual
        with record_attention(models) as recording:
            yield recording

    # -- the segment space: grounding and retrieval ------------------------------------------

    def embed_segments(self, texts: list[str], motions: Any, *,
                       segments: list[list[str]] | None = None, lengths: Any = None,
                       normalized: bool = False) -> SegmentEmbeddings:
        """Text i and motion i in the learned segment space (`segmo.pipeline.space`).

        motions: a list of (t_i, d) arrays/tensors, or a (b, t, d) tensor with `lengths`
        (b,) frames; raw features unless `normalized` (z-scored already). Each motion is
        cut to a multiple of 4 frames (the tokenizer's unit) and encoded at that length, as
        it would be alone (`space.embed_segments`). segments: one list per text
        (default: the bundle's text segmenter).
        """
        alignment_head(self.mask)  # before any work: a model without one cannot do this
        texts = check_texts(texts)
        rows = [self._z_scored(m, normalized)
                for m in motion_rows(motions, lengths, "SegMo.embed_segments")]
        if len(texts) != len(rows):
            raise SegmoError(f"SegMo.embed_segments: {len(texts)} texts for {len(rows)} motions")
        frames = torch.tensor([len(r) for r in rows], device=self.device)
        z = torch.nn.utils.rnn.pad_sequence(rows, batch_first=True)  # zeros past each end
        sentence, vectors, segment_mask, used = self.text_condition(texts, segments)
        words, word_mask = self.word_condition(texts, used)
        return embed_segments(self.tokenizer, self.mask, z, frames, sentence, vectors,
                              segment_mask, used, words, word_mask)

    def _z_scored(self, motion: Any, normalized: bool) -> torch.Tensor:
        """One motion → z-scored (t', d) on the model's device, t' its usable frames."""
        if not normalized:
            return self.normalize_motion(motion)[0][0]
        x, usable = motion_array(motion, self.tokenizer.config.feature_dim, self.max_frames,
                                 self.skeleton.name)
        problem = value_problem(x[:usable].float().cpu().numpy(), 0.0, 1.0)  # z-scores
        if problem is not None:
            raise SegmoError(f"SegMo: the motion (normalized=True, z-scored): not a motion "
                             f"(NaN/inf or absurd values): {problem}")
        return x[:usable].to(self.device)

    def ground(self, text: str, motion: Any, window: int | list[int] | None = None,
               stride: int | None = None, segments: list[str] | None = None,
               search: str | None = None, min_tokens: int | None = None,
               method: str = "similarity") -> GroundingOutput:
        """Where each text segment of `text` happens in `motion` (raw features (t, d)):
        search "ordered" (default; one span per segment, in order, cutting the motion),
        "spans" (each segment's best span of any length) or "window" (the paper's sliding
        windows, the default when `window` is given); method "similarity" (default, the
        learned segment space) or "attention" (where the mask transformer's motion tokens
        look); see `segmo.pipeline.grounding`. `stride` (tokens, default 1) is for "window",
        `min_tokens` (the shortest span, default 2 tokens) for "ordered" and "spans": given
        to another search, either is refused."""
        out = grounding.ground(self, text, motion, search=search, window=window,
                               stride=stride, min_tokens=min_tokens, segments=segments,
                               method=method)
        out.fps = self.fps  # the map's time axis
        return out

    def embed_pairs(self, texts: list[str], motions: Any, spans: Any = None, *,
                    segments: list[list[str]] | None = None, lengths: Any = None,
                    normalized: bool = False
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Paired text/motion segments in the learned space; spans default to the bundle's
        motion segmenter. See `segmo.pipeline.retrieval.embed_pairs`."""
        return retrieval.embed_pairs(
            self, texts, motions, self.config.motion_segmenter if spans is None else spans,
            segments=segments, lengths=lengths, normalized=normalized)

    def retrieve_texts(self, motion: Any, candidates: list[str],
                       span: tuple[int, int] | None = None, top_k: int = 5
                       ) -> list[tuple[str, float]]:
        """Motion (or its frame span) → the top_k candidate texts with their scores."""
        return retrieval.retrieve_texts(self, motion, candidates, span=span, top_k=top_k)

    def retrieve_motions(self, text: str, motions: list, top_k: int = 5
                         ) -> list[tuple[int, float]]:
        """Text → the top_k motions (indices into `motions`) with their scores."""
        return retrieval.retrieve_motions(self, text, motions, top_k=top_k)

