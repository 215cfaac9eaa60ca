"""Measure attention edits and compositions on the built-in corpus (issue 18's protocol).

    python tools/edit_benchmark.py --model runs/quality/bundles/in_sample_s0 --data data/v3 \\
        --action-classifier models/action_classifier --edits 200 --out runs/edits

swap: for test captions with 2–5 ground-truth segments, one segment's text is replaced by
another action's segment text from the test split; source and target are given as their
segments joined by ", then ". Three ways to make the target: `SegMo.edit_text` (attention
swap, `--inject-until`), regeneration from the target text with the source's random
numbers (the same as inject_until 0), and span editing (`SegMo.edit`) over the real
motion's span of that segment. Scored with the corpus' frame-wise action classifier:
- sequence: the predicted action sequence of the whole motion equals the target's, with
  consecutive repeats merged as the classifier merges them (a swap onto a neighbour's
  action, [walk, walk], asks for one walk);
- part: the action of largest mean probability over the segment's span (the real
  motion's spans, a proxy for the generated one's) is the target action, and over each
  other segment's span its own action;
- still: the share of frames outside the changed segment's span whose joints move by
  less than 2 cm (mean over joints) from the source; still_pose the same for the pose
  alone (joints relative to the root), which a changed trajectory earlier on cannot move.
A fourth row is the attention swap with `keep_outside` (tokens outside the attended span
kept).
reweight: for `--reweights` captions, segment k's attention times c ∈ {−1, 0, 0.5, 1, 2, 4};
the frames classified as its action, per c (mean), and the share of captions where that
count does not decrease with c.
compose: `--compositions` motions of 3–6 parts (test captions with their lengths, up to
40 s): per-part action-sequence accuracy (repeats merged, as for swap), and the jerk
(m/s³) and foot skating (cm/s) in the transitions against inside the parts and inside
real test motions.
Intervals are mean ± 95 % half-width; a figure of one value is its mean alone.
The last line is JSON; OUT/edits.json holds it and OUT/edits.md the tables. A bad argument,
model or data folder is one line on stderr (exit status 2).
"""

from __future__ import annotations

import math
import random
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from segmo import SegMo
from segmo.cli import run
from segmo.data.layout import read_ground_truth, read_split
from segmo.errors import ArgumentParser, SegmoError, non_negative_int, positive_int
from segmo.evaluation.report import cell
from segmo.files import json_text
from segmo.models.action_classifier import collapse
from segmo.models.pretrained import load_pretrained
from segmo.motion.features import features_to_joints
from segmo.motion.skeleton_fit import foot_contacts, foot_skating

FACTORS = (-1.0, 0.0, 0.5, 1.0, 2.0, 4.0)
STILL_CM = 2.0
PARTS = ("swap", "reweight", "compose")


def test_captions(data: Path, max_frames: int, max_segments: int = 5) -> list[dict]:
    """Test motions' captions with 2–5 ground-truth segments (at most `max_segments`, what
    the model takes; one caption per motion), their
    segments' texts, actions and spans, and the motion's length."""
    out = []
    for mid in read_split(data, "test"):
        record = read_ground_truth(data, mid)
        frames = int(record["num_frames"]) // 4 * 4
        if frames > max_frames:
            continue
        for caption in record["captions"]:
            segments = caption["segments"]
            if 2 <= len(segments) <= min(5, max_segments):
                out.append({"id": mid, "frames": frames,
                            "texts": [s["text"] for s in segments],
                            "actions": [s["action"] for s in segments],
                            "spans": [(int(s["start"]), min(int(s["end"]), frames)) for s in segments]})
                break
    return out


def joined(texts: list[str]) -> str:
    return ", then ".join(texts) + "."


def part_actions(classifier, features: np.ndarray, spans) -> list[str]:
    p = classifier.frame_probabilities(features)
    return [classifier.classes[int(p[a:b].mean(0).argmax())] for a, b in spans]


