"""T2M generation metrics (spec §9): R-precision, MM-Dist, FID, Diversity, MultiModality.

Pure functions over numpy arrays of embeddings (torch tensors are accepted and converted),
plus `evaluate_generation`, which runs the whole protocol for any generator:

- test split in batches of 32, shuffled, last incomplete batch dropped; one random caption
  per motion (a dataloader over captions yields them; `evaluate_generation` keeps one per
  motion id per repeat); the generator is given the ground-truth lengths;
- R-precision top-1/2/3 from each batch's 32×32 Euclidean distance matrix, MM-Dist = the
  mean matched distance, FID between the real and generated motion embeddings of the split,
  Diversity over 300 random pairs (fewer, with a warning, when a split has ≤ 300 motions,
  like the built-in corpus's test split), MultiModality over `mm_repeats` generations of
  `mm_prompts` prompts (10 pairs each);
- `repeats` (20) repetitions with different seeds, reported as mean ± 1.96·std/√repeats.
A "real" row evaluates the ground-truth motions the same way (its FID is against itself
under a different caption draw, ≈ 0), a "reconstruction" row the tokenizer's round trip of
them, and `by_num_segments` every row again per bucket of the captions' number of text
segments, all through `row_metrics`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import torch

from segmo.errors import SegmoError

# Defined with the evaluator, whose training logs them too; part of the §9 metrics here.
from segmo.models.evaluator import euclidean_distance_matrix, r_precision  # noqa: F401, I001
from segmo.text.vocabulary import CaptionTokens


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def generation_seed(seed: int, offset: int) -> int:
    """The seed of one generated batch of an evaluation run with `seed`: `offset` names the
    batch (its section, repetition and place). Folded into the 63 bits a torch.Generator
    takes: `--seed 20000000000000` (below 2^63, so accepted) made seeds beyond 2^64, and a
    ValueError traceback from torch after the real motions had been scored. Seeds below
    about 9.2e12 give the numbers they always gave."""
    return (int(seed) * 1_000_003 + int(offset)) % 2**63


def _rng(generator: np.random.Generator | None, seed: int | None) -> np.random.Generator:
    return generator if generator is not None else np.random.default_rng(seed)


def matching_score(text_emb: Any, motion_emb: Any) -> float:
    """MM-Dist: mean Euclidean distance between paired rows (n, d)."""
    t, m = _np(text_emb), _np(motion_emb)
    if t.shape != m.shape:
        raise ValueError(f"matching_score: shapes {t.shape} and {m.shape} differ")
    return float(np.linalg.norm(t - m, axis=1).mean())


def _sqrtm_psd(s: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh((s + s.T) / 2)
    return (v * np.sqrt(np.clip(w, 0, None))) @ v.T


def frechet_distance(mu1: Any, sigma1: Any, mu2: Any, sigma2: Any) -> float:
    """Fréchet distance between N(mu1, sigma1) and N(mu2, sigma2):
    |mu1 − mu2|² + tr(S1 + S2 − 2 (S1 S2)^½).

    tr((S1 S2)^½) is computed as the sum of square roots of the eigenvalues of the
    symmetric PSD matrix S1^½ S2 S1^½, which has the same spectrum and avoids a complex
    matrix square root.
    """
    mu1, mu2 = _np(mu1).reshape(-1), _np(mu2).reshape(-1)
    s1, s2 = np.atleast_2d(_np(sigma1)), np.atleast_2d(_np(sigma2))
    if mu1.shape != mu2.shape or s1.shape != s2.shape or s1.shape != (len(mu1), len(mu1)):
        raise ValueError(f"frechet_distance: inconsistent shapes {mu1.shape}, {s1.shape}, {mu2.shape}, {s2.shape}")
    r1 = _sqrtm_psd(s1)
    eig = np.linalg.eigvalsh((r1 @ s2 @ r1 + (r1 @ s2 @ r1).T) / 2)
    tr_covmean = np.sqrt(np.clip(eig, 0, None)).sum()
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * tr_covmean)


def fid(real_emb: Any, gen_emb: Any) -> float:
    """FID between two sets of embeddings (n, d) and (m, d) (sample mean and covariance)."""
    a, b = _np(real_emb), _np(gen_emb)
    if len(a) < 2 or len(b) < 2:
        raise ValueError("fid: need at least 2 embeddings on each side")
    return frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False))


def diversity(emb: Any, num_pairs: int = 300, generator: np.random.Generator | None = None,
              seed: int | None = None) -> float:
    """Mean distance between `num_pairs` random pairs of rows of emb (n, d), n > num_pairs.

    Two independent draws of `num_pairs` distinct indices, paired in order.
    """
    e = _np(emb)
    if len(e) <= num_pairs:
        raise ValueError(f"diversity: need more than num_pairs={num_pairs} embeddings, got {len(e)}")
    rng = _rng(generator, seed)
    i = rng.choice(len(e), num_pairs, replace=False)
    j = rng.choice(len(e), num_pairs, replace=False)
    return float(np.linalg.norm(e[i] - e[j], axis=1).mean())


def multimodality(emb: Any, num_pairs: int = 10, generator: np.random.Generator | None = None,
                  seed: int | None = None) -> float:
    """Mean distance between generations of the same prompt.

    emb (n_prompts, n_repeats, d), n_repeats > num_pairs: per prompt the same two draws of
    `num_pairs` distinct repeat indices are paired; the mean over prompts and pairs.
    """
    e = _np(emb)
    if e.ndim != 3 or e.shape[1] <= num_pairs:
        raise ValueError(f"multimodality: expected (n_prompts, n_repeats > {num_pairs}, d), got {e.shape}")
    rng = _rng(generator, seed)
    i = rng.choice(e.shape[1], num_pairs, replace=False)
    j = rng.choice(e.shape[1], num_pairs, replace=False)
    return float(np.linalg.norm(e[:, i] - e[:, j], axis=-1).mean())


def mean_and_interval(values: Any) -> tuple[float, float]:
    """(mean, 1.96·std/√n) of n repeated measurements (population std, as the T2M code);
    the interval is NaN for one measurement, which has no spread to estimate (it was 0, and
    a single MultiModality run read "± 0.000"), as across seeds (`segmo.evaluation.seeds`);
    metrics.json writes it as null."""
    v = _np(values).reshape(-1)
    if v.size == 0:
        raise ValueError("mean_and_interval: no values")
    if v.size == 1:
        return float(v[0]), float("nan")
    return float(v.mean()), float(1.96 * v.std() / np.sqrt(v.size))


# ------------------------------------------------------------------------- the protocol

EmbedText = Callable[[list[str], dict], Any]
EmbedMotion = Callable[[torch.Tensor, torch.Tensor], Any]
Generate = Callable[[list[str], torch.Tensor, int], torch.Tensor]


def _one_caption_per_motion(batches: Iterable[dict], rng: np.random.Generator, batch_size: int
                            ) -> list[dict]:
    """Regroup caption samples into shuffled batches with one random caption per motion.

    Each input batch is a collated dict (`motion`, `lengths`, `caption`, `id`, ...); rows
    with the same sample `id` are captions of one motion (a time-tagged sub-clip has its own
    id). Returns batches of exactly `batch_size` rows (drop_last), each with `rows`, the
    (input batch, row) pairs it was built from.
    """
    groups: dict[str, list[tuple[dict, int]]] = {}
    for b in batches:
        for r, sid in enumerate(b["id"]):
            groups.setdefault(str(sid), []).append((b, r))
    keys = sorted(groups)
    picks = [groups[k][rng.integers(len(groups[k]))] for k in keys]
    order = rng.permutation(len(picks))
    out = []
    for s in range(0, (len(order) // batch_size) * batch_size, batch_size):
        rows = [picks[i] for i in order[s:s + batch_size]]
        lengths = torch.stack([torch.as_tensor(b["lengths"][r]) for b, r in rows])
        t = int(lengths.max())
        motion = torch.zeros(len(rows), t, rows[0][0]["motion"].shape[-1])
        for k, (b, r) in enumerate(rows):
            motion[k, : int(lengths[k])] = b["motion"][r, : int(lengths[k])]
        out.append({"motion": motion, "lengths": lengths, "caption": [b["caption"][r] for b, r in rows],
                    "id": [b["id"][r] for b, r in rows],
                    "rows": rows})
    return out


def t2m_embedders(evaluator: Any, dataset_root: Any, mean: Any, std: Any
                  ) -> tuple[Callable[[list[str], list[tuple[dict, int]]], np.ndarray], EmbedMotion]:
    """The (embed_text, embed_motion) pair of `evaluate_generation` for a `T2MEvaluator`.

    Texts use the word/POS tokens of `dataset_root/texts` (via the rows' `id` and
    `caption_index`); motions are z-scored with the dataset's `mean`/`std` (d,), which
    `embed_motion` swaps for the evaluator's own statistics.
    """
    tokens = CaptionTokens(dataset_root)
    device = evaluator.mean.device
    mean, std = torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32)

    def embed_text(captions: list[str], rows: list[tuple[dict, int]]) -> np.ndarray:
        lists = [tokens(c, b.get("id", [None] * (r + 1))[r], b.get("caption_index", [None] * (r + 1))[r])
                 for c, (b, r) in zip(captions, rows, strict=True)]
        return evaluator.embed_captions(lists).cpu().numpy()

    def embed_motion(motion: torch.Tensor, lengths: torch.Tensor) -> np.ndarray:
        return evaluator.embed_motion(motion.to(device), lengths, mean, std).cpu().numpy()

    return embed_text, embed_motion


Reconstruct = Callable[[torch.Tensor, torch.Tensor, list[str]], torch.Tensor]
ROWS: tuple[str, ...] = ("real", "generated", "reconstruction")
# Buckets of the number of text segments of a caption (as HumanML3D-E splits real data).
SEGMENT_BUCKETS: tuple[str, ...] = ("1", "2", "3", "4-5")


def segment_bucket(num_segments: int) -> str:
    """The `SEGMENT_BUCKETS` name of a caption with `num_segments` (≥ 1) text segments."""
    if num_segments < 1:
        raise ValueError(f"segment_bucket: a caption has at least one segment, got {num_segments}")
    return str(num_segments) if num_segments <= 3 else "4-5"


def row_metrics(text_e: np.ndarray, emb: np.ndarray, reference: np.ndarray, rng: np.random.Generator,
                top_k: int = 3, batch_size: int = 32, diversity_pairs: int = 300) -> dict[str, float]:
    """One repeat's metrics of paired text/motion embeddings (n, e), FID against `reference`
    (m, e). A metric the rows are too few for is left out: R-precision below `batch_size`
    rows, FID and Diversity below 2; Diversity uses min(diversity_pairs, n − 1) pairs."""
    out: dict[str, float] = {}
    if len(emb) >= batch_size:
        out |= {f"top{k}": float(p) for k, p in enumerate(r_precision(text_e, emb, top_k, batch_size), 1)}
    out["matching"] = matching_score(text_e, emb)
    if len(emb) >= 2 and len(reference) >= 2:
        out["fid"] = fid(reference, emb)
        out["diversity"] = diversity(emb, min(diversity_pairs, len(emb) - 1), generator=rng)
    return out


def _summary(values: dict[str, list[float]], repeats: int) -> dict[str, dict[str, float]]:
    """{metric: {"mean", "interval"}} of the metrics measured in every one of `repeats`."""
    return {k: dict(zip(("mean", "interval"), mean_and_interval(v), strict=True))
            for k, v in values.items() if len(v) == repeats}


def evaluate_generation(
    embed_text: Callable[[list[str], list[tuple[dict, int]]], Any],
    embed_motion: EmbedMotion,
    generate: Generate | None,
    dataloader: Iterable[dict],
    repeats: int = 20,
    batch_size: int = 32,
    top_k: int = 3,
    diversity_pairs: int = 300,
    mm_prompts: int = 100,
    mm_repeats: int = 30,
    mm_pairs: int = 10,
    seed: int = 0,
    reconstruct: Reconstruct | None = None,
    num_segments: dict[str, int] | None = None,
) -> dict[str, Any]:
    """The spec §9 protocol for one generator, with a "real" row; returns
    {"real": {metric: {"mean", "interval"}}, "generated": {...}, "reconstruction": {...}}
    and, given `num_segments`, "by_num_segments": {bucket: {"real": ..., "generated": ...,
    "reconstruction": ..., "count", "per_repeat", "left_out"}}.

    embed_text(captions, rows) → (b, e): `rows` are (collated batch, row) pairs the captions
    came from, so an embedder can read e.g. word/POS tokens stored alongside.
    embed_motion(motion (b, t, d) as in the dataloader, lengths (b,)) → (b, e).
    generate(captions, lengths (b,), seed) → motion (b, t, d) in the dataloader's
    normalisation, or None for the real row only. reconstruct(motion (b, t, d), lengths (b,),
    ids) → motion (b, t, d) likewise: the tokenizer's row (the generator's ceiling), or None.
    The dataloader yields collated caption samples of the test split (all captions); it is
    read once and kept in memory.
    Metrics: "top1".."top{top_k}", "matching", "fid", "diversity", and "multimodality"
    when mm_prompts > 0 and generate is given; all by `row_metrics`.
    num_segments: caption → its number of text segments. Each repeat's rows are then also
    measured per `SEGMENT_BUCKETS` bucket by `row_metrics` (R-precision in consecutive
    batches of the bucket's shuffled rows; FID against the real motions of the bucket); a
    metric missing from any repeat is left out of the bucket and named in "left_out".
    "count" is the bucket's captions in the split, "per_repeat" its mean rows per repeat.
    """
    batches = list(dataloader)
    names = ["real"] + (["generated"] if generate is not None else []) + (
        ["reconstruction"] if reconstruct is not None else [])
    rows_out: dict[str, dict[str, list[float]]] = {name: {} for name in names}
    buckets_out: dict[str, dict[str, dict[str, list[float]]]] = {
        k: {name: {} for name in names} for k in SEGMENT_BUCKETS}
    sizes: dict[str, list[int]] = {k: [] for k in SEGMENT_BUCKETS}
    real_reference: np.ndarray | None = None
    bucket_reference: dict[str, np.ndarray] = {}
    for rep in range(repeats):
        rng = np.random.default_rng([seed, rep])
        groups = _one_caption_per_motion(batches, rng, batch_size)
        if not groups:
            raise SegmoError(f"evaluate_generation: fewer than batch_size={batch_size} motions "
                             "in the split; lower --batch-size")
        text, real, fake, recon = [], [], [], []
        for g_index, g in enumerate(groups):
            text.append(_np(embed_text(g["caption"], g["rows"])))
            real.append(_np(embed_motion(g["motion"], g["lengths"])))
            if generate is not None:
                gen_seed = generation_seed(seed, rep * 10_007 + g_index)
                fake.append(_np(embed_motion(generate(g["caption"], g["lengths"], gen_seed), g["lengths"])))
            if reconstruct is not None:
                recon.append(_np(embed_motion(reconstruct(g["motion"], g["lengths"], g["id"]), g["lengths"])))
        text_e, real_e = np.concatenate(text), np.concatenate(real)
        if real_reference is None:
            real_reference = real_e
        sets = {"real": real_e} | ({"generated": np.concatenate(fake)} if fake else {}) | (
            {"reconstruction": np.concatenate(recon)} if recon else {})
        if rep == 0 and len(real_e) <= diversity_pairs:
            warnings.warn(f"evaluate_generation: {len(real_e)} motions per repeat; Diversity uses "
                          f"{len(real_e) - 1} pairs instead of {diversity_pairs}", stacklevel=2)
        for name, emb in sets.items():
            reference = real_reference if name == "real" and rep > 0 else real_e
            for k, v in row_metrics(text_e, emb, reference, rng, top_k, batch_size, diversity_pairs).items():
                rows_out[name].setdefault(k, []).append(v)
        if num_segments is None:
            continue
        bucket = np.array([segment_bucket(num_segments[c]) for g in groups for c in g["caption"]])
        for b_index, k in enumerate(SEGMENT_BUCKETS):
            rows = np.flatnonzero(bucket == k)
            sizes[k].append(len(rows))
            if len(rows) == 0:
                continue
            bucket_reference.setdefault(k, real_e[rows])
            for name, emb in sets.items():
                reference = bucket_reference[k] if name == "real" else real_e[rows]
                # A generator per bucket and row: the overall rows draw what they drew without
                # buckets, and a row's numbers do not depend on which other rows ran.
                row_rng = np.random.default_rng([seed, rep, 2, b_index, ROWS.index(name)])
                for m, v in row_metrics(text_e[rows], emb[rows], reference, row_rng, top_k, batch_size,
                                        diversity_pairs).items():
                    buckets_out[k][name].setdefault(m, []).append(v)
    if generate is not None and mm_prompts > 0:
        rows_out["generated"]["multimodality"] = multimodality_runs(
            embed_motion, generate, batches, repeats, mm_prompts, mm_repeats, mm_pairs, seed)
    result: dict[str, Any] = {name: _summary(values, repeats) for name, values in rows_out.items()}
    if num_segments is not None:
        counts = {k: 0 for k in SEGMENT_BUCKETS}
        for b in batches:
            for c in b["caption"]:
                counts[segment_bucket(num_segments[c])] += 1
        result["by_num_segments"] = {}
        for k in SEGMENT_BUCKETS:
            if counts[k] == 0:
                continue
            entry = {name: _summary(values, repeats) for name, values in buckets_out[k].items()}
            entry |= {"count": counts[k], "per_repeat": float(np.mean(sizes[k])),
                      "left_out": sorted(set(result["real"]) - set(entry["real"]))}
            result["by_num_segments"][k] = entry
    return result


def multimodality_runs(embed_motion: EmbedMotion, generate: Generate, batches: list[dict], repeats: int,
                        prompts: int, gens: int, pairs: int, seed: int) -> list[float]:
    out = []
    for rep in range(repeats):
        rng = np.random.default_rng([seed, rep, 1])
        groups = _one_caption_per_motion(batches, rng, 1)[:prompts]
        per_prompt = []
        for p, g in enumerate(groups):
            captions, lengths = g["caption"] * gens, g["lengths"].repeat(gens)
            gen_seed = generation_seed(seed, rep * 10_007 + p + 7_000_000)
            per_prompt.append(_np(embed_motion(generate(captions, lengths, gen_seed), lengths)))
        emb = np.stack(per_prompt)
        out.append(multimodality(emb, pairs, generator=rng))
    return out


def format_table(results: dict[str, dict[str, dict[str, float]]], metrics: Sequence[str] | None = None) -> str:
    """Markdown table 'metric | real | generated' of `evaluate_generation`'s result."""
    names = list(results)
    metrics = metrics or list(dict.fromkeys(k for r in results.values() for k in r))
    lines = ["| metric | " + " | ".join(names) + " |", "| --- |" + " --- |" * len(names)]
    for m in metrics:
        cells = [("" if m not in results[n] else f"{results[n][m]['mean']:.3f}"
                  if math.isnan(results[n][m]["interval"])
                  else f"{results[n][m]['mean']:.3f} ± {results[n][m]['interval']:.3f}")
                 for n in names]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
