"""Markdown tables and plots of `segmo evaluate` results (metrics.json → report.md, *.png).

The generation table follows the paper's Tables 1–3: one row per model (plus "Real"),
columns Top-1/2/3, FID, MM-Dist, Diversity, MModality, cells "mean±interval" (95 %
interval over the evaluation repeats). The other sections (retrieval, grounding, ISC,
action order) are single measurements. Everything here reads the plain `metrics.json`
dict written by `segmo.evaluation.cli`, so reports can be rebuilt and compared later
without the models. metrics.json is strict JSON: a NaN figure (the interval of a single
measurement) is written as null, and `cell` reads null as NaN; an older file's bare NaN
reads as it always did.

Example::

    metrics = json.loads(Path("eval/segmo/metrics.json").read_text())
    Path("report.md").write_text(render_report(metrics))
    compare_table([("SegMo", metrics), ("No Align", json.loads(...))])
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from segmo.evaluation.grounding import IOU_THRESHOLDS

# (metrics.json key, column title), in the paper's order.
GENERATION_COLUMNS: tuple[tuple[str, str], ...] = (
    ("top1", "Top-1"), ("top2", "Top-2"), ("top3", "Top-3"), ("fid", "FID"),
    ("matching", "MM-Dist"), ("diversity", "Diversity"), ("multimodality", "MModality"),
)
RETRIEVAL_KS: tuple[int, ...] = (1, 2, 3, 5, 10)
# The sentences the two grounding notes share: how a span is scored, and the baselines.
_GROUNDING_SCORE = "R@1 = the chosen span's temporal IoU with the true span ≥ threshold. "
_GROUNDING_BASELINES = ("Baselines that know only the number of segments: the uniform split, change "
                        "points (cpd) and k-means on the motion features pooled per token.")

# What each section measured, shown above its table.
NOTES: dict[str, str] = {
    "retrieval": (
        "evaluator: Euclidean distances of T2M embeddings, all captions vs all motions for "
        "'full'. segmo: mean cosine of a caption's text segments with as many uniform spans of "
        "the motion in the learned space (one forward pass per pair), first caption of each "
        "motion for 'full'."),
    "grounding": (
        "Each caption with ≥ 2 ground-truth segments, grounded in its real motion with those "
        "segments' texts, one pass per caption. ordered: the motion cut into one span per "
        "segment, in caption order (≥ 2 tokens each), maximising the summed similarity; "
        "spans: each segment's best span of any length ≥ 2 tokens; window: the paper's "
        "sliding windows {window} (tokens; auto = 0.5–2× the mean segment length), stride 1. "
        + _GROUNDING_SCORE + "attention: the ordered and best-span searches over where the mask "
        "transformer's motion tokens look (SegMo.ground(method=\"attention\")). "
        + _GROUNDING_BASELINES),
    "grounding_attention": (
        "Attention grounding only, as {reason} and so no learned space: each caption "
        "with ≥ 2 ground-truth segments, grounded in its real motion with those segments' "
        "texts by where the mask transformer's motion tokens look (SegMo.ground(method="
        "\"attention\")), ordered spans and each segment's best span. "
        + _GROUNDING_SCORE + _GROUNDING_BASELINES),
    "isc": ("Mean cosine of the paired text/motion segments of every caption of the split "
            "(CV = std/mean), motion spans from each segmenter."),
    "reconstruction": (
        "Tokenizer (reconstruction): each real motion through the bundle's tokenizer, every "
        "residual layer, at its length (whole tokens): the generator's ceiling. MPJPE "
        "{mpjpe_mm:.1f} mm with each frame's root joints aligned, {mpjpe_global_mm:.1f} mm "
        "global, over {motions:.0f} motions."),
    "by_num_segments": (
        "Rows of each repeat split by the caption's number of text segments (as the model is "
        "conditioned). FID is against the bucket's real motions and is noisy on small buckets; "
        "R-precision uses batches within the bucket and is '-' where a bucket has fewer motions "
        "than a batch in some repeat."),
    "action_order": (
        "real: the classifier on the real motions (its ceiling); generated: one motion per "
        "motion of the split, from its first caption at the true length, vs that caption's "
        "action sequence."),
    "attributes": (
        "The side, count and speed that a segment of each motion's first caption names, read by "
        "the attribute classifier on the segment's true span (real: the classifier's ceiling; "
        "generated: from the caption at its true length, read on the same frames)."),
}


def number(value: float | None) -> float:
    """A figure of a metrics.json as a float: null (how the file writes NaN) is NaN."""
    return math.nan if value is None else float(value)


def cell(entry: dict[str, float | None] | float | None, digits: int = 3) -> str:
    """"mean±interval" of a repeated metric, the plain number of a single one (or of one
    whose interval is NaN or null: one measurement), "-" if absent (or null)."""
    if entry is None:
        return "-"
    if isinstance(entry, dict):
        mean, interval = number(entry["mean"]), number(entry["interval"])
        if math.isnan(interval):
            return f"{mean:.{digits}f}"
        return f"{mean:.{digits}f}±{interval:.{digits}f}"
    return f"{float(entry):.{digits}f}"


def is_metric(value: Any) -> bool:
    """A metric as `cell` shows it: a number, or {"mean": number, "interval": number}, where
    a number of the dict may be null (NaN in metrics.json)."""
    def real(x: Any) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    if isinstance(value, dict):
        return all(real(value.get(k)) or (k in value and value[k] is None) for k in ("mean", "interval"))
    return real(value)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    def text(cell: str) -> str:  # a name holding '|' or a line break would break the table
        return " ".join(str(cell).split()).replace("|", "\\|")

    lines = ["| " + " | ".join(map(text, header)) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(map(text, r)) + " |" for r in rows]
    return "\n".join(lines)


def generation_table(rows: Sequence[tuple[str, dict[str, Any]]]) -> str:
    """Paper-style table; rows are (name, {metric: {"mean", "interval"}})."""
    header = ["Method"] + [title for _, title in GENERATION_COLUMNS]
    return _table(header, [[name] + [cell(values.get(key)) for key, _ in GENERATION_COLUMNS]
                           for name, values in rows])


def _row_names(metrics: dict[str, Any], name: str | None = None) -> dict[str, str]:
    """metrics.json row key → its name in the tables."""
    model = name or metrics.get("config", {}).get("name") or "model"
    return {"real": "Real", "reconstruction": f"{model} tokenizer (reconstruction)", "generated": model}


def _generation_rows(metrics: dict[str, Any], name: str | None = None, real: bool = True
                     ) -> list[tuple[str, dict[str, Any]]]:
    """(name, row) of the Real (if `real`), reconstruction and generated rows present."""
    generation = metrics.get("generation") or {}
    return [(title, generation[key]) for key, title in _row_names(metrics, name).items()
            if key in generation and (real or key != "real")]


def segments_table(metrics: dict[str, Any]) -> str:
    """The generation rows of each number-of-segments bucket (`by_num_segments`): bucket,
    its captions in the split, the mean motions per repeat it gets, then the metrics."""
    columns = [c for c in GENERATION_COLUMNS if c[0] != "multimodality"]
    header = ["Segments", "Captions", "Per repeat", "Method"] + [title for _, title in columns]
    names = _row_names(metrics)
    rows = []
    for bucket, entry in metrics["generation"]["by_num_segments"].items():
        for key, title in names.items():
            if key in entry:
                rows.append([bucket, str(int(entry["count"])), f"{entry['per_repeat']:.1f}", title]
                            + [cell(entry[key].get(k)) for k, _ in columns])
    return _table(header, rows)


def retrieval_table(retrieval: dict[str, Any]) -> str:
    """Rows: space × protocol × direction; columns R@1/2/3/5/10 and MedR."""
    header = ["Space", "Protocol", "Direction"] + [f"R@{k}" for k in RETRIEVAL_KS] + ["MedR"]
    rows = []
    for space, protocols in retrieval.items():
        if not isinstance(protocols, dict):
            continue
        for protocol, values in protocols.items():
            if not isinstance(values, dict):
                continue
            for direction, title in (("t2m", "text→motion"), ("m2t", "motion→text")):
                if f"{direction}/MedR" not in values:
                    continue
                rows.append([space, protocol, title]
                            + [cell(values.get(f"{direction}/R@{k}")) for k in RETRIEVAL_KS]
                            + [cell(values[f"{direction}/MedR"], 1)])
    return _table(header, rows)


def grounding_table(grounding: dict[str, Any]) -> str:
    """Rows, where present: the default search (plain keys, "ordered spans"; absent for a
    model without the learned space), the other searches, attention grounding and the
    text-free baselines (keys "spans/...", "window/...", "attention/...",
    "attention_spans/...", "uniform/...", "cpd/...", "kmeans/...")."""
    keys = [*(f"R@1,IoU={t:g}" for t in IOU_THRESHOLDS), "mIoU"]
    rows = [["ordered spans"] + [cell(grounding[k]) for k in keys]] if all(k in grounding for k in keys) else []
    for prefix, name in (("spans", "best span"), ("window", "sliding window"),
                         ("attention", "attention, ordered spans"), ("attention_spans", "attention, best span"),
                         ("uniform", "uniform split"), ("cpd", "change points (cpd)"),
                         ("kmeans", "k-means")):
        if all(f"{prefix}/{k}" in grounding for k in keys):
            rows.append([name] + [cell(grounding[f"{prefix}/{k}"]) for k in keys])
    return _table(["Spans"] + keys, rows) + f"\n\n{int(grounding.get('queries', 0))} segment queries."


def isc_table(isc: dict[str, Any]) -> str:
    return _table(["Eval segmenter", "ISC", "CV", "pairs"],
                  [[name, cell(v["mean"]), cell(v["cv"]), str(int(v["pairs"]))] for name, v in isc.items()])


def action_order_table(action_order: dict[str, Any]) -> str:
    """Rows: real, generated, reconstruction; then, given `by_num_segments`, the same per
    number-of-segments bucket of the first captions."""
    header = ["Motions", "Sequence acc.", "Norm. edit dist.", "Frame acc.", "n"]

    def row(name: str, v: dict[str, Any]) -> list[str]:
        return [name, cell(v.get("sequence_accuracy")), cell(v.get("normalised_edit_distance")),
                cell(v.get("frame_accuracy")), str(int(v.get("motions", 0)))]

    table = _table(header, [row(name, v) for name, v in action_order.items() if name != "by_num_segments"])
    buckets = action_order.get("by_num_segments")
    if buckets:
        table += "\n\nBy number of text segments of the first caption:\n\n" + _table(
            ["Segments"] + header, [[bucket] + row(name, v) for bucket, entry in buckets.items()
                                    for name, v in entry.items() if isinstance(v, dict)])
    failing = {name: v for name, v in action_order.items() if name != "by_num_segments" and "errors" in v}
    if failing:
        kinds = list(next(iter(failing.values()))["errors"])
        bins = list(dict.fromkeys(b for v in failing.values() for b in v.get("recall_by_share", {})))
        table += ("\n\nHow sequences fail (share of the motions) and how often a true action is "
                  "found, by its share of the motion's frames:\n\n") + _table(
            ["Motions", *kinds, *[f"found, share {b}" for b in bins]],
            [[name, *[cell(v["errors"][k]) for k in kinds],
              *[cell(v.get("recall_by_share", {}).get(b, {}).get("recall")) for b in bins]]
             for name, v in failing.items()])
    return table


def attributes_table(attributes: dict[str, Any]) -> str:
    names = [n for n in ("side", "count", "speed") if any(n in v for v in attributes.values())]
    return _table(["Motions", "overall", *names, "checks"],
                  [[row, cell(v.get("overall")), *[cell(v.get(n)) for n in names],
                    str(int(v.get("checks", 0)))] for row, v in attributes.items()])


def _multimodality_note(config: dict[str, Any], generated: dict[str, Any]) -> str:
    """"; MModality over R run(s) of P prompts × G generations": P the prompts it ran with
    (one per motion, so fewer than --mm-prompts on a small split; a metrics.json from before
    `multimodality_prompts` was recorded gives the request)."""
    asked = config.get("mm_prompts")
    used = generated.get("multimodality_prompts", asked)
    note = f"; MModality over {config.get('mm_runs')} run(s) of {used} prompts × {config.get('mm_repeats')} generations"
    if isinstance(used, int) and isinstance(asked, int) and used < asked:
        note += f" (--mm-prompts {asked}; the split has {used} motions)"
    return note


def render_report(metrics: dict[str, Any]) -> str:
    """The whole report.md of one evaluation."""
    config = metrics.get("config", {})
    out = [f"# Evaluation of {config.get('name', 'model')}", ""]
    out += [f"- model: `{config.get('model')}`", f"- data: `{config.get('data')}` (split {config.get('split')})",
            f"- evaluator: `{config.get('evaluator')}`",
            f"- repeats: {config.get('repeats')}, seed: {config.get('seed')}, "
            f"batch size: {config.get('batch_size')}, precision: {config.get('precision')}", ""]
    if metrics.get("generation"):
        out += ["## Generation (T2M protocol)", "",
                "R-precision and MM-Dist in batches of "
                f"{config.get('batch_size')}; mean±95 % interval over {config.get('repeats')} repeats"
                + (_multimodality_note(config, metrics["generation"]["generated"])
                   if config.get("mm_prompts") and "generated" in metrics["generation"] else "") + ".", "",
                generation_table(_generation_rows(metrics)), ""]
        reconstruction = metrics["generation"].get("reconstruction")
        if reconstruction:
            out += [NOTES["reconstruction"].format(**reconstruction), ""]
        if metrics["generation"].get("by_num_segments"):
            out += ["### By number of text segments", "", NOTES["by_num_segments"], "", segments_table(metrics), ""]
    notes = metrics.get("notes", {})
    sections = (("retrieval", "Retrieval", retrieval_table), ("grounding", "Grounding", grounding_table),
                ("isc", "Intra-segment consistency (paper Fig. 4)", isc_table),
                ("action_order", "Action order (built-in corpus)", action_order_table),
                ("attributes", "Attribute accuracy (built-in corpus)", attributes_table))
    for key, title, table in sections:
        value = metrics.get(key)
        if not value and not notes.get(key):
            continue
        out += [f"## {title}", ""]
        if notes.get(key):
            out += [notes[key], ""]
        if value:
            out += [table(value), ""]
    if config.get("timings"):
        out += ["## Timings (s)", "", _table(list(config["timings"]),
                                             [[f"{v:.1f}" for v in config["timings"].values()]]), ""]
    return "\n".join(out)


def compare_table(runs: Sequence[tuple[str, dict[str, Any]]]) -> str:
    """Several evaluations side by side (e.g. SegMo vs no alignment, paper Table 3): the Real
    row of the first run that has one, then the reconstruction and generated rows of each run."""
    rows: list[tuple[str, dict[str, Any]]] = []
    for name, metrics in runs:
        if not rows:
            rows += [r for r in _generation_rows(metrics, name) if r[0] == "Real"]
        rows += [r for r in _generation_rows(metrics, name, real=False)]
    if not rows:
        raise ValueError("compare_table: no run has generation metrics")
    return generation_table(rows)


# ------------------------------------------------------------------------------- plots

def _pyplot():
    # matplotlib on use (plots are the last step of `segmo evaluate`), its file backend
    # chosen before pyplot is imported.
    import matplotlib

    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt

    return plt


def plot_isc(isc: dict[str, Any], path: str | Path) -> Path:
    """Bar chart of ISC per evaluation segmenter, CV written on each bar (paper Fig. 4)."""
    plt = _pyplot()
    names = list(isc)
    means = [isc[n]["mean"] for n in names]
    fig, ax = plt.subplots(figsize=(1.2 + 1.2 * len(names), 3))
    bars = ax.bar(names, means, color="#4c72b0")
    for bar, n in zip(bars, names, strict=True):
        ax.annotate(f"CV {isc[n]['cv']:.2f}", (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                    ha="center", va="bottom", fontsize=8)
    ax.set_ylabel("ISC (mean cosine)")
    ax.set_xlabel("evaluation segmenter")
    ax.set_ylim(min(0.0, min(means) * 1.1), max(1e-3, max(means) * 1.2))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