def sequence_right(classifier, features: np.ndarray, actions: list[str]) -> bool:
    """Whether the classifier's action sequence of `features` (t, d) is `actions`; the
    classifier merges consecutive repeats, so they are merged in `actions` too."""
    return classifier.predict_sequence(features) == collapse(actions)


def swap_scores(classifier, out, source_joints, item, k, target_actions) -> dict[str, float]:
    features = out.motion(0)
    sequence = sequence_right(classifier, features, target_actions)
    parts = part_actions(classifier, features, item["spans"])
    part = parts == target_actions
    joints = out.joints[0, : item["frames"]].numpy()
    moved = np.linalg.norm(joints - source_joints, axis=-1).mean(axis=1) * 100
    # The pose alone: each frame's joints relative to its root joint.
    local = np.linalg.norm((joints - joints[:, :1]) - (source_joints - source_joints[:, :1]),
                           axis=-1).mean(axis=1) * 100
    a, b = item["spans"][k]
    outside = np.ones(item["frames"], bool)
    outside[a:b] = False
    return {"sequence": float(sequence), "part": float(part),
            "target_part": float(parts[k] == target_actions[k]),
            "others_kept": float(all(p == t for i, (p, t) in enumerate(zip(parts, target_actions))
                                     if i != k)),
            "still": float((moved[outside] < STILL_CM).mean()),
            "still_pose": float((local[outside] < STILL_CM).mean())}


def mean_interval(values: list[float]) -> dict[str, float]:
    """{"mean", "interval"}: the mean and a 95 % normal-approximation half-width over the
    edits; the interval is NaN for one value, which has no spread to estimate
    (`segmo.evaluation.report.cell` then shows the mean alone, as `segmo evaluate` does)."""
    m = statistics.fmean(values)
    half = 1.96 * statistics.stdev(values) / len(values) ** 0.5 if len(values) > 1 else math.nan
    return {"mean": m, "interval": half}


