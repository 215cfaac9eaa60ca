"""The record of a text-segment folder: ``text_segments/<name>/manifest.jsonl``.

A segment file ``<id>.txt`` keeps the reference layout (line i holds the segments of
caption line i of ``texts/<id>.txt``, joined by '#'); what it was made from is recorded
beside it, one JSON object per written file::

    {"id": "000001", "captions": "<sha256 of the caption list>", "lines": 3,
     "fallbacks": [{"line": 2, "index": 1, "reason": "HTTP 500 (...) after 3 retries"}],
     "no_words": [{"line": 3, "index": 2}]}

``captions`` is `segmo.text.captions.captions_hash` of the file's captions, so a caption
edited in place makes the file stale: `segment-texts` redoes it and the dataset reader
refuses it. ``fallbacks`` are the caption lines (``line`` in the texts file, ``index``
among its caption lines) whose segments came from the rules because the LLM failed;
``no_words`` the caption lines without a word, written as a placeholder line.

The record of a file is appended and fsynced right after that file's atomic write, so a
kill -9 can lose at most the record of the file just written (which then counts as stale
and is redone) and can tear only the last line, which is ignored on read and cut off
before the next append. A later record of an id replaces an earlier one; the file is
rewritten atomically, one record per id in id order, at the end of every run. A folder
without ``manifest.jsonl`` (written by hand, or by the reference code) has no record:
the dataset reader then checks only that the line counts match, and `segment-texts`
refuses to write into it without ``--overwrite`` (unless its ``meta.json`` shows that
segment-texts made it).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from segmo.errors import SegmoError
from segmo.files import write_atomic
from segmo.text.captions import captions_hash

MANIFEST = "manifest.jsonl"


class SegmentManifest:
    """The records of one text-segment folder, {id: record}; see the module docstring."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.path = self.folder / MANIFEST
        self.records: dict[str, dict[str, Any]] = {}
        if self.path.exists() and not self.path.is_file():  # a pipe would block its reads
            raise SegmoError(f"{self.path}: not a regular file (a folder or a pipe?); move it away")
        self.exists = self.path.is_file()
        self._torn = 0  # bytes of a torn last line
        if self.exists:
            self._read()

    def _read(self) -> None:
        data = self.path.read_bytes()
        complete = data.rfind(b"\n") + 1  # what follows the last newline is a torn append
        self._torn = len(data) - complete
        for lineno, raw in enumerate(data[:complete].splitlines(), 1):
            if not raw.strip():
                continue
            try:
                record = json.loads(raw.decode("utf-8"))
                if not (isinstance(record, dict) and isinstance(record.get("id"), str)
                        and isinstance(record.get("captions"), str)):
                    raise ValueError("expected an object with 'id' and 'captions'")
            except ValueError as err:  # UnicodeDecodeError and JSONDecodeError included
                raise SegmoError(f"{self.path}:{lineno}: not a segment record ({err}); delete "
                                 "the file and re-run `segmo segment-texts` to redo the folder") from err
            self.records[record["id"]] = record

    def get(self, motion_id: str) -> dict[str, Any] | None:
        return self.records.get(motion_id)

    def stale_reason(self, motion_id: str, captions: list[str]) -> str | None:
        """Why the segment file of `motion_id` does not belong to `captions`, or None.

        Always None for a folder without a manifest (nothing to compare with)."""
        if not self.exists:
            return None
        record = self.records.get(motion_id)
        if record is None:
            return f"it has no record in {self.path} (written by a killed run, or by hand)"
        if record["captions"] != captions_hash(captions):
            return "its captions were edited after it was segmented"
        return None

    def append(self, record: dict[str, Any]) -> None:
        """Add the record of a file just written; on disk (fsynced) when this returns."""
        if self._torn:  # cut a torn last line off, or the new record would be glued to it
            with open(self.path, "r+b") as f:
                f.truncate(os.path.getsize(self.path) - self._torn)
            self._torn = 0
        line = json.dumps(record, ensure_ascii=False, sort_keys=True) + "\n"
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        self.records[record["id"]] = record
        self.exists = True

    def compact(self, keep: set[str] | None = None) -> None:
        """Rewrite the file atomically: one record per id (those in `keep`), in id order."""
        ids = sorted(self.records if keep is None else set(self.records) & keep)
        self.records = {i: self.records[i] for i in ids}
        write_atomic(self.path, "".join(json.dumps(self.records[i], ensure_ascii=False,
                                                   sort_keys=True) + "\n" for i in ids))
        self._torn = 0
        self.exists = True


_loaded: dict[str, tuple[tuple[int, int], SegmentManifest]] = {}


def load_manifest(folder: str | Path) -> SegmentManifest:
    """The manifest of `folder`, re-read only when the file changed (the dataset reader
    asks once per motion)."""
    manifest_path = Path(folder) / MANIFEST
    try:
        stat = manifest_path.stat()
        stamp = (stat.st_mtime_ns, stat.st_size)
    except FileNotFoundError:
        return SegmentManifest(folder)
    key = str(manifest_path.resolve())
    cached = _loaded.get(key)
    if cached is None or cached[0] != stamp:
        cached = _loaded[key] = (stamp, SegmentManifest(folder))
    return cached[1]
