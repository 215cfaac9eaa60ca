"""`segmo segment-texts`: offline text-segment extraction over a dataset folder.

For every ``DIR/texts/<id>.txt`` this writes ``DIR/text_segments/<name>/<id>.txt``: line i
holds the segments of caption line i (`segmo.text.captions`: the non-blank lines, the
part before the first '#'), joined by '#'. ``<name>`` is the segmenter's name ("rule",
"openai-qwen3-8b", ...). A caption without a word (``.``, ``!!!``) is not segmented: it is
reported (file:line, in the log and in summary.json) and its line holds the caption
itself (or ``.``) as a placeholder, never a blank line; the dataset reader skips it. A
malformed line (not ``caption#tokens#from#to``) is segmented, and reported the same way,
since the dataset reader will skip it too.

One writer per dataset folder: the run holds ``DIR/.segmo-writer.lock`` (`FolderLock`),
so a second `segment-texts` or `encode-texts` on the folder stops at once with the PID
of the first. Each output file is written atomically and its record (the hash of the
captions it was made from, its rule fallbacks) is appended to ``manifest.jsonl``
(`segmo.text.manifest`) right after. A rerun therefore redoes exactly the files that are
missing, stale (a caption edited in place), unrecorded (a killed run), or that hold
captions which fell back to the rules (only those captions are asked again), and a
killed run resumes to the same output as an uninterrupted one. ``--overwrite`` redoes
everything. ``meta.json`` records the backend, model and prompt hash, or the rules'
version (a rerun with another model, prompt or rules into the same folder is refused
without ``--overwrite``);
``summary.json`` the counts of the whole folder after the run. A folder holding segment
files but neither ``meta.json`` nor ``manifest.jsonl`` (written by hand, or by the
reference code) is refused without ``--overwrite`` too: its segments are not ours to
replace.

LLM outages are loud: when more than ``--max-fallback-share`` (default 0) of the
folder's captions hold rule fallbacks after the run, the command writes everything and
then exits with status 2, naming the counts and the record.

Example::

    segmo segment-texts --data data/HumanML3D                      # rules, the default
    segmo segment-texts --data data/HumanML3D --backend openai \\
        --base-url http://localhost:8000/v1 --model Qwen/Qwen3-8B --concurrency 16
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from segmo.errors import ArgumentParser, SegmoError, finite_float, non_negative_int, positive_int
from segmo.files import FolderLock, remove_temporaries, write_atomic
from segmo.text.captions import (
    SEPARATOR,
    CaptionLine,
    captions_hash,
    check_data_folder,
    has_words,
    parse_text_line,
    read_caption_lines,
    read_text,
    texts_file,
)
from segmo.text.llm import MAX_CONCURRENCY, MAX_RETRIES, check_base_url, get_text_segmenter
from segmo.text.manifest import MANIFEST, SegmentManifest
from segmo.text.rules import RULES_VERSION, TextSegmenter

log = logging.getLogger(__name__)


class FallbackShareError(SegmoError):
    """More captions fell back to the rules than ``max_fallback_share`` allows."""


def format_line(segments: list[str]) -> str:
    """One output line; '#' and line breaks cannot occur inside a segment, so they are removed."""
    clean = [" ".join(s.replace(SEPARATOR, " ").split()) for s in segments]
    return SEPARATOR.join(clean)


def ordered_text(segments: list[str]) -> str:
    """A caption's text segments as one text, in execution order ("a man walks forward, then
    a man jumps"): what the word keys read with `SamplingOptions.word_text` "segments"."""
    return ", then ".join(segments)


def placeholder(caption: str) -> str:
    """The line written for a caption without words: the caption itself, or '.' if empty."""
    return format_line([caption]) or "."


