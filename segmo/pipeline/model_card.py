"""The model card (README.md) written into every bundle, as the Hugging Face hub shows it.

It says what the model is, how to load it, what each stage is and was trained on (from
the stages' own config.json), the sampling defaults, and, when `segmo bundle --metrics`
or `SegMo.save_pretrained(metrics=...)` gives them, the evaluation figures.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import torch

from segmo.models.hub import segmo_version

CARD_FILE = "README.md"
# metrics.json paths shown in the card: (key, column title)
METRICS = (("generation/real/top1", "real Top-1"), ("generation/generated/top1", "Top-1"),
           ("generation/generated/fid", "FID"), ("generation/generated/matching", "MM-Dist"),
           ("generation/generated/diversity", "Diversity"),
           ("action_order/generated/sequence_accuracy", "action order"))


def _lookup(metrics: dict, key: str):
    value = metrics
    for part in key.split("/"):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    if isinstance(value, dict):  # {"mean": ..., "interval": ...} from `segmo evaluate`
        if "mean" not in value and "value" not in value:
            return None
        value = value.get("mean", value.get("value"))
    return math.nan if value is None else value  # metrics.json writes NaN as null


def _data_line(meta: dict) -> str:
    data = meta.get("data") or {}
    if not data:
        return "not recorded"
    corpus = data.get("corpus")
    if corpus:
        text = (f"the built-in synthetic corpus, version {corpus.get('version')}, "
                f"{corpus.get('num_motions')} motions, seed {corpus.get('seed')} (`{data['root']}`)")
    else:
        text = f"`{data['root']}`"
    extras = ", ".join(f"{k} {v}" for k, v in data.items() if k not in ("root", "corpus"))
    return text + (f"; {extras}" if extras else "")


def model_card(config, stages: dict[str, torch.nn.Module | None], metrics: dict | None = None,
               name: str = "SegMo model") -> str:
    """The README.md text of a bundle (`config`: its `SegMoConfig`)."""
    lines = ["---", "library_name: segmo", "tags:", "- text-to-motion", "- motion-generation",
             "- segmo", "---", "", f"# {name}", "",
             "A text-to-3D-human-motion model of segmo "
             f"(written by segmo {segmo_version()}): a residual VQ-VAE tokenizer, a mask "
             "transformer and a residual transformer conditioned on the caption and its "
             "ordered text segments (SegMo, WACV 2026).", "",
             "```python", "from segmo import SegMo", "",
             'model = SegMo.from_pretrained("THIS_FOLDER_OR_HUB_ID")',
             'out = model.generate(["a person walks forward, then waves"], lengths=[120])',
             'out.save("samples", formats=("npy", "gif", "bvh"))', "```", "",
             f"Skeleton `{config.skeleton}` at {config.fps:g} fps; text encoder "
             f"`{config.text_encoder}`; text segments from the `{config.text_segmenter}` "
             f"segmenter; guidance scale {config.guidance_scale:g} (residual "
             f"{config.residual_guidance_scale:g}, on "
             f"{'every' if config.residual_guided_layers is None else config.residual_guided_layers} "
             f"residual layer{'s' if config.residual_guided_layers != 1 else ''}); "
             f"{config.steps} decoding steps.", "", "## Stages", "",
             "| stage | kind | parameters | training steps | trained on |",
             "| --- | --- | ---: | ---: | --- |"]
    for stage, module in stages.items():
        if module is None:
            continue
        meta = getattr(module, "meta", {}) or {}
        params = sum(p.numel() for p in module.parameters())
        lines.append(f"| {stage} | {module.kind} | {params:,} | {meta.get('global_step', '?')} | "
                     f"{_data_line(meta)} |")
    lines += ["", "<details><summary>Stage configs</summary>", ""]
    for stage, module in stages.items():
        if module is not None:
            lines += [f"**{stage}**", "", "```json",
                      json.dumps(dataclasses.asdict(module.config), indent=1), "```", ""]
    lines += ["</details>", ""]
    if metrics:
        shown = [(title, _lookup(metrics, key)) for key, title in METRICS]
        shown = [(t, v) for t, v in shown if isinstance(v, (int, float))]
        if shown:
            lines += ["## Evaluation", "", "`segmo evaluate` on the test split:", "",
                      "| " + " | ".join(t for t, _ in shown) + " |",
                      "| " + " | ".join("---:" for _ in shown) + " |",
                      "| " + " | ".join(f"{v:.3f}" for _, v in shown) + " |", ""]
    return "\n".join(lines)


def read_metrics(path: str | Path) -> dict:
    """metrics.json of `segmo evaluate` (a file, or the folder holding it)."""
    from segmo.models.pretrained import read_json

    path = Path(path)
    return read_json(path / "metrics.json" if path.is_dir() else path)
