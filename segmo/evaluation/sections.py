"""What `segmo evaluate` measures beyond the generation metrics — retrieval, grounding,
segment consistency (ISC), action order — and the options and data plumbing shared with
`segmo.evaluation.cli`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from segmo.data.collate import collate
from segmo.data.humanml3d import MotionDataset
from segmo.data.layout import ground_truth_file, read_ground_truth, split_file
from segmo.errors import SegmoError
from segmo.evaluation import report
from segmo.evaluation.action_order import (
    collapse_spans,
    error_shares,
    evaluate_action_order,
    normalised_edit_distance,
    recall_by_share,
    sequence_accuracy,
)
from segmo.evaluation.grounding import auto_windows, grounding_metrics
from segmo.evaluation.metrics import (
    SEGMENT_BUCKETS,
    euclidean_distance_matrix,
    generation_seed,
    segment_bucket,
    t2m_embedders,
)
from segmo.evaluation.retrieval import batched_retrieval_metrics, retrieval_metrics
from segmo.models.action_classifier import ActionClassifier
from segmo.models.alignment import isc_from_cosines, paired_cosine
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline.grounding import (
    MIN_TOKENS,
    SEARCHES,
    attention_shares,
    locate,
    locate_by_attention,
    plot_similarity_map,
)
from segmo.pipeline.retrieval import pair_scores
from segmo.segmentation import get_motion_segmenter, pool_tokens

SEGMENTERS: tuple[str, ...] = ("uniform", "cpd", "kmeans")
# Attention grounding's rows of the grounding section: key prefix → search.
ATTENTION = {"attention": "ordered", "attention_spans": "spans"}
SECTIONS: tuple[str, ...] = ("reconstruction", "retrieval", "grounding", "isc", "action_order", "attributes")


@dataclass
class EvaluateConfig:
    """Options of one evaluation (the command-line flags)."""

    data: str
    evaluator: str
    out: str
    model: str | None = None
    name: str | None = None
    split: str = "test"
    repeats: int = 20
    batch_size: int = 32
    mm_prompts: int = 100
    mm_repeats: int = 30
    mm_runs: int = 1
    action_classifier: str | None = None
    attribute_classifier: str | None = None
    seed: int = 0
    max_motions: int | None = None
    precision: str = "fp32"
    device: str = "cpu"
    text_segments: str | None = None
    steps: int | None = None  # None: the bundle's (`SegMo.sampling`)
    residual_guided_layers: int | None = None  # None: the bundle's
    guidance_mode: str | None = None  # "cfg" | "sink_ctrl"; None: the bundle's
    guidance_scale: float | None = None  # None: the bundle's
    ctrl_k_base: float | None = None  # sink_ctrl's correction strength; None: the bundle's
    unconditional: str | None = None  # "none" | "local"; None: the bundle's
    word_text: str | None = None  # "caption" | "segments"; None: the bundle's
    segment_timing: str | None = None  # "predicted" | "none"; None: the bundle's
    remasking: str | None = None  # "confidence" | "segments"; None: the bundle's
    segment_guidance: float | None = None  # per-segment guidance weight; None: the bundle's
    choice_temperature: float | None = None  # MaskGIT's choice temperature; None: the bundle's
    grounding_window: str = "5"
    retrieval_motions: int = 100
    progress: bool = True
    skip: tuple[str, ...] = ()
    similarity_maps: int = 4
    real_only: bool = False
    timings: dict[str, float] = field(default_factory=dict)


# ------------------------------------------------------------------------------- data

def load_batches(cfg: EvaluateConfig, skeleton: str) -> tuple[Any, list[dict]]:
    """The split as a MotionDataset (one sample per caption, whole clips cropped to
    multiples of 4 from the end) and its collated batches, in file order."""
    ds = MotionDataset(cfg.data, cfg.split, skeleton, text_segments=cfg.text_segments,
                       max_motions=cfg.max_motions)
    ds.mean, ds.std = np.array(ds.mean, dtype=np.float32), np.array(ds.std, dtype=np.float32)
    if len(ds) == 0:
        raise SegmoError(f"{split_file(cfg.data, cfg.split)}: no usable samples ({ds.summary})")
    return ds, list(DataLoader(ds, batch_size=64, collate_fn=collate))


def all_rows(batches: list[dict]) -> list[tuple[dict, int]]:
    return [(b, r) for b in batches for r in range(len(b["id"]))]


def raw_features(ds: Any, b: dict, r: int) -> np.ndarray:
    """Raw features (t, d) of row r of a collated batch (undoing the dataset's z-score)."""
    t = int(b["lengths"][r])
    return (b["motion"][r, :t].numpy() * ds.std + ds.mean).astype(np.float32)


def first_rows(batches: list[dict]) -> list[tuple[dict, int]]:
    """One row per sample id (its first caption), in order."""
    seen, out = set(), []
    for b, r in all_rows(batches):
        if b["id"][r] not in seen:
            seen.add(b["id"][r])
            out.append((b, r))
    return out


def _index(batches: list[dict]) -> tuple[np.ndarray, list[tuple[dict, int]]]:
    """text_to_motion (N,) of every row, and the first row of each motion."""
    firsts = first_rows(batches)
    ids = {b["id"][r]: i for i, (b, r) in enumerate(firsts)}
    return np.array([ids[b["id"][r]] for b, r in all_rows(batches)]), firsts


def _protocols(scores: np.ndarray, index: np.ndarray, distance: bool, cfg: EvaluateConfig) -> dict:
    out = {"full": retrieval_metrics(scores, index, distance)}
    if scores.shape[1] >= cfg.batch_size:
        out[f"batches of {cfg.batch_size}"] = batched_retrieval_metrics(
            scores, index, distance, batch_size=cfg.batch_size, seed=cfg.seed)
    return out


def evaluator_retrieval(cfg: EvaluateConfig, evaluator: Any, ds: Any, batches: list[dict]) -> dict:
    embed_text, embed_motion = t2m_embedders(evaluator, cfg.data, ds.mean, ds.std)
    index, firsts = _index(batches)
    text = np.concatenate([embed_text(b["caption"], [(b, r) for r in range(len(b["id"]))]) for b in batches])
    motion = []
    for s in range(0, len(firsts), 64):
        chunk = firsts[s:s + 64]
        lengths = torch.stack([b["lengths"][r] for b, r in chunk])
        m = torch.zeros(len(chunk), int(lengths.max()), ds.mean.shape[0])
        for k, (b, r) in enumerate(chunk):
            m[k, : int(lengths[k])] = b["motion"][r, : int(lengths[k])]
        motion.append(np.asarray(embed_motion(m, lengths)))
    return _protocols(euclidean_distance_matrix(text, np.concatenate(motion)), index, True, cfg)


def _pair_scores(model: Any, captions: list[str], segments: list[list[str]], motions: list[np.ndarray],
                 pairs: list[tuple[int, int]], batch_size: int, progress: bool = False) -> np.ndarray:
    """Mean paired-segment cosine (uniform spans) of each (text i, motion j) pair, (len(pairs),).
    SegMo's motion features depend on the text prefix, so every pair is its own forward pass."""
    out = []
    for s in tqdm(range(0, len(pairs), batch_size), desc="pairs", leave=False, disable=not progress):
        chunk = pairs[s:s + batch_size]
        t, m, mask = model.embed_pairs([captions[i] for i, _ in chunk], [motions[j] for _, j in chunk],
                                       "uniform", segments=[segments[i] for i, _ in chunk])
        out.append(pair_scores(t.float(), m.float(), mask.bool()).cpu().numpy())
    return np.concatenate(out)


def segmo_retrieval(cfg: EvaluateConfig, model: Any, ds: Any, batches: list[dict],
                    segments_of: dict[str, list[str]] | None) -> dict:
    """Retrieval in SegMo's space, score = mean cosine of the paired segments (as
    `SegMo.retrieve_motions`). Full protocol on the first `retrieval_motions` motions with
    their first caption (N² forward passes); batches protocol as `batched_retrieval_metrics`."""
    firsts = first_rows(batches)
    captions = [b["caption"][r] for b, r in firsts]
    segments = known_segments(captions, segments_of) or model.segment_texts(captions)
    motions = [raw_features(ds, b, r) for b, r in firsts]
    out = {}
    k = len(firsts) if cfg.retrieval_motions <= 0 else min(cfg.retrieval_motions, len(firsts))
    pairs = [(i, j) for i in range(k) for j in range(k)]
    full = _pair_scores(model, captions, segments, motions, pairs, cfg.batch_size, cfg.progress).reshape(k, k)
    out[f"full ({k} motions)"] = retrieval_metrics(full)
    if len(firsts) >= cfg.batch_size:
        # One random caption per motion, shuffled blocks of batch_size motions, metrics averaged.
        rows = all_rows(batches)
        by_id: dict[str, list[int]] = {}
        for i, (b, r) in enumerate(rows):
            by_id.setdefault(b["id"][r], []).append(i)
        rng = np.random.default_rng(cfg.seed)
        pick = [by_id[b["id"][r]][rng.integers(len(by_id[b["id"][r]]))] for b, r in firsts]
        all_captions = [b["caption"][r] for b, r in rows]
        all_segments = known_segments(all_captions, segments_of) or model.segment_texts(all_captions)
        order = rng.permutation(len(firsts))
        blocks = []
        for s in range(0, (len(order) // cfg.batch_size) * cfg.batch_size, cfg.batch_size):
            block = order[s:s + cfg.batch_size]
            texts = [all_captions[pick[j]] for j in block]
            segs = [all_segments[pick[j]] for j in block]
            pairs = [(i, j) for i in range(len(block)) for j in range(len(block))]
            scores = _pair_scores(model, texts, segs, [motions[j] for j in block], pairs, cfg.batch_size)
            blocks.append(retrieval_metrics(scores.reshape(len(block), len(block))))
        out[f"batches of {cfg.batch_size}"] = {key: float(np.mean([bl[key] for bl in blocks])) for key in blocks[0]}
    return out


def known_segments(captions: list[str], segments_of: dict[str, list[str]] | None) -> list[list[str]] | None:
    return [segments_of.get(c, [c]) for c in captions] if segments_of else None


# ---------------------------------------------------------------------- grounding, ISC

def ground_truth(cfg: EvaluateConfig, mid: str, caption_index: int, t: int) -> list[dict] | None:
    """Ground-truth segments of one caption clipped to the motion's first t frames."""
    if not ground_truth_file(cfg.data, mid).is_file():
        return None
    segs = read_ground_truth(cfg.data, mid)["captions"][caption_index]["segments"]
    return [dict(s, start=min(int(s["start"]), t), end=min(int(s["end"]), t)) for s in segs]


def _windows(cfg: EvaluateConfig, n: int, a: int) -> int | list[int]:
    """Window sizes in tokens of the "window" row: "auto" = `auto_windows` (0.5–2× the mean
    segment length), else the given comma-separated sizes (default 5, the paper's)."""
    if cfg.grounding_window == "auto":
        return auto_windows(n, a)
    return [int(w) for w in str(cfg.grounding_window).split(",")]


def grounding_section(cfg: EvaluateConfig, model: Any, ds: Any, batches: list[dict], out: Path,
                      similarity: bool = True) -> dict[str, float] | None:
    """Ground the true segments of every caption with ≥ 2 of them, with each search of
    `segmo.pipeline.grounding` on one pass per caption; R@1 at IoU and mIoU of the chosen
    span vs the true span. Keys: the default search ("ordered") plain, "spans/...",
    "window/..." (`--grounding-window`), "attention/..." and "attention_spans/..." (method
    "attention", searches "ordered" and "spans"), and "uniform/...", "cpd/...", "kmeans/..." for the
    text-free motion segmenters told the number of segments (baselines; cpd and kmeans on
    the z-scored features pooled per token). The maps plotted are the ordered search's.
    similarity False (a model without an alignment head, so no learned space): the attention
    and baseline keys only, no plain keys and no maps."""
    searches = SEARCHES if similarity else ()
    pred: dict[str, list] = {search: [] for search in (*searches, *ATTENTION)}
    baselines: dict[str, list] = {name: [] for name in SEGMENTERS}
    gold, plotted = [], 0
    for b, r in tqdm(all_rows(batches), desc="grounding", disable=not cfg.progress):
        t = int(b["lengths"][r])
        truth = ground_truth(cfg, b["id"][r], b["caption_index"][r], t)
        n = t // FRAMES_PER_TOKEN
        if not truth or not 2 <= len(truth) <= min(model.max_segments, n // MIN_TOKENS) or any(
                s["end"] <= s["start"] for s in truth):
            continue
        motion = raw_features(ds, b, r)
        texts = [s["text"] for s in truth]
        found = {}
        if similarity:
            space = model.embed_segments([b["caption"][r]], [motion], segments=[texts])
            found = {search: locate(space, b["caption"][r], len(motion), search,
                                    window=_windows(cfg, n, len(truth)) if search == "window" else None)
                     for search in SEARCHES}
        share = attention_shares(model, b["caption"][r], motion, texts)  # one pass, both searches
        for name, search in ATTENTION.items():
            found[name] = locate_by_attention(b["caption"][r], texts, share, len(motion), search)
        for search, g in found.items():
            pred[search] += [tuple(p) for p in g.best_spans_frames]
        gold += [(s["start"], s["end"]) for s in truth]
        tokens = pool_tokens(b["motion"][r, :t].numpy())
        for name, spans in baselines.items():
            spans += [(FRAMES_PER_TOKEN * s, FRAMES_PER_TOKEN * e)
                      for s, e in get_motion_segmenter(name)(tokens, len(truth), n)]
        if similarity and plotted < cfg.similarity_maps:
            plt = report._pyplot()
            (out / "similarity_maps").mkdir(parents=True, exist_ok=True)
            ax = plot_similarity_map(found["ordered"], truth=[(s["start"], s["end"]) for s in truth],
                                     title=b["caption"][r] + "\ntruth (frames): " + ", ".join(
                                         f"{s['start']}-{s['end']}" for s in truth))
            ax.figure.tight_layout()
            ax.figure.savefig(out / "similarity_maps" / f"{b['id'][r]}_{b['caption_index'][r]}.png", dpi=110)
            plt.close(ax.figure)
            plotted += 1
    if not gold:
        return None
    result = {"queries": float(len(gold))}
    for name, spans in (*pred.items(), *baselines.items()):
        scores = grounding_metrics(np.array(spans), np.array(gold))
        result |= scores if name == "ordered" else {f"{name}/{k}": v for k, v in scores.items()}
    return result


def isc_section(cfg: EvaluateConfig, model: Any, ds: Any, batches: list[dict],
                segments_of: dict[str, list[str]] | None) -> dict[str, dict[str, float]]:
    rows = all_rows(batches)
    out = {}
    for name in SEGMENTERS:
        cosines = []
        for s in range(0, len(rows), cfg.batch_size):
            chunk = rows[s:s + cfg.batch_size]
            captions = [b["caption"][r] for b, r in chunk]
            t, m, mask = model.embed_pairs(captions, [raw_features(ds, b, r) for b, r in chunk], name,
                                           segments=known_segments(captions, segments_of))
            cosines.append(paired_cosine(t.float(), m.float(), mask.bool()).cpu())
        c = torch.cat(cosines)
        mean, cv = isc_from_cosines(c)
        out[name] = {"mean": mean, "cv": cv, "pairs": float(c.numel())}
    return out


# ------------------------------------------------------------------------ action order

def load_classifier(cfg: EvaluateConfig, out: Path) -> Any:
    if cfg.action_classifier == "train":
        # Lightning takes seconds to import; only this option trains anything.
        from segmo.tasks.action_classifier import train_action_classifier

        clf = train_action_classifier(cfg.data, epochs=10, seed=cfg.seed)
        clf.save_pretrained(out / "action_classifier")
        return clf
    return ActionClassifier.from_pretrained(cfg.action_classifier)


def _order_metrics(preds: list[list[str]], trues: list[list[str]], shares: list[list[float]]
                   ) -> dict[str, Any]:
    """Sequence accuracy, normalised edit distance, the `error_shares` of the failures and
    `recall_by_share` (`shares`: each true action's share of its motion)."""
    return {"sequence_accuracy": sequence_accuracy(preds, trues),
            "normalised_edit_distance": normalised_edit_distance(preds, trues),
            "motions": float(len(preds)), "errors": error_shares(preds, trues),
            "recall_by_share": recall_by_share(preds, trues, shares)}


def action_order_section(cfg: EvaluateConfig, clf: Any, ds: Any, batches: list[dict], generate: Any,
                         reconstruct: Any = None, num_segments: dict[str, int] | None = None
                         ) -> dict[str, Any]:
    """Action order of the real motions (`evaluate_action_order`, with frame accuracy), and of
    the motions generated from / reconstructed (`cli.Reconstructor`) for each motion's first
    caption, vs that caption's actions, with the kinds of failure and how often actions are
    found by their share of the motion (`segmo.evaluation.action_order`); with
    `num_segments` (caption → its text segments) also per `SEGMENT_BUCKETS` bucket of the
    first captions, real motions included."""
    result = {"real": evaluate_action_order(clf, cfg.data, cfg.split, max_motions=cfg.max_motions)}
    if generate is None:
        return result
    firsts = [(b, r) for b, r in first_rows(batches) if ground_truth(cfg, b["id"][r], b["caption_index"][r], 1)]
    truth = [collapse_spans(ground_truth(cfg, b["id"][r], b["caption_index"][r], int(b["lengths"][r])),
                            int(b["lengths"][r])) for b, r in firsts]
    trues = [actions for actions, _ in truth]
    shares = [share for _, share in truth]
    preds: dict[str, list[list[str]]] = {"generated": []}
    for s in range(0, len(firsts), cfg.batch_size):
        chunk = firsts[s:s + cfg.batch_size]
        captions = [b["caption"][r] for b, r in chunk]
        lengths = torch.stack([b["lengths"][r] for b, r in chunk])
        features, got = generate.raw(captions, lengths, generation_seed(cfg.seed, 9_000_000 + s))
        preds["generated"] += [clf.predict_sequence(features[k, : int(got[k])].numpy()) for k in range(len(chunk))]
    if reconstruct is not None:
        preds["reconstruction"] = [clf.predict_sequence(reconstruct.raw(b["id"][r])) for b, r in firsts]
    if not firsts:
        return result
    result |= {name: _order_metrics(p, trues, shares) for name, p in preds.items()}
    if num_segments is not None:
        preds = {"real": [clf.predict_sequence(raw_features(ds, b, r)) for b, r in firsts]} | preds
        bucket = [segment_bucket(num_segments[b["caption"][r]]) for b, r in firsts]
        result["by_num_segments"] = {}
        for k in SEGMENT_BUCKETS:
            rows = [i for i, x in enumerate(bucket) if x == k]
            if rows:
                result["by_num_segments"][k] = {
                    name: _order_metrics([p[i] for i in rows], [trues[i] for i in rows],
                                         [shares[i] for i in rows])
                    for name, p in preds.items()} | {"count": len(rows)}
    return result


# ---------------------------------------------------------------------------- driver