def describe(segmenter: TextSegmenter, backend: str) -> dict[str, Any]:
    """What `meta.json` records about a segmenter."""
    prompt = getattr(segmenter, "prompt", None)
    return {
        "backend": backend,
        "name": segmenter.name,
        "model": (getattr(segmenter, "model_name", None) or getattr(segmenter, "model", None))
        if backend != "rule" else None,
        "prompt_hash": prompt.hash if prompt is not None else None,
        "rules_version": RULES_VERSION if backend == "rule" else None,
        "max_segments": getattr(segmenter, "max_segments", None),
    }


@dataclass
class _Job:
    """One segment file to (re)write: which of its caption lines to ask the segmenter."""

    motion_id: str
    lines: list[CaptionLine]
    ask: list[int]  # indices into `lines`
    keep: list[str]  # the current output lines (a retry of fallbacks keeps the others)


def _plan(files: list[Path], out_dir: Path, manifest: SegmentManifest, overwrite: bool
          ) -> tuple[list[_Job], list[str]]:
    """The files to (re)write, and the malformed caption lines of all files (for the summary)."""
    jobs, malformed = [], []
    for path in files:
        lines = read_caption_lines(path)
        malformed += _malformed(f"texts/{path.name}", lines)
        out = out_dir / path.name
        record = manifest.get(path.stem)
        current = read_text(out).splitlines() if out.is_file() and not overwrite else None
        fresh = (current is not None and len(current) == len(lines)
                 and manifest.stale_reason(path.stem, [c.caption for c in lines]) is None
                 and record is not None)
        if not fresh:
            jobs.append(_Job(path.stem, lines, list(range(len(lines))), []))
        elif record.get("fallbacks"):  # fresh, but some captions fell back: ask only those
            jobs.append(_Job(path.stem, lines, sorted(f["index"] for f in record["fallbacks"]), current))
    return jobs, malformed


def _malformed(label: str, lines: list[CaptionLine]) -> list[str]:
    """"FILE:LINE: why" for each line with words that the dataset reader will skip (it is
    segmented all the same: segments depend on the caption only)."""
    out = []
    for cap in lines:
        if has_words(cap.caption):
            try:
                parse_text_line(cap.text, label, cap.lineno)
            except ValueError as err:
                out.append(str(err))
    return out


def _batches(jobs: list[_Job], batch_captions: int) -> Iterator[list[_Job]]:
    batch: list[_Job] = []
    size = 0
    for job in jobs:
        batch.append(job)
        size += len(job.ask)
        if size >= batch_captions:
            yield batch
            batch, size = [], 0
    if batch:
        yield batch


def _segment(segmenter: TextSegmenter, captions: list[str]) -> tuple[list[list[str]], dict[int, str]]:
    if hasattr(segmenter, "segment_with_fallbacks"):
        results, fell_back = segmenter.segment_with_fallbacks(captions)
    else:
        results, fell_back = segmenter.segment(captions), {}
    if len(results) != len(captions):
        raise RuntimeError(f"segment-texts: {segmenter.name} returned {len(results)} results "
                           f"for {len(captions)} captions")
    return results, fell_back


def _write(job: _Job, results: dict[int, list[str]], fell_back: dict[int, str], texts_path: Path,
           out_dir: Path, manifest: SegmentManifest) -> None:
    """Write one segment file atomically, then append its record."""
    lines, no_words = list(job.keep) or [""] * len(job.lines), []
    for i, cap in enumerate(job.lines):
        if not has_words(cap.caption):
            lines[i] = placeholder(cap.caption)
            no_words.append({"line": cap.lineno, "index": i})
            log.warning("%s:%d: caption %r has no words; not segmented (its segment line is a "
                        "placeholder, and the dataset reader skips it)", texts_path, cap.lineno, cap.caption)
        elif i in results:
            lines[i] = format_line(results[i])
    # a retry asks every caption that fell back before, so the new record's fallbacks are
    # exactly this run's
    fallbacks = [{"line": job.lines[i].lineno, "index": i, "reason": fell_back[i]} for i in sorted(fell_back)]
    write_atomic(out_dir / f"{job.motion_id}.txt", "".join(line + "\n" for line in lines))
    manifest.append({"id": job.motion_id, "captions": captions_hash([c.caption for c in job.lines]),
                     "lines": len(lines), "fallbacks": fallbacks, "no_words": no_words})


