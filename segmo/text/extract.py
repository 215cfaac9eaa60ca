"""`segmo segment-texts`: offline text-segment extraction over a dataset folder.

For every ``DIR/texts/<id>.txt`` this writes ``DIR/text_segments/<name>/<id>.txt``: line i
holds the segments of caption i (the part of line i before the first '#'), joined by
'#'. ``<name>`` is the segmenter's name ("rule", "openai-qwen3-8b", ...).

Each output file is written atomically (temporary file + ``os.replace``), so a file that
exists is complete: a killed run restarts where it stopped, skipping finished files,
losing at most the captions of the batch in flight and duplicating nothing. A file is
redone if its line count no longer matches its texts file, or with ``--overwrite``.
``meta.json`` records the backend, model and prompt hash (a rerun with another model or
prompt into the same folder is refused without ``--overwrite``); ``summary.json`` the
counts of the whole folder after the run.

Example::

    segmo segment-texts --data data/HumanML3D                      # rules, the default
    segmo segment-texts --data data/HumanML3D --backend openai \\
        --base-url http://localhost:8000/v1 --model Qwen/Qwen3-8B --concurrency 16
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tqdm import tqdm

from segmo.text.llm import get_segmenter
from segmo.text.rules import TextSegmenter

SEPARATOR = "#"


def read_captions(path: Path) -> list[str]:
    """Captions of a HumanML3D texts file, one per line (``caption#tokens#from#to``).

    Raises ValueError naming the file and line if it is not UTF-8 text.
    """
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        raise ValueError(f"{path}:{line}: not UTF-8 text ({err.reason})") from err
    return [line.split(SEPARATOR, 1)[0].strip() for line in text.splitlines()]


def format_line(segments: list[str]) -> str:
    """One output line; '#' and line breaks cannot occur inside a segment, so they are removed."""
    clean = [" ".join(s.replace(SEPARATOR, " ").split()) for s in segments]
    return SEPARATOR.join(clean)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _line_count(path: Path) -> int:
    return len(path.read_text(encoding="utf-8").splitlines())


def describe(segmenter: TextSegmenter, backend: str) -> dict[str, Any]:
    """What `meta.json` records about a segmenter."""
    prompt = getattr(segmenter, "prompt", None)
    return {
        "backend": backend,
        "name": segmenter.name,
        "model": (getattr(segmenter, "model_name", None) or getattr(segmenter, "model", None))
        if backend != "rule" else None,
        "prompt_hash": prompt.hash if prompt is not None else None,
        "max_segments": getattr(segmenter, "max_segments", None),
    }


def _batches(ids: list[str], texts_dir: Path, batch_captions: int) -> Iterator[list[tuple[str, list[str]]]]:
    batch: list[tuple[str, list[str]]] = []
    size = 0
    for motion_id in ids:
        captions = read_captions(texts_dir / f"{motion_id}.txt")
        batch.append((motion_id, captions))
        size += len(captions)
        if size >= batch_captions:
            yield batch
            batch, size = [], 0
    if batch:
        yield batch


def segment_folder(data: str | Path, segmenter: TextSegmenter, backend: str = "rule", *,
                   overwrite: bool = False, batch_captions: int = 256, progress: bool = True) -> dict[str, Any]:
    """Segment every ``texts/<id>.txt`` of `data`; returns the summary (also saved as summary.json)."""
    data = Path(data)
    texts_dir = data / "texts"
    if not texts_dir.is_dir():
        raise FileNotFoundError(f"segment-texts: no texts/ folder in {data}")
    out_dir = data / "text_segments" / segmenter.name
    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.glob(".*.tmp"):  # left by a killed run
        stale.unlink()
    meta = describe(segmenter, backend)
    meta_path = out_dir / "meta.json"
    if meta_path.is_file() and not overwrite:
        old = json.loads(meta_path.read_text(encoding="utf-8"))
        changed = [k for k in ("backend", "model", "prompt_hash") if old.get(k) != meta[k]]
        if changed:
            raise ValueError(f"segment-texts: {out_dir} was made with other {changed} "
                             f"({old}); use --overwrite or another folder")
    _write_atomic(meta_path, json.dumps(meta, indent=2) + "\n")

    ids = sorted(p.stem for p in texts_dir.glob("*.txt"))
    todo = []
    for motion_id in ids:
        out = out_dir / f"{motion_id}.txt"
        if overwrite or not out.is_file() or _line_count(out) != len(read_captions(texts_dir / f"{motion_id}.txt")):
            todo.append(motion_id)
    fallbacks_before = getattr(segmenter, "fallbacks", 0)
    t0 = time.perf_counter()
    with tqdm(total=len(todo), desc=f"segment-texts [{segmenter.name}]", unit="file", disable=not progress) as bar:
        for batch in _batches(todo, texts_dir, batch_captions):
            flat = [c for _, captions in batch for c in captions]
            results = segmenter.segment(flat)
            if len(results) != len(flat):
                raise RuntimeError(f"segment-texts: {segmenter.name} returned {len(results)} results "
                                   f"for {len(flat)} captions")
            k = 0
            for motion_id, captions in batch:
                lines = [format_line(r) for r in results[k : k + len(captions)]]
                k += len(captions)
                _write_atomic(out_dir / f"{motion_id}.txt", "".join(line + "\n" for line in lines))
                bar.update(1)
    elapsed = time.perf_counter() - t0

    histogram: Counter[int] = Counter()
    for motion_id in ids:
        for line in (out_dir / f"{motion_id}.txt").read_text(encoding="utf-8").splitlines():
            histogram[len(line.split(SEPARATOR))] += 1
    captions = sum(histogram.values())
    summary = {
        **meta,
        "motions": len(ids),
        "captions": captions,
        "segment_histogram": {str(k): histogram[k] for k in sorted(histogram)},
        "mean_segments": round(sum(k * v for k, v in histogram.items()) / max(captions, 1), 4),
        "processed_files": len(todo),
        "skipped_files": len(ids) - len(todo),
        "fallbacks": getattr(segmenter, "fallbacks", 0) - fallbacks_before,
        "seconds": round(elapsed, 3),
    }
    _write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="segmo segment-texts", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="dataset folder holding texts/")
    parser.add_argument("--backend", choices=["rule", "openai", "transformers"], default="rule")
    parser.add_argument("--model", help="model name (openai) or name/path (transformers)")
    parser.add_argument("--base-url", help="OpenAI-compatible server, e.g. http://localhost:8000/v1")
    parser.add_argument("--api-key-env", help="environment variable holding the API key (OPENAI_API_KEY)")
    parser.add_argument("--concurrency", type=int, help="parallel requests (openai, default 8)")
    parser.add_argument("--timeout", type=float, help="seconds per request (openai, default 60)")
    parser.add_argument("--max-retries", type=int, help="re-asks before the rule fallback")
    parser.add_argument("--device", help="torch device (transformers, default cpu)")
    parser.add_argument("--batch-size", type=int, help="generation batch (transformers, default 8)")
    parser.add_argument("--no-think", action="store_true",
                        help="openai: ask the server to disable Qwen3 thinking (chat_template_kwargs)")
    parser.add_argument("--batch-captions", type=int, default=256, help="captions per segmenter call")
    parser.add_argument("--overwrite", action="store_true", help="redo every file")
    args = parser.parse_args(argv)

    if args.backend == "rule":
        given = [f for f in ("model", "base_url", "concurrency", "timeout", "device", "batch_size")
                 if getattr(args, f) is not None]
        if given:
            parser.error(f"--backend rule takes none of {['--' + g.replace('_', '-') for g in given]}")
        segmenter = get_segmenter("rule")
    elif args.backend == "openai":
        if not args.base_url or not args.model:
            parser.error("--backend openai needs --base-url and --model")
        extra = {"chat_template_kwargs": {"enable_thinking": False}} if args.no_think else None
        segmenter = get_segmenter("openai", base_url=args.base_url, model=args.model,
                                  api_key_env=args.api_key_env, concurrency=args.concurrency,
                                  timeout=args.timeout, max_retries=args.max_retries, extra_body=extra)
    else:
        if not args.model:
            parser.error("--backend transformers needs --model")
        segmenter = get_segmenter("transformers", model_name_or_path=args.model, device=args.device,
                                  batch_size=args.batch_size, max_retries=args.max_retries)
    summary = segment_folder(args.data, segmenter, args.backend, overwrite=args.overwrite,
                             batch_captions=args.batch_captions)
    out_dir = args.data / "text_segments" / segmenter.name
    print(f"segment-texts: {summary['motions']} motions, {summary['captions']} captions -> {out_dir}")
    print(f"  segments per caption: {summary['segment_histogram']} (mean {summary['mean_segments']})")
    print(f"  processed {summary['processed_files']} files, skipped {summary['skipped_files']}, "
          f"fallbacks {summary['fallbacks']}, {summary['seconds']:.1f} s")
