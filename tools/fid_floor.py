"""What a generated FID can be read against on a split of this size: the split's real motions
against other motions in the evaluator's space of `segmo evaluate`, with nothing generated.

    python tools/fid_floor.py --data data/v3 --evaluator models/evaluator [--split test] \\
        [--other train] [--repeats 10] [--sizes 96,288,800] [--resample [--mistakes 0.1,0.3]] \\
        [--kinds left-out,stretched,substituted,extra,misnamed,mixed] \\
        [--action-classifier models/action_classifier] [--out floor.json]

`segmo evaluate`'s real row compares the split with itself (two draws of its motions) and
its reconstruction row every real motion with its own round trip: both pair each motion
with itself. A generator makes new motions of the same captions. Rows (mean ± 95 %
interval over --repeats draws; N motions a side; Top-1, MM-Dist, FID and Diversity where
the motions pair with the split's captions, one drawn per motion, FID alone where not):

- `itself`: two draws of N of the split's motions (like `segmo evaluate`'s real row);
- `other`: N of the split's motions against N motions of --other: real motions, but of
  other captions;
- `disjoint N`: two disjoint draws of N motions of --other, for each N of --sizes: FID's
  finite-sample bias, which shrinks about as 1/N;
- with --resample (the built-in corpus only: it needs `segments/<id>.json` and the
  corpus' generator): every motion of the split made again by the corpus' generator from
  its ground-truth actions (`segmo.synth.sequence.resample_motion`), a new realization
  for every repeat, against the split's motions, paired as a generator's are.
  `same parameters`: the same actions with their durations, tempo, sides and counts, new
  transitions, rests and idiosyncrasy (the closest a remake comes, as a reconstruction);
  `the caption's parameters`: the same actions agreeing on what a caption can name (side,
  count and speed class, a turn's angle, a deep bow), every parameter drawn anew until it
  does (what a generator that gets everything its caption says right, and draws the rest
  as the corpus does, would score); `new parameters`: the same actions in the same order and
  nothing else;
- with --mistakes R1,R2 also the caption's parameters with a generator's errors made in
  each action at each rate (`with_mistake`): a short action left out, replaced by another
  (substituted), an extra short action put in, or an action's parameters drawn anew
  (misnamed), or the first three mixed (--kinds picks among them): what each kind of
  error costs. A remake that leaves an action out is shorter by it, where a generator is
  given a length and fills it: the row "left out, stretched" slows each such remake evenly
  (`segmo.synth.actions.resample_frames`) to the length of the same motion's remake
  without the mistake (the caption's parameters row's), the other bound.

With --action-classifier (the built-in corpus' classifier behind `segmo evaluate`'s action
order) every remade row and `itself` also report action order: the share of the split's
motions of 2+ and of 3+ ground-truth actions whose remake (for `itself`: the real motion)
the classifier reads as exactly their actions in order, over all the split's motions and
each repeat, as `tools/order_by_template.py` counts it for a generator.

N is the split's motions rounded down to whole batches of --batch-size, as `segmo
evaluate` draws them. Each motion is embedded once (its whole clip, as `segmo evaluate`
reads real motions); the draws pick among the embeddings.
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn.utils.rnn import pad_sequence

from segmo.data.layout import ground_truth_file, read_ground_truth
from segmo.errors import (
    ArgumentParser,
    SegmoError,
    ascii_whole_number,
    non_negative_int,
    positive_int,
)
from segmo.evaluation.action_order import sequence_accuracy
from segmo.evaluation.metrics import fid, mean_and_interval, row_metrics, t2m_embedders
from segmo.evaluation.sections import EvaluateConfig, all_rows, first_rows, load_batches
from segmo.files import json_text, write_atomic
from segmo.models.action_classifier import ActionClassifier, collapse
from segmo.models.evaluator import T2MEvaluator
from segmo.motion.features import joints_to_features
from segmo.synth.actions import ACTIONS, resample_frames, sample_params
from segmo.synth.sequence import (
    RESAMPLE_KEEPS,
    SHORT_V2,
    choose_short,
    resample_motion,
    seated_before,
)

RESAMPLED = {"same parameters": "all", "the caption's parameters": "named", "new parameters": "none"}  # row → keep
# --kinds name → (`with_mistake`'s kind, stretched to the remake's length), the row's words
MISTAKES = {"left-out": (("left out", False), "short actions left out"),
            "stretched": (("left out", True), "short actions left out, stretched"),
            "substituted": (("substituted", False), "short actions substituted"),
            "extra": (("extra", False), "actions with a short one before"),
            "misnamed": (("misnamed", False), "actions misnamed"),
            "mixed": (("mixed", False), "actions wrong, a third each left out, substituted, extra")}
ORDERS = {"order, 2+ actions": 2, "order, 3+ actions": 3}  # row metric → fewest ground-truth actions


class Split:
    """The motions of one split, one per id in file order, and the evaluator's embeddings of
    them and of their captions; with `classifier`, its reading of their action sequences."""

    def __init__(self, evaluator: Any, data: Path, split: str, classifier: ActionClassifier | None = None) -> None:
        self.skeleton = "kit" if evaluator.config.feature_dim == 251 else "t2m"
        ds, batches = load_batches(EvaluateConfig(data=str(data), evaluator="", out="", split=split),
                                   self.skeleton)
        self.data, self.mean, self.std, self.classifier = data, ds.mean, ds.std, classifier
        self.embed_text, self.embed_motion = t2m_embedders(evaluator, data, ds.mean, ds.std)
        self.batches = batches
        rows = first_rows(batches)
        self.ids = [b["id"][r] for b, r in rows]
        self.frames = [int(b["lengths"][r]) for b, r in rows]
        motions = [b["motion"][r, :frames] for (b, r), frames in zip(rows, self.frames, strict=True)]
        self.embeddings = self.embed(motions)
        self.sequences = self.read(motions) if classifier else None
        self.actions: dict[str, list[dict]] = {}  # ground-truth actions, read once per motion

    @cached_property
    def texts(self) -> list[np.ndarray]:
        """(captions, embed_dim) of every caption of each motion: a paired row draws one per
        motion, as `segmo evaluate` does (the test split's first captions are mostly
        held-out templates). Only the split the rows pair with needs them."""
        captions = all_rows(self.batches)
        with torch.no_grad():
            text = self.embed_text([b["caption"][r] for b, r in captions], captions)
        where = {mid: i for i, mid in enumerate(self.ids)}
        grouped: list[list[np.ndarray]] = [[] for _ in self.ids]
        for (b, r), vector in zip(captions, text, strict=True):
            grouped[where[b["id"][r]]].append(vector)
        return [np.stack(v) for v in grouped]

    def embed(self, motions: list[torch.Tensor]) -> np.ndarray:
        """(len(motions), embed_dim) of z-scored (t, d) motions, 32 at a time."""
        out = []
        with torch.no_grad():
            for start in range(0, len(motions), 32):
                chunk = motions[start:start + 32]
                lengths = torch.tensor([len(m) for m in chunk])
                out.append(self.embed_motion(pad_sequence(chunk, batch_first=True), lengths))
        return np.concatenate(out)

    def read(self, motions: list[torch.Tensor]) -> list[list[str]]:
        """The classifier's action sequence of each z-scored (t, d) motion."""
        return [self.classifier.predict_sequence((m.numpy() * self.std + self.mean).astype(np.float32))
                for m in motions]

    def ground_truth(self, k: int) -> list[dict]:
        """The ground-truth actions of motion k, read once."""
        mid = self.ids[k]
        if mid not in self.actions:
            try:
                self.actions[mid] = read_ground_truth(self.data, mid)["actions"]
            except (ValueError, KeyError, TypeError) as error:
                raise SegmoError(f"{ground_truth_file(self.data, mid)}: no ground-truth actions ({error!r})") from None
        return self.actions[mid]

    def orders(self, sequences: list[list[str]]) -> dict[str, float]:
        """`ORDERS` of the classifier's `sequences`, one per motion of the split, against the
        motions' ground-truth actions (each where the split has such motions)."""
        out = {}
        for name, fewest in ORDERS.items():
            rows = [k for k in range(len(self.ids)) if len(self.ground_truth(k)) >= fewest]
            if rows:
                out[name] = sequence_accuracy([sequences[k] for k in rows],
                                              [collapse([a["action"] for a in self.ground_truth(k)]) for k in rows])
        return out

    def resampled(self, version: int, keep: str, seed: int, repeat: int,
                  mistake: tuple[str, float] | None = None, stretched: bool = False
                  ) -> tuple[np.ndarray, dict[str, float]]:
        """Embeddings of every motion made again from its ground-truth actions (module
        docstring), with `mistake` (kind, rate) made first (`with_mistake`); `stretched`: a
        remake that lost an action slowed to the length of the same remake without the
        mistake (the same draws); and with a classifier their `orders` (else {})."""
        motions = []
        for k, mid in enumerate(self.ids):
            key = [seed, repeat, k, RESAMPLE_KEEPS.index(keep)]
            rng, truth = np.random.default_rng(key), self.ground_truth(k)
            try:
                actions = with_mistake(truth, *mistake, rng, version) if mistake else truth
                joints = resample_motion(rng, actions, version, keep).joints
                if stretched and len(actions) < len(truth):  # to the length without the mistake
                    unmistaken = resample_motion(np.random.default_rng(key), truth, version, keep)
                    joints = resample_frames(joints, len(unmistaken.joints))
            except (ValueError, KeyError, TypeError) as error:  # a ground truth the corpus cannot make
                raise SegmoError(f"{ground_truth_file(self.data, mid)}: cannot be made again ({error!r})") from None
            features = joints_to_features(joints.astype(np.float32), self.skeleton)
            motions.append(torch.from_numpy(((features - self.mean) / self.std).astype(np.float32)))
        return self.embed(motions), (self.orders(self.read(motions)) if self.classifier else {})