def segment_folder(data: str | Path, segmenter: TextSegmenter, backend: str = "rule", *,
                   overwrite: bool = False, batch_captions: int = 256,
                   max_fallback_share: float | None = 0.0, progress: bool = True) -> dict[str, Any]:
    """Segment every ``texts/<id>.txt`` of `data`; returns the summary (also saved as summary.json).

    Holds the folder's writer lock for the whole run (`FolderBusyError` if another writer
    has it). Raises `FallbackShareError` after writing everything when more than
    `max_fallback_share` of the folder's captions hold rule fallbacks (None: never).
    """
    if batch_captions < 1:
        raise SegmoError(f"batch_captions must be >= 1, got {batch_captions}")
    if max_fallback_share is not None and not 0 <= max_fallback_share <= 1:
        raise SegmoError(f"max_fallback_share must be between 0 and 1, got {max_fallback_share}")
    data, files = check_data_folder(data)
    with FolderLock(data, "segmo segment-texts"):
        out_dir = data / "text_segments" / segmenter.name
        out_dir.mkdir(parents=True, exist_ok=True)
        remove_temporaries(out_dir)  # left by a killed run; ours are not live: we hold the lock
        meta = describe(segmenter, backend)
        meta_path = out_dir / "meta.json"
        if (not overwrite and not meta_path.exists() and not (out_dir / MANIFEST).exists()
                and any(out_dir.glob("*.txt"))):
            # made by hand or by the reference code: legitimate segments, not ours to replace
            raise SegmoError(f"{out_dir}: holds segment files not written by segment-texts (no meta.json, "
                             "no manifest.jsonl); use --overwrite to replace them, or move the folder "
                             "away (its name comes from --backend and --model)")
        if meta_path.is_file() and not overwrite:
            try:
                old = json.loads(read_text(meta_path))
                if not isinstance(old, dict):
                    raise ValueError("not a JSON object")
            except ValueError as err:
                raise SegmoError(f"{meta_path}: not valid JSON ({err}); delete it or use --overwrite") from err
            changed = [k for k in ("backend", "model", "prompt_hash", "rules_version")
                       if old.get(k) != meta[k]]
            if changed:
                raise SegmoError(f"{out_dir} was made with other {', '.join(changed)} ({old}); "
                                 "use --overwrite or another folder")
        write_atomic(meta_path, json.dumps(meta, indent=2) + "\n")
        manifest = SegmentManifest(out_dir)

        jobs, malformed = _plan(files, out_dir, manifest, overwrite)
        for problem in malformed:
            log.warning("%s/%s; segmented, but the dataset reader will skip the line", data, problem)
        t0 = time.perf_counter()
        fallbacks_now = 0
        total = sum(1 for job in jobs for i in job.ask if has_words(job.lines[i].caption))
        with tqdm(total=total, desc=f"segment-texts [{segmenter.name}]", unit="caption",
                  disable=not progress) as bar:
            # An LLM backend moves the bar as its answers arrive, the rules batch by batch.
            live = hasattr(segmenter, "progress")
            if live:
                segmenter.progress = bar.update
            try:
                for batch in _batches(jobs, batch_captions):
                    asked = [(job, i) for job in batch for i in job.ask if has_words(job.lines[i].caption)]
                    results, fell_back = _segment(segmenter, [job.lines[i].caption for job, i in asked])
                    fallbacks_now += len(fell_back)
                    for job in batch:
                        mine = {k: i for k, (owner, i) in enumerate(asked) if owner is job}
                        _write(job, {i: results[k] for k, i in mine.items()},
                               {i: fell_back[k] for k, i in mine.items() if k in fell_back},
                               texts_file(data, job.motion_id), out_dir, manifest)
                    if not live:
                        bar.update(len(asked))
            finally:
                if live:
                    segmenter.progress = None
        elapsed = time.perf_counter() - t0
        ids = [p.stem for p in files]
        manifest.compact({p.stem for p in out_dir.glob("*.txt")})
        summary = _summary(meta, ids, out_dir, manifest, len(jobs), fallbacks_now, elapsed)
        summary["malformed"] = malformed
        write_atomic(out_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
    captions, fallen = summary["captions"], summary["fallback_captions"]
    if max_fallback_share is not None and fallen > max_fallback_share * max(captions, 1):
        raise FallbackShareError(
            f"{fallen} of {captions} captions ({100 * fallen / max(captions, 1):.1f}%) hold rule "
            f"fallbacks because the LLM failed (allowed: {100 * max_fallback_share:g}%, "
            f"--max-fallback-share {max_fallback_share:g}); each is recorded with its reason under "
            f"\"fallbacks\" in {manifest.path}; re-run to retry them")
    return summary


def _summary(meta: dict, ids: list[str], out_dir: Path, manifest: SegmentManifest, processed: int,
             fallbacks_now: int, elapsed: float) -> dict[str, Any]:
    histogram: Counter[int] = Counter()
    no_words, fallen = [], 0
    for motion_id in ids:
        record = manifest.get(motion_id) or {}
        skip = {n["index"] for n in record.get("no_words", [])}
        no_words += [f"texts/{motion_id}.txt:{n['line']}" for n in record.get("no_words", [])]
        fallen += len(record.get("fallbacks", []))
        lines = read_text(out_dir / f"{motion_id}.txt").splitlines()
        histogram.update(len(line.split(SEPARATOR)) for i, line in enumerate(lines) if i not in skip)
    captions = sum(histogram.values())
    return {
        **meta,
        "motions": len(ids),
        "captions": captions,
        "segment_histogram": {str(k): histogram[k] for k in sorted(histogram)},
        "mean_segments": round(sum(k * v for k, v in histogram.items()) / max(captions, 1), 4),
        "processed_files": processed,
        "skipped_files": len(ids) - processed,
        "fallbacks": fallbacks_now,  # captions that fell back in this run
        "fallback_captions": fallen,  # captions of the folder holding a fallback now
        "no_words": no_words,
        "seconds": round(elapsed, 3),
    }


# --------------------------------------------------------------------------- command
def _seconds(text: str) -> float:
    value = finite_float(text)
    # A day at most: beyond what the platform's clock holds, a socket fails with OverflowError.
    if not 0 < value <= 86400:
        raise argparse.ArgumentTypeError(f"expected a number of seconds in (0, 86400], got {text!r}")
    return value


def _retries(text: str) -> int:
    value = non_negative_int(text)
    if value > MAX_RETRIES:  # each waits up to 8 s, or two minutes for a Retry-After
        raise argparse.ArgumentTypeError(f"expected at most {MAX_RETRIES} retries, got {text!r}")
    return value


def _concurrency(text: str) -> int:
    value = positive_int(text)
    if value > MAX_CONCURRENCY:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_CONCURRENCY} parallel requests, "
                                         f"got {text!r}")
    return value


