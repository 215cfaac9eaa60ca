"""`segmo evaluate`: every metric of a SegMo bundle on one split → metrics.json, report.md, plots.

    segmo evaluate --model models/segmo --data data/synth --evaluator models/evaluator \\
        --action-classifier models/action_classifier --out eval/segmo
    segmo evaluate --real-only --data data/synth --evaluator models/evaluator --out eval/real
    segmo evaluate --compare eval/segmo eval/no_align --out eval/compare

Sections (spec §9, paper §4):
- generation: the T2M protocol (`metrics.evaluate_generation`), a "Real" row and the
  model's row, mean ± 95 % interval over `--repeats`; the generator gets the ground-truth
  lengths and a seeded `torch.Generator` per batch. MultiModality runs `--mm-runs` times
  (not once per repeat: 20 × 100 prompts × 30 generations is out of reach on a CPU), one
  prompt per motion: a split with fewer motions than `--mm-prompts` gives fewer (a warning;
  metrics.json records the number as generated.multimodality_prompts).
  A reconstruction row (`Reconstructor`: real motion → the bundle's tokenizer → decoded,
  the generator's ceiling, with its MPJPE; `--skip reconstruction` leaves it out), and every
  row again per bucket of the caption's number of text segments ("1", "2", "3", "4-5").
- retrieval (TMR protocols, full split and batches of 32), in the evaluator's space and in
  SegMo's learned segment space, where a (caption, motion) score is the mean cosine of the
  caption's text segments with as many uniform spans of the motion (`SegMo.retrieve_motions`'s
  score); SegMo's motion features depend on the text, so each pair costs a forward pass and
  the full protocol is limited to `--retrieval-motions` motions (first caption each).
- grounding (built-in corpus only, `DATA/segments/<id>.json`): each caption's ground-truth
  segments are grounded in the real motion (explicit segments) with each search of
  `segmo.pipeline.grounding` (ordered spans, each segment's best span, the paper's sliding
  window `--grounding-window`) in the learned space and by attention (where the mask
  transformer's motion tokens look; the only method for a model trained without alignment);
  the chosen span vs the true span → R@1 at IoU 0.3/0.5/0.7 and mIoU, beside the text-free
  uniform split, change points and k-means; a few maps are plotted.
- ISC and its CV (paper Fig. 4) per motion segmenter on the real test pairs.
- action order (built-in corpus, `--action-classifier DIR`, or `train` to fit one): exact
  sequence accuracy and normalised edit distance of motions generated from each motion's
  first caption vs that caption's action sequence, and of the real motions (the ceiling).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, get_args

import numpy as np
import torch
from tqdm import tqdm

from segmo.data.layout import has_ground_truth, split_file
from segmo.errors import (
    ArgumentParser,
    SegmoError,
    ascii_whole_number,
    finite_float,
    non_negative_float,
    non_negative_int,
    positive_int,
)
from segmo.evaluation import report
from segmo.evaluation.metrics import (
    evaluate_generation,
    mean_and_interval,
    multimodality_runs,
    t2m_embedders,
)
from segmo.evaluation.sections import (
    SECTIONS,
    EvaluateConfig,
    action_order_section,
    all_rows,
    evaluator_retrieval,
    first_rows,
    ground_truth,
    grounding_section,
    isc_section,
    known_segments,
    load_batches,
    load_classifier,
    raw_features,
    segmo_retrieval,
)
from segmo.files import json_text, output_folder, write_atomic
from segmo.generation.allocator import keep_freed_memory
from segmo.generation.generate import resolve_precision
from segmo.generation.sampling import Remasking, SamplingOptions, SegmentTiming, WordText
from segmo.models.hub import is_hub_id
from segmo.models.pretrained import load_pretrained, read_json
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.features import features_to_joints, joint_errors
from segmo.pipeline import SegMo
from segmo.pipeline.inputs import resolve_device

# ------------------------------------------------------------------------- generation

class Generator:
    """Wraps `SegMo.generate` for the metrics: captions + ground-truth lengths + a seed →
    motions z-scored with the dataset's statistics (b, max(lengths), d)."""

    def __init__(self, model: Any, cfg: EvaluateConfig, mean: np.ndarray, std: np.ndarray,
                 segments_of: dict[str, list[str]] | None = None) -> None:
        self.model, self.cfg, self.segments_of = model, cfg, segments_of
        self.mean, self.std = torch.as_tensor(mean).float(), torch.as_tensor(std).float()
        # The bundle's sampling (None), but for the options only a SamplingOptions carries.
        given = {name: getattr(cfg, name) for name in ("ctrl_k_base", "unconditional", "word_text",
                                                  "segment_timing", "remasking",
                                                  "segment_guidance", "choice_temperature")
                 if getattr(cfg, name) is not None}
        self.sampling = replace(model.sampling, **given) if given else None
        self.motions = 0
        self.seconds = 0.0
        self.bar: Any = None

    def expect(self, total: int, what: str) -> None:
        """Start a progress bar for the next `total` motions (one bar per section)."""
        if self.bar is not None:
            self.bar.close()
        self.bar = tqdm(total=total, desc=f"generate ({what})", unit="motion",
                        disable=not self.cfg.progress)

    def raw(self, captions: list[str], lengths: Any, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw features (b, t, d) and lengths (b,) of one generated batch."""
        start = time.perf_counter()
        segments = ([self.segments_of.get(c, [c]) for c in captions] if self.segments_of else None)
        device = getattr(self.model, "device", torch.device(self.cfg.device))
        out = self.model.generate(list(captions), [int(x) for x in lengths], segments=segments,
                                  sampling=self.sampling, steps=self.cfg.steps, precision=self.cfg.precision,
                                  residual_guided_layers=self.cfg.residual_guided_layers,
                                  guidance=self.cfg.guidance_mode,
                                  guidance_scale=self.cfg.guidance_scale,
                                  generator=torch.Generator(device=device).manual_seed(int(seed)))
        self.motions += len(captions)
        if self.bar is None:
            self.bar = tqdm(desc="generate", unit="motion", disable=not self.cfg.progress)
        self.bar.update(len(captions))
        self.seconds += time.perf_counter() - start
        return out.features.float().cpu(), out.lengths.cpu()

    def __call__(self, captions: list[str], lengths: torch.Tensor, seed: int) -> torch.Tensor:
        features, got = self.raw(captions, lengths, seed)
        t = int(lengths.max())
        z = torch.zeros(len(captions), t, features.shape[-1])
        n = min(t, features.shape[1])
        z[:, :n] = (features[:, :n] - self.mean) / self.std
        z[torch.arange(t)[None, :] >= got[:, None]] = 0.0
        return z


class Reconstructor:
    """The tokenizer's row, the generator's ceiling: each real motion → the bundle's
    tokenizer (every residual layer) → decoded motion, at its length cropped to whole tokens
    as the generator's lengths are (`SegMo.encode_motion`, `SegMo.decode`).

    A reconstruction depends on the motion only, not on the caption a repeat draws, so each
    motion of the split is reconstructed once, here, and kept (z-scored with the dataset's
    statistics, as `Generator` returns motions); `errors` holds the MPJPE (mm) over the
    split's frames, root-aligned and global (`segmo.motion.joint_errors`)."""

    def __init__(self, model: Any, cfg: EvaluateConfig, ds: Any, batches: list[dict]) -> None:
        self.mean, self.std = torch.as_tensor(ds.mean).float(), torch.as_tensor(ds.std).float()
        self.features: dict[str, torch.Tensor] = {}  # id → (t, d)
        aligned = drift = 0.0
        frames = 0
        for b, r in tqdm(first_rows(batches), desc="reconstruct", disable=not cfg.progress):
            real = torch.as_tensor(raw_features(ds, b, r))  # (t, d) raw
            tokens = model.encode_motion(real)  # (1, n, q), every layer
            t = tokens.shape[1] * FRAMES_PER_TOKEN
            out = model.decode(tokens, torch.tensor([t], device=tokens.device), [b["caption"][r]],
                               [[b["caption"][r]]], cfg.precision)
            fake = out.features[0].float().cpu()  # (t, d) raw
            self.features[b["id"][r]] = (fake - self.mean) / self.std
            a, g = joint_errors(features_to_joints(real[:t].double(), model.skeleton),
                                features_to_joints(fake.double(), model.skeleton))  # (t,) each
            aligned, drift, frames = aligned + float(a.sum()), drift + float(g.sum()), frames + t
        to_mm = model.skeleton.unit * 1000.0 / max(frames, 1)
        self.errors = {"mpjpe_mm": aligned * to_mm, "mpjpe_global_mm": drift * to_mm,
                       "motions": float(len(self.features))}

    def raw(self, mid: str) -> np.ndarray:
        """Raw reconstructed features (t, d) of motion `mid`."""
        return (self.features[mid] * self.std + self.mean).numpy()

    def __call__(self, motion: torch.Tensor, lengths: torch.Tensor, ids: list[str]) -> torch.Tensor:
        """The reconstructions of motions `ids`, padded as `motion` (b, t, d)."""
        out = torch.zeros_like(motion)
        for k, mid in enumerate(ids):
            x = self.features[mid][: int(lengths[k])]
            out[k, : len(x)] = x
        return out


def num_segments_of(model: Any, batches: list[dict], segments_of: dict[str, list[str]] | None
                    ) -> dict[str, int]:
    """caption → its number of text segments as the model is conditioned: the data's
    (`--text-segments`, or one per caption without a model), else the bundle's segmenter's."""
    if model is None or segments_of:
        return {c: len(s) for b in batches for c, s in zip(b["caption"], b["segments"], strict=True)}
    captions = list(dict.fromkeys(c for b in batches for c in b["caption"]))
    return {c: len(s) for c, s in zip(captions, model.segment_texts(captions), strict=True)}


def generation_section(cfg: EvaluateConfig, evaluator: Any, ds: Any, batches: list[dict], generate: Any,
                       reconstruct: Reconstructor | None = None,
                       num_segments: dict[str, int] | None = None) -> dict[str, Any]:
    embed_text, embed_motion = t2m_embedders(evaluator, cfg.data, ds.mean, ds.std)
    if generate is not None:
        generate.expect(cfg.repeats * sum(len(b["id"]) for b in batches), "metrics")
    result = evaluate_generation(embed_text, embed_motion, generate, batches, repeats=cfg.repeats,
                                 batch_size=cfg.batch_size, mm_prompts=0, seed=cfg.seed,
                                 reconstruct=reconstruct, num_segments=num_segments)
    if reconstruct is not None:
        result["reconstruction"] |= reconstruct.errors
    if generate is not None and cfg.mm_prompts > 0 and cfg.mm_runs > 0:
        # One prompt per motion: a split with fewer motions than --mm-prompts gives fewer.
        prompts = min(cfg.mm_prompts, len({str(i) for b in batches for i in b["id"]}))
        if prompts < cfg.mm_prompts:
            warnings.warn(f"--mm-prompts {cfg.mm_prompts}: the split has {prompts} motions; "
                          f"MultiModality uses {prompts} prompts", stacklevel=2)
        generate.expect(cfg.mm_runs * prompts * cfg.mm_repeats, "multimodality")
        runs = multimodality_runs(embed_motion, generate, batches, cfg.mm_runs, prompts,
                                   cfg.mm_repeats, 10, cfg.seed)
        mean, interval = mean_and_interval(runs)
        result["generated"]["multimodality"] = {"mean": mean, "interval": interval}
        result["generated"]["multimodality_prompts"] = prompts
    return result


# -------------------------------------------------------------------------- retrieval

def _timed(cfg: EvaluateConfig, key: str, fn: Any, *args: Any) -> Any:
    start = time.perf_counter()
    value = fn(*args)
    cfg.timings[key] = round(time.perf_counter() - start, 2)
    return value


def evaluate(cfg: EvaluateConfig, model: Any = None) -> dict[str, Any]:
    """Run every section that applies, write OUT/metrics.json, report.md and plots; return
    the metrics dict. `model`: an already built SegMo (else loaded from `cfg.model`)."""
    out = Path(cfg.out)
    if cfg.model is None and model is None and not cfg.real_only:
        raise SegmoError("segmo evaluate: --model is required unless --real-only")
    start = time.perf_counter()
    started = time.time()  # file times: which plots in OUT this run drew
    evaluator = load_pretrained(cfg.evaluator).to(cfg.device).eval()
    if getattr(evaluator, "kind", None) != "evaluator":
        raise SegmoError(f"--evaluator {cfg.evaluator}: holds a {getattr(evaluator, 'kind', '?')!r} "
                         "model, not a T2M evaluator (train one with configs/evaluator/)")
    if not evaluator.meta.get("words"):  # checked before any generation, which needs it
        raise SegmoError(f"--evaluator {cfg.evaluator}: config.json's meta has no 'words' (the "
                         "vocabulary `segmo export` of an evaluator writes)")
    if cfg.real_only:
        model = None
    elif model is None:
        model = SegMo.from_pretrained(cfg.model, device=cfg.device)
    out.mkdir(parents=True, exist_ok=True)
    skeleton = model.skeleton.name if model is not None else (
        "kit" if evaluator.config.feature_dim == 251 else "t2m")
    cfg.name = cfg.name or ("Real" if model is None else Path(cfg.model or "model").name)
    ds, batches = load_batches(cfg, skeleton)
    segments_of = ({c: list(s) for b in batches for c, s in zip(b["caption"], b["segments"], strict=True)}
                   if cfg.text_segments else None)
    generate = Generator(model, cfg, ds.mean, ds.std, segments_of) if model is not None else None
    # A model trained without alignment (the "no align" ablation) has no shared space.
    aligned = model is not None and getattr(model.mask, "alignment", None) is not None
    has_truth = has_ground_truth(cfg.data)
    skip = set(cfg.skip)
    metrics: dict[str, Any] = {"notes": {}}
    if model is not None:
        _timed(cfg, "text_encoding", _encode_texts, cfg, model, batches, segments_of, has_truth)
    reconstruct = None
    if model is not None and "reconstruction" not in skip:
        _log(cfg, "tokenizer reconstruction")
        reconstruct = _timed(cfg, "reconstruction", Reconstructor, model, cfg, ds, batches)
    num_segments = num_segments_of(model, batches, segments_of)
    _log(cfg, f"generation metrics: {cfg.repeats} repeats of {sum(len(b['id']) for b in batches)} captions")
    metrics["generation"] = _timed(cfg, "generation", generation_section, cfg, evaluator, ds, batches, generate,
                                   reconstruct, num_segments)
    notes = metrics["notes"]

    def unavailable(section: str, need_truth: bool = False) -> str | None:
        """Why a learned-space section cannot run (None = it can); noted in the report."""
        if not aligned:
            return "the model has no alignment head (trained with alignment none)"
        if need_truth and not has_truth:
            return "the dataset has no segments/ ground truth"
        return None

    if "retrieval" not in skip:
        _log(cfg, "retrieval")
        retrieval = {"evaluator": _timed(cfg, "retrieval_evaluator", evaluator_retrieval, cfg, evaluator, ds,
                                         batches)}
        if model is not None and unavailable("retrieval") is None:
            retrieval["segmo"] = _timed(cfg, "retrieval_segmo", segmo_retrieval, cfg, model, ds, batches,
                                        segments_of)
            notes["retrieval"] = report.NOTES["retrieval"]
        elif model is not None:
            notes["retrieval"] = f"SegMo space skipped: {unavailable('retrieval')}."
        metrics["retrieval"] = retrieval
    if model is not None and "grounding" not in skip:
        # Attention grounding needs only the mask transformer: a model without the learned
        # space (alignment none) is still grounded by it, beside the text-free baselines.
        if has_truth:
            _log(cfg, "grounding")
            grounding = _timed(cfg, "grounding", grounding_section, cfg, model, ds, batches, out, aligned)
            if grounding:
                metrics["grounding"] = grounding
            notes["grounding"] = (report.NOTES["grounding"].format(window=cfg.grounding_window) if aligned else
                                  report.NOTES["grounding_attention"].format(reason=unavailable("grounding")))
        else:
            notes["grounding"] = f"Skipped: {unavailable('grounding', need_truth=True)}."
    if model is not None and "isc" not in skip:
        if unavailable("isc") is None:
            _log(cfg, "intra-segment consistency")
            metrics["isc"] = _timed(cfg, "isc", isc_section, cfg, model, ds, batches, segments_of)
            report.plot_isc(metrics["isc"], out / "isc.png")
            notes["isc"] = report.NOTES["isc"]
        else:
            notes["isc"] = f"Skipped: {unavailable('isc')}."
    if cfg.action_classifier and "action_order" not in skip:
        if has_truth:
            _log(cfg, "action order")
            clf = load_classifier(cfg, out)
            if generate is not None:
                generate.expect(len(first_rows(batches)), "action order")
            metrics["action_order"] = _timed(cfg, "action_order", action_order_section, cfg, clf, ds, batches,
                                             generate, reconstruct, num_segments)
            notes["action_order"] = report.NOTES["action_order"]
        else:
            notes["action_order"] = "Skipped: the dataset has no segments/ ground truth."
    if cfg.attribute_classifier and "attributes" not in skip:
        if has_truth:
            _log(cfg, "attributes")
            from segmo.evaluation.attributes import attribute_section
            from segmo.models.action_classifier import AttributeClassifier

            clf = AttributeClassifier.from_pretrained(cfg.attribute_classifier)
            metrics["attributes"] = _timed(cfg, "attributes", attribute_section, cfg, clf, ds, batches,
                                           generate, reconstruct)
            notes["attributes"] = report.NOTES["attributes"]
        else:
            notes["attributes"] = "Skipped: the dataset has no segments/ ground truth."
    cfg.timings["total"] = round(time.perf_counter() - start, 2)
    if generate is not None and generate.motions:
        cfg.timings["generation_ms_per_motion"] = round(1000 * generate.seconds / generate.motions, 2)
        cfg.timings["generated_motions"] = float(generate.motions)
    metrics["config"] = asdict(cfg) | {"motions": len({i for b in batches for i in b["id"]}),
                                       "captions": sum(len(b["id"]) for b in batches)}
    _remove_earlier_plots(out, started)
    # strict JSON: a NaN (one repeat's interval) is written as null, which report.cell reads as NaN
    write_atomic(out / "metrics.json", json_text(metrics, indent=2) + "\n")
    write_atomic(out / "report.md", report.render_report(metrics))
    return metrics


def _remove_earlier_plots(out: Path, started: float) -> None:
    """Remove the plots an earlier evaluation left in `out` that this one did not draw
    again (older than its start: a section skipped this time, fewer similarity maps):
    beside this run's metrics.json they would show another run's, or another model's,
    figures."""
    for pattern in ("isc.png", "similarity_maps/*.png"):
        for path in out.glob(pattern):
            if path.stat().st_mtime < started:
                path.unlink()
    maps = out / "similarity_maps"
    if maps.is_dir() and not any(maps.iterdir()):
        maps.rmdir()


def _encode_texts(cfg: EvaluateConfig, model: Any, batches: list[dict],
                  segments_of: dict[str, list[str]] | None, has_truth: bool) -> None:
    """Encode every caption and segment text once, in large batches: the pipeline caches
    sentence vectors per text, and encoding them one call at a time is far slower."""
    captions = list(dict.fromkeys(c for b in batches for c in b["caption"]))
    texts = captions + [t for s in (known_segments(captions, segments_of) or model.segment_texts(captions)) for t in s]
    if has_truth:
        for b, r in all_rows(batches):
            texts += [s["text"] for s in ground_truth(cfg, b["id"][r], b["caption_index"][r], 1) or []]
    texts = list(dict.fromkeys(texts))
    _log(cfg, f"encoding {len(texts)} texts with {model.text_encoder_name}")
    for s in range(0, len(texts), 256):
        model.encode_texts(texts[s:s + 256])


def _log(cfg: EvaluateConfig, message: str) -> None:
    if cfg.progress:
        print(f"[segmo evaluate] {message}", file=sys.stderr, flush=True)


def compare(paths: list[str], out: str | Path) -> str:
    """Put several metrics.json (files or evaluation directories) side by side in OUT/compare.md."""
    runs = []
    for p in paths:
        path = Path(p) / "metrics.json" if Path(p).is_dir() else Path(p)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no metrics.json (run `segmo evaluate` first)")
        metrics = read_json(path)
        config, generation = metrics.get("config", {}), metrics.get("generation", {})
        if not isinstance(config, dict) or not isinstance(generation, dict) or not all(
                isinstance(row, dict) for row in generation.values()):
            raise SegmoError(f"{path}: not a metrics.json of `segmo evaluate` ('generation' must "
                             "hold rows and 'config' be an object)")
        for key in ("real", "reconstruction", "generated"):
            for metric, _ in report.GENERATION_COLUMNS:
                value = generation.get(key, {}).get(metric)
                if value is not None and not report.is_metric(value):
                    raise SegmoError(f"{path}: generation.{key}.{metric}: expected a number or "
                                     f"{{\"mean\": ..., \"interval\": ...}}, got {value!r:.60}")
        runs.append((config.get("name") or path.parent.name, metrics))
    try:
        table = report.compare_table(runs)
    except ValueError:
        raise SegmoError("--compare: no metrics.json given has generation rows (real, "
                         "reconstruction or generated)") from None
    Path(out).mkdir(parents=True, exist_ok=True)
    write_atomic(Path(out) / "compare.md", table + "\n")
    return table


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="segmo evaluate", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", help="SegMo bundle directory (`segmo bundle`)")
    p.add_argument("--data", help="dataset root (HumanML3D layout)")
    p.add_argument("--evaluator", help="T2M evaluator model directory")
    p.add_argument("--out", type=output_folder, required=True, help="output directory")
    p.add_argument("--name", help="row name in the tables (default: the model directory's name)")
    p.add_argument("--split", default="test")
    p.add_argument("--repeats", type=positive_int, default=20)
    p.add_argument("--batch-size", type=positive_int, default=32)
    p.add_argument("--mm-prompts", type=non_negative_int, default=100, help="MultiModality prompts (one per motion: at most the split's motions); 0 disables")
    p.add_argument("--mm-repeats", type=positive_int, default=30, help="generations per prompt (> 10)")
    p.add_argument("--mm-runs", type=non_negative_int, default=1, help="MultiModality repetitions")
    p.add_argument("--action-classifier", help="action-classifier directory, or 'train' to fit one")
    p.add_argument("--attribute-classifier", help="attribute-classifier directory (built-in corpus): "
                                                  "accuracy of the side/count/speed a caption names")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--max-motions", type=positive_int, help="keep the first N motions of the split")
    p.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                   help="auto: bf16 on CPUs with native bf16 (AVX512-BF16, AMX), else fp32")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=positive_int, help="torch CPU threads (1 avoids stalls on a busy machine)")
    p.add_argument("--text-segments", help="use DATA/text_segments/NAME instead of the bundle's segmenter")
    p.add_argument("--steps", type=positive_int, default=None,
                   help="mask decoding steps (default: the bundle's, "
                        f"{SamplingOptions.steps} unless it says otherwise)")
    p.add_argument("--guidance-mode", choices=("cfg", "sink_ctrl"), default=None,
                   help="base-token guidance: cfg or sink_ctrl (default: the bundle's)")
    p.add_argument("--guidance-scale", type=finite_float, default=None,
                   help="CFG scale of the base tokens (default: the bundle's)")
    p.add_argument("--residual-guided-layers", type=non_negative_int, default=None,
                   help="how many residual layers, from the first, are guided (default: the "
                        "bundle's, all unless it says otherwise)")
    p.add_argument("--ctrl-k-base", type=finite_float, default=None,
                   help="sink_ctrl's correction strength k_base, in logits (default: the "
                        "bundle's; 0 = plain CFG)")
    p.add_argument("--unconditional", choices=("none", "local"), default=None,
                   help="what guidance's unconditional rows keep (default: the bundle's)")
    p.add_argument("--word-text", choices=get_args(WordText), default=None,
                   help="what a words model's word keys read: the caption or its text segments "
                        "in execution order (default: the bundle's)")
    p.add_argument("--segment-timing", choices=get_args(SegmentTiming), default=None,
                   help="what a mask transformer trained with segment timing is given: the "
                        "spans its timing head predicts, or none (default: the bundle's)")
    p.add_argument("--remasking", choices=get_args(Remasking), default=None,
                   help="which tokens each decoding step masks again: the least confident of "
                        "the motion, or of each segment (default: the bundle's)")
    p.add_argument("--segment-guidance", type=non_negative_float, default=None,
                   help="per-segment guidance weight of the base tokens, 0 = off (default: the "
                        "bundle's)")
    p.add_argument("--choice-temperature", type=non_negative_float, default=None,
                   help="MaskGIT choice temperature of the decoding steps' remasking, 0 = off "
                        "(default: the bundle's)")
    p.add_argument("--grounding-window", default="5",
                   help="sliding-window sizes in tokens of grounding's window row, e.g. 5 (the "
                        "paper's, default) or 4,8,16; auto = 0.5-2x the mean segment")
    p.add_argument("--retrieval-motions", type=non_negative_int, default=100,
                   help="motions of SegMo's full retrieval protocol (N^2 passes); 0 = all")
    p.add_argument("--skip", default="", help=f"comma-separated sections to leave out: {','.join(SECTIONS)}")
    p.add_argument("--no-progress", dest="progress", action="store_false")
    p.add_argument("--similarity-maps", type=non_negative_int, default=4, help="grounding maps to plot")
    p.add_argument("--real-only", action="store_true", help="evaluate the real motions only (no model)")
    p.add_argument("--compare", nargs="+", metavar="DIR", help="tabulate existing evaluations instead")
    return p


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.compare:
        print(compare(args.compare, args.out))
        return
    for flag in ("data", "evaluator"):
        if getattr(args, flag) is None:
            parser.error(f"--{flag} is required (unless --compare)")
    if args.model is None and not args.real_only:
        parser.error("--model is required (or --real-only)")
    if args.mm_prompts > 0 and args.mm_repeats <= 10:
        parser.error(f"--mm-repeats={args.mm_repeats} must exceed 10 (the pairs MultiModality draws)")
    for flag in ("model", "data", "evaluator"):
        value = getattr(args, flag)
        if value is not None and not Path(value).is_dir() and not (flag != "data" and is_hub_id(value)):
            parser.error(f"--{flag} {value}: no such directory")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        parser.error(f"--out {args.out}: exists and is not a directory")
    if args.batch_size < 2:
        parser.error(f"argument --batch-size: R-precision needs at least 2 rows, got {args.batch_size}")
    if not split_file(args.data, args.split).is_file():
        parser.error(f"--split {args.split}: {split_file(args.data, args.split)} does not exist")
    if args.text_segments and not (Path(args.data) / "text_segments" / args.text_segments).is_dir():
        parser.error(f"--text-segments {args.text_segments}: no folder "
                     f"{Path(args.data) / 'text_segments' / args.text_segments}")
    if args.attribute_classifier is not None and not Path(args.attribute_classifier).is_dir():
        parser.error(f"--attribute-classifier {args.attribute_classifier}: no such directory")
    if args.action_classifier not in (None, "train") and not Path(args.action_classifier).is_dir():
        parser.error(f"--action-classifier {args.action_classifier}: no such directory (or 'train')")
    window = args.grounding_window
    sizes = [ascii_whole_number(w.strip()) for w in window.split(",")]
    if window != "auto" and not all(size is not None and size >= 1 for size in sizes):
        parser.error(f"argument --grounding-window: 'auto' or window sizes >= 1 such as 5 or "
                     f"4,8,16, got {window!r:.80}")
    skip = tuple(x for x in args.skip.split(",") if x)
    unknown = set(skip) - set(SECTIONS)
    if unknown:
        parser.error(f"--skip: unknown section(s) {sorted(unknown)}; choose from {SECTIONS}")
    try:
        resolve_device(args.device)
    except SegmoError as error:
        parser.error(f"--device {args.device}: {str(error).removeprefix('SegMo: ')}")
    cores = os.cpu_count() or 1
    if args.threads and args.threads > 4 * cores:
        parser.error(f"--threads {args.threads}: this machine has {cores} CPU cores; give at most "
                     f"{4 * cores}")
    if args.threads:
        torch.set_num_threads(args.threads)
    keep_freed_memory()
    if args.precision == "auto":  # the report records what ran
        args.precision = resolve_precision("auto", torch.device(args.device))[0]
    cfg = EvaluateConfig(**{k: v for k, v in vars(args).items() if k not in ("compare", "skip", "threads")},
                         skip=skip)
    metrics = evaluate(cfg)
    print(report.generation_table(report._generation_rows(metrics)))
    print(f"wrote {Path(cfg.out) / 'metrics.json'} and {Path(cfg.out) / 'report.md'}")


if __name__ == "__main__":
    main()
