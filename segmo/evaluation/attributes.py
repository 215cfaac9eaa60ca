"""Fine-grained attribute accuracy: do the motions do what the caption's modifiers say?

For each test motion's first caption, every text segment that names a modifier
(`segmo.data.attributes.named_attributes`: "left"/"right", "twice", "slowly", ...) is
checked on its frames: the attribute classifier (`AttributeClassifier`, trained on the
corpus' action parameters) reads the attribute from the segment's ground-truth span and
compares it with the value the corpus recorded for that action. The real motions give
the classifier's own ceiling; the reconstruction row the tokenizer's. Generated motions
get the caption's true length, and are read on the same spans: a generator that puts a
segment elsewhere in time is scored on the frames where it should be.

Result: per row ("real", "reconstruction", "generated"), the accuracy of each attribute
and over all checks, and the number of checks.
"""

from __future__ import annotations

from typing import Any

import torch

from segmo.data.attributes import ATTRIBUTES, attribute_labels, named_attributes
from segmo.data.collate import IGNORE
from segmo.data.layout import read_ground_truth
from segmo.evaluation.metrics import generation_seed
from segmo.evaluation.sections import EvaluateConfig, first_rows, ground_truth, raw_features

MIN_FRAMES = 4  # a span shorter than one token is not read


def attribute_queries(cfg: EvaluateConfig, batches: list[dict]) -> list[tuple[dict, int, list]]:
    """(batch, row, [(start, end, {attribute: true value})]) of the first captions that
    name at least one attribute their action has."""
    queries = []
    for b, r in first_rows(batches):
        mid, t = b["id"][r], int(b["lengths"][r])
        segments = ground_truth(cfg, mid, b["caption_index"][r], t)
        if not segments:
            continue
        actions = {(a["action"], int(a["start"])): a for a in read_ground_truth(cfg.data, mid)["actions"]}
        checks = []
        for segment in segments:
            action = actions.get((segment["action"], int(segment["start"])))
            named = named_attributes(segment["text"])
            if action is None or not named or segment["end"] - segment["start"] < MIN_FRAMES:
                continue
            labels = attribute_labels(action["action"], action.get("params") or {})
            truth = {name: ATTRIBUTES[name][labels[k]] for k, name in enumerate(ATTRIBUTES)
                     if name in named and labels[k] != IGNORE}
            if truth:
                checks.append((int(segment["start"]), int(segment["end"]), truth))
        if checks:
            queries.append((b, r, checks))
    return queries


def _score(clf: Any, queries: list, motions: list[Any]) -> dict[str, float]:
    correct = {name: 0 for name in ATTRIBUTES}
    total = {name: 0 for name in ATTRIBUTES}
    for (_, _, checks), features in zip(queries, motions, strict=True):
        for start, end, truth in checks:
            end = min(end, len(features))
            if end - start < MIN_FRAMES:
                continue
            found = clf.span_attributes(features, start, end)
            for name, value in truth.items():
                total[name] += 1
                correct[name] += found[name] == value
    out = {name: correct[name] / total[name] for name in ATTRIBUTES if total[name]}
    checks = sum(total.values())
    out["overall"] = sum(correct.values()) / checks if checks else float("nan")
    out["checks"] = float(checks)
    return out


def attribute_section(cfg: EvaluateConfig, clf: Any, ds: Any, batches: list[dict], generate: Any,
                      reconstruct: Any = None) -> dict[str, Any]:
    queries = attribute_queries(cfg, batches)
    result = {"real": _score(clf, queries, [raw_features(ds, b, r) for b, r, _ in queries])}
    if reconstruct is not None:
        result["reconstruction"] = _score(clf, queries, [reconstruct.raw(b["id"][r]) for b, r, _ in queries])
    if generate is not None and queries:
        generate.expect(len(queries), "attributes")
        motions = []
        for s in range(0, len(queries), cfg.batch_size):
            chunk = queries[s:s + cfg.batch_size]
            lengths = torch.stack([b["lengths"][r] for b, r, _ in chunk])
            features, got = generate.raw([b["caption"][r] for b, r, _ in chunk], lengths,
                                         generation_seed(cfg.seed, 11_000_000 + s))
            motions += [features[k, : int(got[k])].numpy() for k in range(len(chunk))]
        result["generated"] = _score(clf, queries, motions)
    return result
