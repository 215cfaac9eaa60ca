"""Reconstruction quality of an exported tokenizer, layer by layer.

    python tools/eval_tokenizer.py --model models/rvq --data data/synth --split test

Each clip of the split (whole clips, cropped to a multiple of 4, z-scored with the model's
own statistics) is encoded once; decoding with the first k quantizer layers, k = 1..q,
gives MPJPE(k) in mm on joints recovered from the de-normalised features, with the root
joints of each frame aligned first as in MoMask's evaluation (pose error), and the global
MPJPE(k) that keeps the root trajectory integrated from the velocity features (so its
drift counts too). Clips are
batched only with clips of the same length, so no padding enters the convolutions. Code
usage (fraction of codes used) and perplexity are computed per layer over all tokens of
the split. The last printed line is a JSON object:
{"mpjpe_mm": [q floats], "mpjpe_global_mm": [q], "code_usage": [q], "perplexity": [q], ...}.

On the built-in corpus, `--action-classifier DIR` (configs/action_classifier) also reads
the actions of the full reconstructions: their sequence accuracy against the true action
sequence, overall and by number of actions (1, 2, 3+; real motions score 1.0), each
action's frame accuracy on its true span, and the most frequent confusions, under
"actions" in the JSON object. A tokenizer that blurs two actions into one (a leap forward
decoded as a jump in place, a punch as a clap) caps every generator trained on it there.

    python tools/eval_tokenizer.py --model models/rvq --data data/synth \
        --action-classifier models/action_classifier
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict

import numpy as np
import torch

from segmo.cli import run
from segmo.data import MotionWindowDataset
from segmo.data.layout import has_ground_truth, read_actions
from segmo.errors import ArgumentParser, SegmoError, positive_int
from segmo.evaluation.action_order import frame_confusions
from segmo.models.action_classifier import ActionClassifier, collapse
from segmo.models.pretrained import load_pretrained
from segmo.models.tokenizer import RVQVAE
from segmo.motion.features import features_to_joints, joint_errors
from segmo.motion.skeleton import get_skeleton
from segmo.pipeline.inputs import resolve_device


@torch.no_grad()
def evaluate(model: RVQVAE, dataset: MotionWindowDataset, batch_size: int = 32,
             device: str = "cpu") -> dict:
    """MPJPE (mm) by number of layers and per-layer code statistics over `dataset`."""
    skeleton = dataset.skeleton
    model = model.to(device).eval()
    q, k = model.num_quantizers, model.codebook_size
    by_length: dict[int, list[torch.Tensor]] = defaultdict(list)
    for i in range(len(dataset)):
        motion = dataset[i]["motion"]
        by_length[motion.shape[0]].append(motion)
    aligned_sum = torch.zeros(q, dtype=torch.float64)
    global_sum = torch.zeros(q, dtype=torch.float64)
    frames = 0
    counts = torch.zeros(q, k, dtype=torch.float64)
    for length in sorted(by_length):
        clips = by_length[length]
        for start in range(0, len(clips), batch_size):
            motion = torch.stack(clips[start:start + batch_size]).to(device)  # (b, t, d)
            indices = model.encode(motion)  # (b, n, q)
            for layer in range(q):
                counts[layer] += torch.bincount(indices[..., layer].flatten().cpu(), minlength=k)
            real = features_to_joints(model.denormalize(motion).double(), skeleton)
            for depth in range(1, q + 1):
                fake = features_to_joints(model.denormalize(model.decode(indices[..., :depth])).double(), skeleton)
                aligned, drift = joint_errors(real, fake)  # (b, t) each
                aligned_sum[depth - 1] += aligned.sum().cpu()
                global_sum[depth - 1] += drift.sum().cpu()
            frames += motion.shape[0] * motion.shape[1]
    if frames == 0:
        raise ValueError(f"{dataset.root}: no clips to evaluate (summary: {dataset.summary})")
    probs = counts / counts.sum(1, keepdim=True)
    perplexity = torch.exp(-(probs * torch.log(probs.clamp(min=1e-12))).sum(1))
    to_mm = skeleton.unit * 1000.0 / frames
    return {
        "mpjpe_mm": [round(float(v), 3) for v in aligned_sum * to_mm],
        "mpjpe_global_mm": [round(float(v), 3) for v in global_sum * to_mm],
        "code_usage": [round(float(v), 4) for v in (counts > 0).double().mean(1)],
        "perplexity": [round(float(v), 2) for v in perplexity],
        "clips": len(dataset),
        "frames": frames,
    }


@torch.no_grad()
def action_fidelity(model: RVQVAE, dataset: MotionWindowDataset, classifier: ActionClassifier) -> dict:
    """How the action classifier reads each clip's full reconstruction (see the module
    docstring); needs the corpus' ground-truth actions."""
    model = model.cpu().eval()
    reconstructions, hits = {}, defaultdict(list)
    for i in range(len(dataset)):
        item = dataset[i]
        decoded = model.decode(model.encode(item["motion"][None].float()))
        features = model.denormalize(decoded)[0].float().numpy()
        reconstructions[item["id"]] = features
        true = collapse(read_actions(dataset.root, item["id"])[0])
        hit = classifier.predict_sequence(features) == true
        hits["all"].append(hit)
        hits[str(len(true)) if len(true) < 3 else "3+"].append(hit)
    reading = frame_confusions(classifier, dataset.root, reconstructions)
    return {"sequence_accuracy": {k: float(np.mean(v)) for k, v in sorted(hits.items())},
            "clips": {k: len(v) for k, v in sorted(hits.items())}, **reading}


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(prog="eval_tokenizer.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="exported tokenizer directory")
    parser.add_argument("--data", required=True, help="dataset folder (HumanML3D layout)")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--batch-size", type=positive_int, default=32)
    parser.add_argument("--max-motions", type=positive_int, default=None, help="first N ids of the split")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--action-classifier", default=None,
                        help="built-in corpus: also read the reconstructions' actions with this classifier")
    args = parser.parse_args(argv)
    try:
        resolve_device(args.device)
    except SegmoError as error:
        parser.error(f"--device {args.device}: {str(error).removeprefix('SegMo: ')}")
    if args.action_classifier is not None and not has_ground_truth(args.data):
        parser.error(f"--action-classifier: {args.data} has no ground-truth actions (segments/); "
                     "only the built-in corpus (segmo synth) has them")

    model = RVQVAE.from_pretrained(args.model)
    if "skeleton" not in model.meta:
        parser.error(f"{args.model}/config.json: meta names no skeleton")
    skeleton = get_skeleton(model.meta["skeleton"])
    dataset = MotionWindowDataset(
        args.data, args.split, skeleton, window=None, mean=model.mean.numpy(),
        std=model.std.numpy(), random_crop=False, max_motions=args.max_motions,
    )
    result = evaluate(model, dataset, args.batch_size, args.device)
    result.update(model=args.model, data=args.data, split=args.split)
    if args.action_classifier is not None:
        classifier = load_pretrained(args.action_classifier)
        if not isinstance(classifier, ActionClassifier):
            parser.error(f"--action-classifier {args.action_classifier}: not an action classifier")
        result["actions"] = action_fidelity(model, dataset, classifier.eval())
    print(f"{'layers':>6}  {'MPJPE (mm)':>10}  {'global (mm)':>11}")
    for depth, (value, drift) in enumerate(zip(result["mpjpe_mm"], result["mpjpe_global_mm"]), 1):
        print(f"{depth:>6}  {value:>10.2f}  {drift:>11.2f}")
    print(f"{'layer':>6}  {'usage':>6}  {'perplexity':>10}")
    for layer, (usage, ppl) in enumerate(zip(result["code_usage"], result["perplexity"])):
        print(f"{layer:>6}  {usage:>6.3f}  {ppl:>10.1f}")
    if "actions" in result:
        actions = result["actions"]
        print("action sequence of the reconstructions: " + ", ".join(
            f"{k} {v:.3f} ({actions['clips'][k]})" for k, v in actions["sequence_accuracy"].items()))
        for c in actions["confusions"]:
            print(f"  {c['true']} read as {c['read_as']}: {c['share']:.1%} of its frames")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("eval_tokenizer.py", main, sys.argv[1:])