def with_mistake(actions: list[dict], kind: str, rate: float, rng: np.random.Generator,
                 version: int) -> list[dict]:
    """A generator's kind of error, made in each action at `rate`: `left out` a short action
    that leaves the body as it is (never the last one left); `substituted` such an action
    replaced by another short one the body can do there, unlike it and its neighbours;
    `extra` a short action put in before an action (not the first), unlike its neighbours;
    `misnamed` an action's parameters drawn anew (side, count, speed class and the rest:
    they may come out the same); `mixed` left out, substituted and extra, each at a third
    of `rate`. `MISTAKES` names the rows."""
    if kind == "mixed":
        for part in ("left out", "substituted", "extra"):
            actions = with_mistake(actions, part, rate / 3, rng, version)
        return actions
    names = [a["action"] for a in actions]
    seated = seated_before(names)

    def short(k: int, neighbours: list[str]) -> dict | None:
        try:
            name = choose_short(rng, seated[k], neighbours)
        except ValueError:  # no short action the body can do there is left
            return None
        return {"action": name, "params": sample_params(name, rng, version)}

    out = []
    for k, action in enumerate(actions):
        neutral = action["action"] in SHORT_V2 and ACTIONS[action["action"]].ends is None
        if kind == "left out" and neutral and not (not out and k == len(actions) - 1) and rng.random() < rate:
            continue
        if kind == "substituted" and neutral and rng.random() < rate:
            action = short(k, names[max(k - 1, 0):k + 2]) or action
        if kind == "extra" and k > 0 and rng.random() < rate:
            out += [a for a in [short(k, names[k - 1:k + 1])] if a]
        if kind == "misnamed" and rng.random() < rate:
            action = action | {"params": sample_params(action["action"], rng, version)}
        out.append(action)
    return out