def _share(text: str) -> float:
    value = finite_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a share between 0 and 1, got {text!r}")
    return value


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="segmo segment-texts", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="dataset folder holding texts/")
    parser.add_argument("--backend", choices=["rule", "openai", "transformers"], default="rule")
    parser.add_argument("--model", help="model name (openai) or name/path (transformers)")
    parser.add_argument("--base-url", help="OpenAI-compatible server, e.g. http://localhost:8000/v1 "
                                           "(default: $OPENAI_BASE_URL)")
    parser.add_argument("--api-key-env", help="environment variable holding the API key (OPENAI_API_KEY)")
    parser.add_argument("--concurrency", type=_concurrency, help="parallel requests (openai, default 8)")
    parser.add_argument("--structured-output", choices=["auto", "json_schema", "off"], default="auto",
                        help="openai: ask for a JSON-schema response_format (auto: unless the "
                             "server refuses it)")
    parser.add_argument("--timeout", type=_seconds,
                        help="seconds to wait for the server, and for an answer to arrive once "
                             "it begins (openai, default 60)")
    parser.add_argument("--max-retries", type=_retries,
                        help="retries of a failed request and re-asks of a rejected answer before "
                             "the rule fallback (default: openai 3, transformers 1)")
    parser.add_argument("--max-fallback-share", type=_share, default=0.0,
                        help="exit with status 2 when more than this share of the captions hold rule "
                             "fallbacks after the run (default 0)")
    parser.add_argument("--device", help="torch device (transformers, default cpu)")
    parser.add_argument("--batch-size", type=positive_int, help="generation batch (transformers, default 8)")
    parser.add_argument("--no-think", action="store_true",
                        help="openai: ask the server to disable Qwen3 thinking (chat_template_kwargs)")
    parser.add_argument("--batch-captions", type=positive_int, default=256, help="captions per segmenter call")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo every file, also in a folder segment-texts did not write")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    check_data_folder(args.data)  # before an LLM backend loads a model
    if args.backend == "rule":
        given = [f for f in ("model", "base_url", "concurrency", "timeout", "device", "batch_size",
                             "max_retries") if getattr(args, f) is not None]
        if given:
            parser.error(f"--backend rule takes none of {['--' + g.replace('_', '-') for g in given]}")
        segmenter = get_text_segmenter("rule")
    elif args.backend == "openai":
        if not args.model:
            parser.error("--backend openai needs --model")
        base_url = args.base_url or os.environ.get("OPENAI_BASE_URL")
        if not base_url:
            parser.error("--backend openai needs --base-url (or OPENAI_BASE_URL in the environment)")
        try:
            check_base_url(base_url)
        except SegmoError as err:
            parser.error(f"argument --base-url: {err}")
        extra = {"chat_template_kwargs": {"enable_thinking": False}} if args.no_think else None
        segmenter = get_text_segmenter("openai", base_url=base_url, model=args.model,
                                       api_key_env=args.api_key_env, concurrency=args.concurrency,
                                       timeout=args.timeout, max_retries=args.max_retries,
                                       extra_body=extra, structured_output=args.structured_output)
    else:
        if not args.model:
            parser.error("--backend transformers needs --model")
        segmenter = get_text_segmenter("transformers", model_name_or_path=args.model,
                                       device=args.device, batch_size=args.batch_size,
                                       max_retries=args.max_retries)
    out_dir = args.data / "text_segments" / segmenter.name
    try:
        summary = segment_folder(args.data, segmenter, args.backend, overwrite=args.overwrite,
                                 batch_captions=args.batch_captions,
                                 max_fallback_share=args.max_fallback_share, progress=not args.quiet)
    except FallbackShareError:
        _print(json.loads(read_text(out_dir / "summary.json")), out_dir)
        raise
    _print(summary, out_dir)


def _print(summary: dict[str, Any], out_dir: Path) -> None:
    print(f"segment-texts: {summary['motions']} motions, {summary['captions']} captions -> {out_dir}")
    print(f"  segments per caption: {summary['segment_histogram']} (mean {summary['mean_segments']})")
    print(f"  processed {summary['processed_files']} files, skipped {summary['skipped_files']}, "
          f"fallbacks {summary['fallbacks']} this run, {summary['fallback_captions']} in the folder, "
          f"{summary['seconds']:.1f} s")
    if summary["no_words"]:
        shown = ", ".join(summary["no_words"][:5])
        more = f" (+{len(summary['no_words']) - 5} more, listed in summary.json)" if len(summary["no_words"]) > 5 else ""
        print(f"  {len(summary['no_words'])} caption(s) without words, not segmented: {shown}{more}")
    if summary["malformed"]:
        more = f" (+{len(summary['malformed']) - 1} more, listed in summary.json)" if len(summary["malformed"]) > 1 else ""
        print(f"  {len(summary['malformed'])} malformed caption line(s), segmented but skipped by the "
              f"dataset reader: {summary['malformed'][0]}{more}")
