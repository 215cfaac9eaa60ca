"""What "the caption lines of ``texts/<id>.txt``" are: one definition for every reader.

`segment-texts` (which writes one segment line per caption line), `encode-texts` (which
encodes the captions) and the dataset reader (which pairs caption line i with segment
line i) all read a texts file through `read_caption_lines`, so they cannot disagree on
which lines count:

* a caption line is a line of the file that is not blank (whitespace only);
* its caption is the part before the first '#', whitespace runs collapsed to one space;
* a caption without a letter or digit (``.``, ``!!!``, an empty first field) has no words:
  `segment-texts` reports it and writes a placeholder line, the dataset reader skips it
  as a bad line, `encode-texts` does not encode it.

`parse_text_line` reads the other fields of a line (``caption#word/POS ...#from#to``: the
time tags the dataset reader cuts sub-clips with). `captions_hash` is what a segment
file's record in ``manifest.jsonl`` stores, so that a caption edited in place makes its
segment file stale (`segmo.text.manifest`).
"""

from __future__ import annotations

import codecs
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from segmo.errors import SegmoError

SEPARATOR = "#"
TEXTS = "texts"  # ROOT/texts/<id>.txt
_WORD = re.compile(r"[^\W_]")  # a letter or digit, in any script


@dataclass(frozen=True)
class CaptionLine:
    """One caption line of a texts file."""

    lineno: int  # 1-based line number in the file, for messages
    text: str  # the whole line, stripped
    caption: str  # the part before the first '#', whitespace-normalised


def texts_file(root: str | Path, motion_id: str) -> Path:
    """``ROOT/texts/<id>.txt``: the caption lines of one motion."""
    return Path(root) / TEXTS / f"{motion_id}.txt"


def caption_of(line: str) -> str:
    """The caption of a texts-file line: the first '#' field, whitespace-normalised."""
    return " ".join(line.split(SEPARATOR, 1)[0].split())


def has_words(text: str) -> bool:
    """Whether `text` holds a letter or a digit (``.`` and ``!!!`` do not)."""
    return _WORD.search(text) is not None


def read_text(path: Path) -> str:
    """A file's text, decoded as UTF-8 (a leading byte-order mark, which Windows editors
    write, left out); SegmoError naming the file and line otherwise."""
    if path.exists() and not path.is_file() and not path.is_dir():  # a pipe would block
        raise SegmoError(f"{path}: not a regular file (a pipe or a device?)")
    data = path.read_bytes().removeprefix(codecs.BOM_UTF8)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        column = err.start - data.rfind(b"\n", 0, err.start)
        raise SegmoError(f"{path}:{line}: not UTF-8 text ({err.reason} at byte {column} "
                         "of the line)") from err


def read_caption_lines(path: str | Path) -> list[CaptionLine]:
    """The caption lines of a texts file (see the module docstring), in file order."""
    path = Path(path)
    return [CaptionLine(n, s.strip(), caption_of(s))
            for n, s in enumerate(read_text(path).splitlines(), 1) if s.strip()]


@dataclass(frozen=True)
class Caption:
    """One parsed line of ``texts/<id>.txt``; ``start``/``end`` in seconds, both 0 = whole clip."""

    text: str
    start: float
    end: float
    line: int  # 1-based line number in the file, for messages

    @property
    def whole_clip(self) -> bool:
        return self.start == 0.0 and self.end == 0.0


def parse_text_line(line: str, path: str | Path = "<text>", lineno: int = 0) -> Caption:
    """Parse ``caption#word/POS ...#from#to``; NaN tags count as 0 (HumanML3D convention)."""
    parts = line.strip().split("#")
    where = f"{path}:{lineno}"
    if len(parts) != 4:
        raise SegmoError(f"{where}: expected 'caption#tokens#from#to', got {len(parts)} "
                         f"'#'-separated fields: {line.strip()[:80]!r}")
    caption = parts[0].strip()
    if not has_words(caption):  # "", ".", "!!!": segment-texts reports these too
        raise SegmoError(f"{where}: caption without words: {caption!r}")
    try:
        start, end = float(parts[2]), float(parts[3])
    except ValueError:
        raise SegmoError(f"{where}: from/to are not numbers: {parts[2]!r}, {parts[3]!r}") from None
    start = 0.0 if math.isnan(start) else start
    end = 0.0 if math.isnan(end) else end
    if not (math.isfinite(start) and math.isfinite(end)):  # `inf` seconds: no frame
        raise SegmoError(f"{where}: time tags must be finite seconds, got from={start} to={end}")
    if not (start == 0.0 and end == 0.0) and not (0.0 <= start < end):
        raise SegmoError(f"{where}: bad time tags from={start} to={end}")
    return Caption(caption, start, end, lineno)


def captions_hash(captions: list[str]) -> str:
    """sha256 (hex) of a file's caption list, in order; what a segment file was made from."""
    payload = json.dumps([" ".join(c.split()) for c in captions], ensure_ascii=False)
    return hashlib.sha256(payload.encode("utf-8")).hexdigest()


def check_data_folder(data: str | Path) -> tuple[Path, list[Path]]:
    """`data` and its texts files; SegmoError naming what is wrong with the folder."""
    data = Path(data)
    if not data.exists():
        raise SegmoError(f"--data {data}: no such folder")
    if not data.is_dir():
        raise SegmoError(f"--data {data}: is a file, not a dataset folder (the folder holding texts/)")
    texts_dir = data / TEXTS
    if not texts_dir.is_dir():
        raise SegmoError(f"--data {data}: no texts/ folder in it (expected {texts_dir}/<id>.txt)")
    entries = sorted(texts_dir.glob("*.txt"))
    others = [p.name for p in entries if not p.is_file()]
    if others:  # skipped, their motions would lose captions without a word
        raise SegmoError(f"{texts_dir}: {len(others)} of its *.txt entries are not caption files "
                         f"(a broken link, a folder or a pipe), e.g. {others[0]!r}; fix or remove them")
    files = entries
    if not files:
        raise SegmoError(f"{texts_dir} holds no <id>.txt caption files")
    return data, files