def jerk(joints: np.ndarray, fps: float) -> np.ndarray:
    """(t − 3,) mean joint jerk magnitude (m/s³) per frame."""
    third = np.diff(joints, n=3, axis=0) * fps ** 3
    return np.linalg.norm(third, axis=-1).mean(axis=1)


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, write OUT, print the tables and the JSON line; the result is
    returned. SegmoError (or OSError) for a bad argument, model or data folder."""
    p = ArgumentParser(prog="edit_benchmark.py", description=__doc__.split("\n")[0])
    p.add_argument("--model", required=True)
    p.add_argument("--data", required=True, type=Path)
    p.add_argument("--action-classifier", required=True)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--edits", type=positive_int, default=200)
    p.add_argument("--reweights", type=positive_int, default=60)
    p.add_argument("--compositions", type=positive_int, default=20)
    p.add_argument("--inject-until", type=float, default=None,
                   help="default: segmo.generation.attention_edit.INJECT_UNTIL")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--threads", type=positive_int, default=None)
    p.add_argument("--skip", default="", help="comma-separated: swap,reweight,compose")
    args = p.parse_args(argv)
    skip = set(filter(None, args.skip.split(",")))
    unknown = sorted(skip - set(PARTS))
    if unknown:
        p.error(f"--skip {unknown[0]}: expected swap, reweight or compose")
    if not args.data.is_dir():
        p.error(f"--data {args.data}: no such folder")
    if args.threads:
        torch.set_num_threads(args.threads)
    model = SegMo.from_pretrained(args.model)
    classifier = load_pretrained(args.action_classifier).eval()
    items = test_captions(args.data, model.max_frames, model.max_segments)
    if not items:
        raise SegmoError(f"--data {args.data}: no test caption of 2–{min(5, model.max_segments)} "
                         f"segments in a motion of at most {model.max_frames} frames")
    rng = random.Random(args.seed)
    pool = [(a, t) for item in items for a, t in zip(item["actions"], item["texts"])]
    inject = {} if args.inject_until is None else {"inject_until": args.inject_until}
    result: dict = {"model": str(args.model), "captions": len(items)}
    lines = [f"# Attention edits on {args.data} (test split)", ""]
    started = time.perf_counter()

    if "swap" not in skip:
        scores: dict[str, list[dict]] = {"attention swap": [], "attention swap, keep outside": [],
                                         "regenerate": [], "span edit": []}
        for e in range(args.edits):
            item = items[e % len(items)]
            k = rng.randrange(len(item["texts"]))
            action, text = rng.choice([x for x in pool if x[0] != item["actions"][k]])
            targets = list(item["texts"])
            targets[k] = text
            actions = list(item["actions"])
            actions[k] = action
            g = torch.Generator().manual_seed(args.seed * 100003 + e)
            source = model.generate([joined(item["texts"])], [item["frames"]],
                                    segments=[item["texts"]], generator=g)
            src_joints = source.joints[0, : item["frames"]].numpy()
            made = {
                "attention swap": model.edit_text(source, joined(targets), "swap",
                                                  target_segments=[targets], **inject),
                "attention swap, keep outside": model.edit_text(
                    source, joined(targets), "swap", target_segments=[targets],
                    keep_outside=True, **inject),
                "regenerate": model.edit_text(source, joined(targets), "swap",
                                              target_segments=[targets], inject_until=0.0),
                "span edit": model.edit(source, item["spans"][k], joined(targets), segments=targets,
                                        generator=torch.Generator().manual_seed(e)),
            }
            for name, out in made.items():
                scores[name].append(swap_scores(classifier, out, src_joints, item, k, actions))
            if (e + 1) % 20 == 0:
                print(f"swap {e + 1}/{args.edits}, {time.perf_counter() - started:.0f} s",
                      file=sys.stderr, flush=True)
        table = {}
        lines += [f"## Swap one segment's action ({args.edits} edits)", "",
                  "| method | sequence | target in its part | others kept | parts all right | "
                  f"frames outside moving < {STILL_CM:g} cm | poses outside moving < {STILL_CM:g} cm |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for name, rows in scores.items():
            table[name] = {key: mean_interval([r[key] for r in rows]) for key in rows[0]}
            cells = " | ".join(cell(table[name][key])
                               for key in ("sequence", "target_part", "others_kept", "part", "still",
                                           "still_pose"))
            lines.append(f"| {name} | {cells} |")
        result["swap"] = {name: {key: round(v["mean"], 4) for key, v in t.items()}
                          for name, t in table.items()}
        result["swap_interval"] = {name: {key: round(v["interval"], 4) for key, v in t.items()}
                                   for name, t in table.items()}
        lines.append("")

    if "reweight" not in skip:
        durations = {c: [] for c in FACTORS}
        monotone = []
        for e in range(args.reweights):
            item = items[e % len(items)]
            k = rng.randrange(len(item["texts"]))
            source = model.generate([joined(item["texts"])], [item["frames"]],
                                    segments=[item["texts"]],
                                    generator=torch.Generator().manual_seed(args.seed * 7 + e))
            counts = []
            for c in FACTORS:
                out = model.edit_text(source, mode="reweight", weights={k + 1: c})
                labels = classifier.frame_probabilities(out.motion(0)).argmax(1)
                counts.append(int((np.array(classifier.classes)[labels] == item["actions"][k]).sum()))
                durations[c].append(counts[-1])
            monotone.append(float(all(b >= a for a, b in zip(counts, counts[1:]))))
        lines += [f"## Reweight one segment ({args.reweights} captions): frames of its action", "",
                  "| c | " + " | ".join(f"{c:g}" for c in FACTORS) + " |",
                  "| --- |" + " --- |" * len(FACTORS),
                  "| frames (mean ± 95 %) | " + " | ".join(
                      cell(mean_interval(durations[c]), 1) for c in FACTORS) + " |",
                  "", f"Non-decreasing in c for {statistics.fmean(monotone):.2f} of the captions.", ""]
        result["reweight"] = {f"{c:g}": round(statistics.fmean(v), 2) for c, v in durations.items()}
        result["reweight_monotone_share"] = round(statistics.fmean(monotone), 3)

    if "compose" not in skip:
        accuracy, jerk_in, jerk_at, skate_in, skate_at, seconds = [], [], [], [], [], []
        for e in range(args.compositions):
            count = rng.randint(3, 6)
            chosen = rng.sample(items, count)
            parts = []
            for item in chosen:
                if sum(f for _, f in parts) + item["frames"] + 20 * len(parts) > 800:
                    break
                parts.append((joined(item["texts"]), item["frames"]))
            if len(parts) < 3:
                parts = [(joined(i["texts"]), min(i["frames"], 200)) for i in chosen[:3]]
            out = model.compose(parts, generator=torch.Generator().manual_seed(e))
            features, joints = out.motion(0), out.joints[0].numpy()
            spans = out.spans[0]
            seconds.append(len(features) / out.fps)
            for (a, b), item in zip(spans, chosen):
                accuracy.append(float(sequence_right(classifier, features[a:b], item["actions"])))
            j = jerk(joints, out.fps)
            contacts = foot_contacts(joints, out.skeleton)
            inside = np.zeros(len(j), bool)
            for a, b in spans:
                inside[a:max(a, b - 3)] = True
            jerk_in.append(float(j[inside].mean()))
            jerk_at.append(float(j[~inside].mean()))
            for (_, b), (c, _) in zip(spans, spans[1:]):  # the transition frames
                skate_at.append(foot_skating(joints[b - 4:c + 4], contacts[b - 4:c + 4], out.skeleton) * 100)
            skate_in.append(statistics.fmean(foot_skating(joints[a:b], contacts[a:b], out.skeleton) * 100
                                             for a, b in spans))
        real_jerk, real_skate = [], []
        for item in items[:100]:
            raw = np.load(args.data / "new_joint_vecs" / f"{item['id']}.npy")
            joints = features_to_joints(torch.as_tensor(raw)[None], model.skeleton)[0].numpy()
            real_jerk.append(float(jerk(joints, model.fps).mean()))
            real_skate.append(foot_skating(joints, foot_contacts(joints, model.skeleton), model.skeleton) * 100)
        composed = {"parts": len(accuracy), "seconds_mean": statistics.fmean(seconds),
                    "seconds_max": max(seconds), "part_accuracy": statistics.fmean(accuracy),
                    "jerk_transitions": statistics.fmean(jerk_at), "jerk_parts": statistics.fmean(jerk_in),
                    "jerk_real": statistics.fmean(real_jerk),
                    "skating_transitions_cm_s": statistics.fmean(skate_at),
                    "skating_parts_cm_s": statistics.fmean(skate_in),
                    "skating_real_cm_s": statistics.fmean(real_skate)}
        lines += [f"## Composition ({args.compositions} motions of 3–6 parts, "
                  f"{composed['seconds_mean']:.1f} s mean, {composed['seconds_max']:.1f} s max)", "",
                  "| | part action-sequence accuracy | jerk (m/s³) | foot skating (cm/s) |",
                  "| --- | --- | --- | --- |",
                  f"| transitions | | {composed['jerk_transitions']:.1f} | {composed['skating_transitions_cm_s']:.1f} |",
                  f"| inside the parts | {composed['part_accuracy']:.3f} | {composed['jerk_parts']:.1f} | "
                  f"{composed['skating_parts_cm_s']:.1f} |",
                  f"| real test motions | | {composed['jerk_real']:.1f} | {composed['skating_real_cm_s']:.1f} |", ""]
        result["compose"] = {k: round(v, 3) for k, v in composed.items()}

    result["seconds"] = round(time.perf_counter() - started, 1)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "edits.md").write_text("\n".join(lines) + "\n")
    (args.out / "edits.json").write_text(json_text(result, indent=1) + "\n")
    print("\n".join(lines))
    print(json_text(result))
    return result


if __name__ == "__main__":
    run("edit_benchmark.py", main, sys.argv[1:])