def corpus_version(data: Path) -> int:
    """The built-in corpus version of `data` (its corpus.json), for --resample."""
    try:
        return int(json.loads((data / "corpus.json").read_text())["version"])
    except (OSError, ValueError, KeyError, TypeError):
        raise SegmoError(f"--resample: {data / 'corpus.json'} is missing or has no version; only the "
                         "built-in corpus (segmo synth) can be made again") from None


PAIRED = ("top1", "matching", "fid", "diversity")  # the metrics of a row whose motions pair with captions


def summary(per_repeat: list[dict[str, float]], motions: int) -> dict[str, Any]:
    """{"motions": motions, metric: {"mean", "interval"}} over the repeats."""
    out: dict[str, Any] = {"motions": motions}
    for metric in per_repeat[0]:
        mean, interval = mean_and_interval([r[metric] for r in per_repeat])
        out[metric] = {"mean": mean, "interval": interval}
    return out


def floor(split_emb: np.ndarray, texts: list[np.ndarray], other_emb: np.ndarray, n: int, sizes: list[int],
          repeats: int, seed: int, resampled: dict[str, list[np.ndarray]] | None = None,
          batch_size: int = 32, orders: dict[str, list[dict[str, float]]] | None = None
          ) -> dict[str, dict[str, Any]]:
    """The table's rows: {name: {"motions": N, metric: {"mean", "interval"}}}; rows whose
    motions pair with the split's captions (`texts[i]`: (captions, embed_dim) of motion i,
    one drawn per motion and draw) have `PAIRED`, the others FID only. `resampled`: row
    name → one (len(split_emb), embed_dim) array per repeat, row i made from motion i.
    `orders`: row name ("itself" or a `resampled` one) → one {`ORDERS` metric: value} per
    repeat, added to the row."""
    rng = np.random.default_rng(seed)
    orders = orders or {}

    def pick(k: int, among: int) -> np.ndarray:
        return rng.choice(among, k, replace=False)

    def paired(emb: np.ndarray, rows: np.ndarray, reference: np.ndarray) -> dict[str, float]:
        text = np.stack([texts[i][rng.integers(len(texts[i]))] for i in rows])
        metrics = row_metrics(text, emb[rows], reference, rng, batch_size=batch_size)
        return {k: metrics[k] for k in PAIRED if k in metrics}

    def with_orders(name: str, draws: list[dict[str, float]]) -> list[dict[str, float]]:
        return [d | o for d, o in zip(draws, orders[name], strict=True)] if name in orders else draws

    out = {"itself": summary(with_orders("itself", [
               paired(split_emb, pick(n, len(split_emb)), split_emb[pick(n, len(split_emb))])
               for _ in range(repeats)]), n),
           "other": summary([{"fid": fid(split_emb[pick(n, len(split_emb))], other_emb[pick(n, len(other_emb))])}
                             for _ in range(repeats)], n)}
    for k in sizes:
        draws = []
        for _ in range(repeats):
            order = rng.permutation(len(other_emb))
            draws.append({"fid": fid(other_emb[order[:k]], other_emb[order[k:2 * k]])})
        out[f"disjoint {k}"] = summary(draws, k)
    for name, per_repeat in (resampled or {}).items():
        draws = []
        for emb in per_repeat:
            rows = pick(n, len(split_emb))  # the same motions on both sides
            draws.append(paired(emb, rows, split_emb[rows]))
        out[f"resampled, {name}"] = summary(with_orders(name, draws), n)
    return out


def table(rows: dict[str, dict[str, Any]], split: str, other: str) -> str:
    what = {"itself": f"{split} against itself (two draws, like `segmo evaluate`'s real row)",
            "other": f"{split} against as many {other} motions"}
    what |= {name: f"{split} made again, {name.removeprefix('resampled, ')}" for name in rows
             if name.startswith("resampled, ")}
    metrics = [*PAIRED, *(o for o in ORDERS if any(o in r for r in rows.values()))]
    heads = {"top1": "Top-1", "matching": "MM-Dist", "fid": "FID", "diversity": "Diversity"}
    lines = ["| real motions compared | motions a side | " + " | ".join(heads.get(m, m) for m in metrics) + " |",
             "| --- | --- |" + " --- |" * len(metrics)]
    for name, r in rows.items():
        cells = [f"{r[m]['mean']:.3f} ± {r[m]['interval']:.3f}" if m in r else "–" for m in metrics]
        lines.append(f"| {what.get(name, f'{other} against {other}, disjoint')} | {r['motions']} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def sizes_argument(text: str) -> list[int]:
    """`--sizes`: whole numbers of at least 2, comma-separated."""
    sizes = [ascii_whole_number(s.strip()) for s in text.split(",") if s.strip()]
    if not all(size is not None and size >= 2 for size in sizes):
        raise argparse.ArgumentTypeError(f"{text!r:.80}: expected whole numbers of at least 2, separated by "
                                         "commas")
    return sizes


def rates_argument(text: str) -> list[float]:
    """`--mistakes`: rates above 0 and at most 1, comma-separated."""
    try:
        rates = [float(p) for p in text.split(",") if p.strip()]
    except ValueError:
        rates = [-1.0]
    if not all(0 < r <= 1 for r in rates):
        raise argparse.ArgumentTypeError(f"{text!r}: expected rates above 0 and at most 1, separated by commas")
    return rates


def kinds_argument(text: str) -> list[str]:
    """`--kinds`: names of `MISTAKES`, comma-separated."""
    kinds = [k.strip() for k in text.split(",") if k.strip()]
    if not kinds or any(k not in MISTAKES for k in kinds):
        raise argparse.ArgumentTypeError(f"{text!r}: expected some of {', '.join(MISTAKES)}, separated by commas")
    return kinds


def load(cls: type, path: Path, argument: str) -> Any:
    """The `cls` model at `path` (its `from_pretrained` refuses another kind), in eval mode;
    a failure names `argument`."""
    try:
        return cls.from_pretrained(path).eval()
    except (SegmoError, OSError) as error:
        raise SegmoError(f"{argument} {error}") from None


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="fid_floor.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, type=Path, help="a dataset folder (HumanML3D layout)")
    parser.add_argument("--evaluator", required=True, type=Path, help="a T2M evaluator (segmo export)")
    parser.add_argument("--split", default="test", help="the split a generator is evaluated on")
    parser.add_argument("--other", default="train", help="the split the other real motions come from")
    parser.add_argument("--repeats", type=positive_int, default=10)
    parser.add_argument("--batch-size", type=positive_int, default=32, help="as segmo evaluate's")
    parser.add_argument("--sizes", type=sizes_argument, default=[],
                        help="comma-separated N for the disjoint rows, e.g. 96,288,800")
    parser.add_argument("--resample", action="store_true",
                        help="also the split made again by the built-in corpus' generator")
    parser.add_argument("--mistakes", type=rates_argument, default=[],
                        help="with --resample, also rows of the caption's parameters with each kind "
                             "of a generator's error made at these rates, e.g. 0.1,0.3")
    parser.add_argument("--kinds", type=kinds_argument,
                        help=f"with --mistakes, which kinds of error (comma-separated; default all: "
                             f"{','.join(MISTAKES)})")
    parser.add_argument("--action-classifier", type=Path,
                        help="also action order, read by this classifier (segmo export; the built-in corpus only)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--out", type=Path, help="also write the rows as JSON here")
    try:  # the project's parser raises SegmoError: every failure is one line
        args = parser.parse_args(argv)
        if not args.data.is_dir():
            parser.error(f"--data {args.data}: no such folder")
        if args.out and (args.out.is_dir() or not args.out.parent.is_dir()):
            parser.error(f"--out {args.out}: " + ("is a folder; give a file name" if args.out.is_dir()
                                                   else f"its folder {args.out.parent} does not exist"))
        inputs = [("--data", args.data), ("--evaluator", args.evaluator),
                  ("--action-classifier", args.action_classifier)]
        for flag, folder in inputs:
            if args.out and folder and args.out.resolve().is_relative_to(folder.resolve()):
                parser.error(f"--out {args.out}: inside {flag} {folder}; write the rows elsewhere")
        if args.mistakes and not args.resample:
            parser.error("--mistakes: needs --resample (they are made in the remade motions)")
        if args.kinds and not args.mistakes:
            parser.error("--kinds: needs --mistakes (the rates to make them at)")
        if args.split == args.other:
            parser.error(f"--other {args.other}: the same split as --split; the other motions must be other ones")
        version = corpus_version(args.data) if args.resample else None
        evaluator = load(T2MEvaluator, args.evaluator, "--evaluator")
        classifier = (load(ActionClassifier, args.action_classifier, "--action-classifier")
                      if args.action_classifier else None)
        split = Split(evaluator, args.data, args.split, classifier)
        other = Split(evaluator, args.data, args.other)
        n = len(split.ids) // args.batch_size * args.batch_size
        if n < 2:
            raise SegmoError(f"--split {args.split}: {len(split.ids)} motions, fewer than two in whole "
                             f"batches of --batch-size {args.batch_size}")
        need = max(n, 2 * max(args.sizes, default=0))
        if need > len(other.ids):
            raise SegmoError(f"--other {args.other}: {len(other.ids)} motions, fewer than the {need} "
                             f"these rows draw (--split {args.split}'s {n}, twice the largest --sizes)")
        made = {}  # row name → one (embeddings, orders) per repeat
        for name, keep in RESAMPLED.items() if args.resample else ():
            made[name] = [split.resampled(version, keep, args.seed, r) for r in range(args.repeats)]
        for (kind, stretched), what in (MISTAKES[k] for k in args.kinds or MISTAKES) if args.mistakes else ():
            for rate in args.mistakes:
                made[f"the caption's parameters, {100 * rate:g}% of the {what}"] = [
                    split.resampled(version, "named", args.seed, r, (kind, rate), stretched)
                    for r in range(args.repeats)]
        orders = {name: [o for _, o in per_repeat] for name, per_repeat in made.items() if classifier}
        if classifier:
            orders["itself"] = [split.orders(split.sequences)] * args.repeats
    except (SegmoError, OSError) as error:
        print(f"fid_floor: {error}", file=sys.stderr)
        return 2
    rows = floor(split.embeddings, split.texts, other.embeddings, n, args.sizes, args.repeats, args.seed,
                 {name: [e for e, _ in per_repeat] for name, per_repeat in made.items()}, args.batch_size, orders)
    print(table(rows, args.split, args.other))
    if args.out:
        write_atomic(args.out, json_text({"split": args.split, "other": args.other, "rows": rows},
                                         indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
