"""The text-feature cache at ``ROOT/text_features/<encoder>/`` and `segmo encode-texts`.

Every distinct text of a dataset -- each caption of ``texts/<id>.txt`` and each segment of
``text_segments/<name>/<id>.txt`` -- is encoded once by a frozen encoder, so training never
runs the text model. Texts are keyed by `normalise_text`: leading/trailing whitespace
removed and inner runs of whitespace collapsed to one space; case and punctuation are kept
(the encoders' tokenizers decide what they ignore).

Layout (all arrays ``.npy``, memory-mapped on read)::

    meta.json                  encoder name, kind, dim, max_length, model path, identity
                               (digest of its weights), library versions
    index.json                 {"format": 1, "shards": [{"name", "texts", "token_texts"}]}
    shard-00000.sentence.npy   (m, dim) float16, row i = shard["texts"][i]
    shard-00000.tokens.npy     (L, dim) float16, token features of shard["token_texts"]
    shard-00000.offsets.npy    (k + 1,) int64, text j's tokens are rows offsets[j]:offsets[j+1]

Token features are kept for captions only (segments need just a sentence vector).
Sentence vectors are float16, half the size of float32: on all-MiniLM-L6-v2 (400
synthetic captions/segments) cosine similarities between texts move by at most 6e-5.
Captions are the caption lines of `segmo.text.captions` (the definition segment-texts
and the dataset reader use); captions and segments without a word (".") are not encoded.

Updates are incremental and crash-safe: a run encodes only texts missing from the cache,
writes each new shard's files atomically (`segmo.files.write_atomic`), and only then
atomically replaces ``index.json``; files of a killed run that never reached the index
are ignored and later overwritten, so a killed run resumes to the same files as an
uninterrupted one. One writer per dataset folder: `update_cache` holds the folder's
`FolderLock` for its whole run, so a second `encode-texts` (or a `segment-texts`) on the
same folder stops at once naming the first one's PID, and nothing is lost. A cache is
refused when the encoder's weights (a hub name's: its cached snapshot's) or the length
it cuts texts to differ from the recorded ones. Expected failures (a missing folder, a
file that is not UTF-8, a corrupt index.json or meta.json, an unknown encoder) raise
`SegmoError` naming the file or argument.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from segmo import __version__
from segmo.errors import ArgumentParser, SegmoError, positive_int
from segmo.files import FolderLock, atomic_open, remove_temporaries, write_atomic
from segmo.text.captions import check_data_folder, has_words, read_caption_lines, read_text
from segmo.text.encoders import (
    TextEncoder,
    encoder_folder_name,
    encoder_identity,
    encoder_max_length,
    encoder_source,
    get_text_encoder,
)

FORMAT = 1
INDEX, META = "index.json", "meta.json"
MAX_DIM = 1 << 16  # widths of text features (CLIP 512, MiniLM 384); a larger one is damage


def normalise_text(text: str) -> str:
    """The cache key of a text: whitespace runs collapsed to one space, ends stripped."""
    return " ".join(text.split())


def cache_folder(root: str | Path, encoder: str) -> Path:
    """``ROOT/text_features/<encoder folder name>``."""
    return Path(root) / "text_features" / encoder_folder_name(encoder)


# --------------------------------------------------------------------------- reading texts
def read_captions(root: str | Path) -> list[str]:
    """Normalised captions of ``ROOT/texts/*.txt`` (`segmo.text.captions`), in file order,
    duplicates kept, captions without words left out."""
    _, files = check_data_folder(root)
    return [c.caption for path in files for c in read_caption_lines(path) if has_words(c.caption)]


def read_segments(root: str | Path, names: list[str] | None = None) -> list[str]:
    """Normalised text segments ('#'-separated on each line) of ``ROOT/text_segments/<name>/``
    for the given names, or for every folder present when `names` is None."""
    base = Path(root) / "text_segments"
    present = sorted(p.name for p in base.iterdir() if p.is_dir()) if base.is_dir() else []
    if names is None:
        names = present
    missing = [n for n in names if n not in present]
    if missing:
        raise SegmoError(f"--segments {missing[0]}: no text-segment folder {base / missing[0]} "
                         f"(present: {', '.join(present) or 'none'}; build one with "
                         "`segmo segment-texts`)")
    segments = []
    for name in names:
        for path in sorted((base / name).glob("*.txt")):
            for line in read_text(path).splitlines():
                segments += [s for s in map(normalise_text, line.split("#")) if has_words(s)]
    return segments


def _read_json(path: Path, what: str) -> Any:
    """A JSON object from `path`; SegmoError naming the file when it is not one."""
    try:
        value = json.loads(read_text(path))
        if not isinstance(value, dict):
            raise ValueError("not a JSON object")
        return value
    except ValueError as err:
        raise SegmoError(f"{path}: corrupt {what} ({err}); delete {path.parent} and re-run "
                         "`segmo encode-texts`") from err


def _read_index(folder: Path) -> dict:
    index = _read_json(folder / INDEX, "text-feature index")
    shards = index.get("shards")
    if index.get("format") != FORMAT or not isinstance(shards, list) or not all(
            isinstance(sh, dict) and {"name", "texts", "token_texts"} <= set(sh) for sh in shards):
        raise SegmoError(f"{folder / INDEX}: not a format-{FORMAT} text-feature index (expected "
                         '{"format": 1, "shards": [{"name", "texts", "token_texts"}, ...]}); delete '
                         f"{folder} and re-run `segmo encode-texts`")
    return index


# --------------------------------------------------------------------------- the cache
class TextFeatureCache:
    """Read-only view of a built cache: fast dict lookups into memory-mapped shards.

    Example::

        cache = TextFeatureCache.open("data/synth", "minilm")
        cache.sentence(["a person walks forward"])   # (1, 384) float32
        cache.tokens("a person walks forward")       # (l, 384) float32, captions only
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.meta = _read_json(self.folder / META, "text-feature metadata")
        dim = self.meta.get("dim")
        if isinstance(dim, bool) or not isinstance(dim, int) or not 1 <= dim <= MAX_DIM \
                or not isinstance(self.meta.get("encoder"), str):
            raise SegmoError(f"{self.folder / META}: no valid 'dim' (a whole number up to "
                             f"{MAX_DIM}) and 'encoder'; delete {self.folder} and re-run "
                             "`segmo encode-texts`")
        self.dim, self.encoder = dim, self.meta["encoder"]
        index = _read_index(self.folder)
        self._sentences: list[np.ndarray] = []
        self._tokens: list[np.ndarray | None] = []
        self._rows: dict[str, tuple[int, int]] = {}  # text -> (shard, row)
        self._spans: dict[str, tuple[int, int, int]] = {}  # text -> (shard, start, end)
        for s, shard in enumerate(index["shards"]):
            sentence, tokens, offsets = self._open_shard(shard)
            self._sentences.append(sentence)
            self._rows.update((t, (s, r)) for r, t in enumerate(shard["texts"]))
            self._tokens.append(tokens)
            if tokens is not None:
                self._spans.update((t, (s, offsets[j], offsets[j + 1]))
                                   for j, t in enumerate(shard["token_texts"]))

    def _open_shard(self, shard: dict) -> tuple[np.ndarray, np.ndarray | None, list[int]]:
        """A shard's sentence vectors, token features and offsets, memory-mapped, once their
        names, shapes, types and offsets agree with index.json (SegmoError naming the file:
        a shard cut short, of another width or type, or offsets past its end were read as
        valid). Shards swapped with others of the same shape are not found."""
        name, texts, token_texts = shard["name"], shard["texts"], shard["token_texts"]
        redo = f"; delete {self.folder} and re-run `segmo encode-texts`"
        if not (isinstance(name, str) and re.fullmatch(r"shard-\d{5}", name)
                and isinstance(texts, list) and isinstance(token_texts, list)
                and all(isinstance(t, str) for t in [*texts, *token_texts])):
            raise SegmoError(f"{self.folder / INDEX}: shard {str(name)[:40]!r} is not a shard "
                             f"entry of segmo's (name shard-NNNNN, lists of texts){redo}")
        stem = self.folder / name
        sentence = _load_array(f"{stem}.sentence.npy", mmap_mode="r")
        if sentence.shape != (len(texts), self.dim) or sentence.dtype.kind != "f":
            raise SegmoError(f"{stem}.sentence.npy: {sentence.dtype} of shape {sentence.shape}, "
                             f"expected floats of shape ({len(texts)}, {self.dim}){redo}")
        if not token_texts:
            return sentence, None, []
        tokens = _load_array(f"{stem}.tokens.npy", mmap_mode="r")
        offsets = _load_array(f"{stem}.offsets.npy", mmap_mode="r")
        if tokens.ndim != 2 or tokens.shape[1] != self.dim or tokens.dtype.kind != "f":
            raise SegmoError(f"{stem}.tokens.npy: {tokens.dtype} of shape {tokens.shape}, "
                             f"expected floats of shape (tokens, {self.dim}){redo}")
        if offsets.shape != (len(token_texts) + 1,) or offsets.dtype.kind not in "iu":
            raise SegmoError(f"{stem}.offsets.npy: {offsets.dtype} of shape {offsets.shape}, "
                             f"expected {len(token_texts) + 1} whole numbers{redo}")
        bounds = offsets.tolist()
        if bounds[0] != 0 or bounds[-1] != len(tokens) or any(
                a > b for a, b in zip(bounds, bounds[1:])):
            raise SegmoError(f"{stem}.offsets.npy: offsets must run from 0 up to the "
                             f"{len(tokens)} rows of {stem.name}.tokens.npy{redo}")
        return sentence, tokens, bounds

    @classmethod
    def open(cls, root: str | Path, encoder: str) -> TextFeatureCache:
        """Open ``ROOT/text_features/<encoder>/``; FileNotFoundError when it was never built,
        SegmoError naming the file when a file of it is corrupt."""
        folder = cache_folder(root, encoder)
        if not (folder / INDEX).is_file() or not (folder / META).is_file():
            raise FileNotFoundError(f"no text-feature cache at {folder}; build it with "
                                    f"`segmo encode-texts --data {root} --encoder {encoder}`")
        cache = cls(folder)
        source = encoder_source(encoder)
        check_encoder(folder, cache.meta, source, encoder_max_length(source))
        return cache

    def sentence(self, texts: list[str]) -> torch.Tensor:
        """(n, dim) float32 sentence vectors; KeyError naming the first text not cached."""
        if isinstance(texts, str):
            raise TypeError("TextFeatureCache.sentence(texts): pass a list of strings")
        out = np.empty((len(texts), self.dim), dtype=np.float32)
        for i, text in enumerate(texts):
            key = normalise_text(text)
            if key not in self._rows:
                raise KeyError(f"text {text!r} is not in the text-feature cache {self.folder}; "
                               "re-run `segmo encode-texts` after adding it")
            shard, row = self._rows[key]
            out[i] = self._sentences[shard][row]
        return torch.from_numpy(out)

    def tokens(self, text: str) -> torch.Tensor:
        """(l, dim) float32 token features of a caption (special tokens included)."""
        key = normalise_text(text)
        if key not in self._spans:
            kind = "a segment only (token features are kept for captions)" \
                if key in self._rows else "not cached"
            raise KeyError(f"no token features for {text!r} in {self.folder}: {kind}")
        shard, start, end = self._spans[key]
        return torch.from_numpy(np.asarray(self._tokens[shard][start:end], dtype=np.float32))

    def has_tokens(self, text: str) -> bool:
        return normalise_text(text) in self._spans

    def __contains__(self, text: object) -> bool:
        return isinstance(text, str) and normalise_text(text) in self._rows

    def __len__(self) -> int:
        return len(self._rows)

    # Memory maps do not pickle; DataLoader workers re-open the folder instead.
    def __getstate__(self) -> dict:
        return {"folder": str(self.folder)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(Path(state["folder"]))

    def __repr__(self) -> str:
        return f"TextFeatureCache({str(self.folder)!r}, texts={len(self)}, dim={self.dim})"


# --------------------------------------------------------------------------- building
@dataclass
class CacheSummary:
    """What one `update_cache` run did. `new` counts texts encoded in this run (new
    sentences, or captions whose token features were missing)."""

    folder: Path
    total: int
    new: int
    reused: int
    seconds: float
    bytes_on_disk: int

    def __str__(self) -> str:
        return (f"{self.folder}: {self.total} distinct texts, {self.new} new, {self.reused} "
                f"reused, {self.seconds:.1f} s, {self.bytes_on_disk / 2**20:.1f} MiB on disk")


def check_encoder(folder: Path, meta: dict, source: str | Path | None,
                  max_length: int | None = None) -> None:
    """SegmoError when the cache in `folder` was encoded by other weights than the encoder
    in directory `source` (`encoder_identity`), or by the same weights with texts cut at
    another length than its `max_length`; not checked when either identity is unknown (an
    encoder object not read from a directory): two encoder directories of one name share
    a folder, a hub name's main moved to new weights, or sentence_bert_config.json
    changed, and old features were served as the encoder's."""
    built, now = meta.get("identity"), encoder_identity(source)
    if built is None or now is None:
        return
    if built != now:
        raise SegmoError(f"{folder}: its features were encoded by another {meta.get('encoder')!r} "
                         f"encoder than {source} (the weights differ); delete the folder to "
                         "encode again, or give this encoder a directory of another name")
    cut = meta.get("max_length")
    if isinstance(cut, int) and max_length is not None and cut != max_length:
        raise SegmoError(f"{folder}: its features were cut at {cut} tokens, the encoder {source} "
                         f"now cuts at {max_length} (its tokenizer or sentence_bert_config.json "
                         "changed); delete the folder to encode again")


def _load_array(path: str, mmap_mode: str | None = None) -> np.ndarray:
    try:
        return np.load(path, mmap_mode=mmap_mode)
    except (OSError, ValueError, EOFError) as err:
        raise SegmoError(f"{path}: unreadable shard of the text-feature cache ({err}); delete "
                         f"{Path(path).parent} and re-run `segmo encode-texts`") from err


def _write_json(path: Path, obj: dict) -> None:
    write_atomic(path, json.dumps(obj, ensure_ascii=False))


def _meta(encoder: TextEncoder) -> dict:
    import transformers  # on use: reading a cache, and an injected encoder, need none of it

    return {"encoder": encoder.name, "kind": type(encoder).__name__, "dim": encoder.dim,
            "max_length": encoder.max_length, "model_path": encoder.model_path,
            "identity": encoder_identity(encoder.folder),
            "format": FORMAT, "sentence_dtype": "float16", "token_dtype": "float16",
            "versions": {"segmo": __version__, "torch": torch.__version__,
                         "transformers": transformers.__version__, "numpy": np.__version__}}


def update_cache(root: str | Path, encoder: str | TextEncoder, segments: list[str] | None = None,
                 batch_size: int = 64, device: str = "cpu", shard_size: int = 1024,
                 progress: bool = True) -> CacheSummary:
    """Encode every caption and text segment of `root` not yet cached, appending shards.

    `segments`: names of ``text_segments/`` folders (None = all present). `encoder`: a name
    for `get_text_encoder` or an encoder object (whose `name` picks the folder); a named
    encoder is loaded only when something needs encoding. `shard_size` texts per shard.
    Holds the folder's writer lock for the whole run (`FolderBusyError` if another writer
    has it).
    """
    if batch_size < 1 or shard_size < 1:
        raise SegmoError(f"batch_size and shard_size must be >= 1, got {batch_size}, {shard_size}")
    start = time.perf_counter()
    root, _ = check_data_folder(root)
    with FolderLock(root, "segmo encode-texts"):
        captions = read_captions(root)
        if not captions:
            raise SegmoError(f"no caption with words in {root / 'texts'}")
        caption_set = dict.fromkeys(captions)  # ordered set
        all_texts = dict.fromkeys([*caption_set, *read_segments(root, segments)])
        name = encoder.name if isinstance(encoder, TextEncoder) else encoder_folder_name(encoder)
        folder = root / "text_features" / name
        if folder.is_dir():
            remove_temporaries(folder)  # from a killed run; never referenced

        index = _read_index(folder) if (folder / INDEX).is_file() else {"format": FORMAT, "shards": []}
        old = _read_json(folder / META, "text-feature metadata") if (folder / META).is_file() else None
        if old is not None:  # before anything is reused
            if isinstance(encoder, TextEncoder):
                check_encoder(folder, old, encoder.folder, encoder.max_length)
            else:
                source = encoder_source(encoder)
                check_encoder(folder, old, source, encoder_max_length(source))
        have = {t for shard in index["shards"] for t in shard["texts"]}
        have_tokens = {t for shard in index["shards"] for t in shard["token_texts"]}
        todo = [t for t in all_texts if t not in have or (t in caption_set and t not in have_tokens)]
        # similar lengths in a shard keep the encoder's padding small
        todo.sort(key=len, reverse=True)

        if todo:
            if not isinstance(encoder, TextEncoder):
                encoder = _load_encoder(encoder, device)
            # Made once the encoder loads: a bad --encoder or --device leaves no empty folder.
            folder.mkdir(parents=True, exist_ok=True)
            meta = _meta(encoder)
            if old is not None:
                if (old.get("dim"), old.get("kind")) != (meta["dim"], meta["kind"]):
                    raise SegmoError(f"{folder} holds {old.get('kind')} features of dim "
                                     f"{old.get('dim')}, but encoder {encoder!r} gives dim "
                                     f"{meta['dim']}; delete the folder or use another encoder name")
            else:
                _write_json(folder / META, meta)
            if not (folder / INDEX).is_file():  # an empty but valid cache from the start
                _write_json(folder / INDEX, index)
            bar = tqdm(total=len(todo), desc=f"encode-texts [{name}]", unit="text",
                       disable=not progress)
            for first in range(0, len(todo), shard_size):
                chunk = todo[first:first + shard_size]
                _append_shard(folder, index, encoder, chunk, have, caption_set, batch_size)
                bar.update(len(chunk))
            bar.close()

        size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    return CacheSummary(folder=folder, total=len(all_texts), new=len(todo),
                        reused=len(all_texts) - len(todo),
                        seconds=time.perf_counter() - start, bytes_on_disk=size)


def _load_encoder(name: str, device: str) -> TextEncoder:
    """`get_text_encoder`, with its expected failures as one SegmoError line."""
    try:
        torch.device(device)
    except RuntimeError as err:
        raise SegmoError(f"--device {device!r}: not a torch device ({err})") from err
    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise SegmoError(f"--device {device!r}: this torch build sees no CUDA device")
    try:
        return get_text_encoder(name, device=device)
    except (OSError, ImportError, ValueError) as err:
        raise SegmoError(f"--encoder {name!r}: {err}") from err


def _append_shard(folder: Path, index: dict, encoder: TextEncoder, chunk: list[str],
                  have: set[str], captions: dict, batch_size: int) -> None:
    """Encode `chunk`, write one shard, then publish it in index.json (the commit point)."""
    out = encoder.encode(chunk, batch_size=batch_size)
    if out.sentence.shape[1] != encoder.dim:
        raise ValueError(f"encoder {encoder!r} returned width {out.sentence.shape[1]}")
    rows = [i for i, t in enumerate(chunk) if t not in have]
    token_rows = [i for i, t in enumerate(chunk) if t in captions]
    lengths = out.token_mask[token_rows].sum(1).tolist() if token_rows else []
    offsets = np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]).astype(np.int64)
    tokens = out.tokens[token_rows][out.token_mask[token_rows]] if token_rows \
        else torch.zeros(0, encoder.dim)

    stem = f"shard-{len(index['shards']):05d}"
    arrays = {"sentence": out.sentence[rows].numpy().astype(np.float16),
              "tokens": tokens.numpy().astype(np.float16), "offsets": offsets}
    for kind, array in arrays.items():
        with atomic_open(folder / f"{stem}.{kind}.npy", "wb") as f:
            np.save(f, array)
    shard = {"name": stem, "texts": [chunk[i] for i in rows],
             "token_texts": [chunk[i] for i in token_rows]}
    _write_json(folder / INDEX, {**index, "shards": [*index["shards"], shard]})
    index["shards"].append(shard)
    have.update(shard["texts"])


# --------------------------------------------------------------------------- command
def main(argv: list[str] | None = None) -> None:
    """`segmo encode-texts`: build or extend ``DATA/text_features/<encoder>/``."""
    parser = ArgumentParser(
        prog="segmo encode-texts",
        description="Encode every caption and text segment of a dataset once with a frozen "
                    "text encoder and cache the features under DATA/text_features/<encoder>/.")
    parser.add_argument("--data", type=Path, required=True, help="dataset root (holds texts/)")
    parser.add_argument("--encoder", default="minilm",
                        help="minilm (packaged, default), clip, a model directory or hub name")
    parser.add_argument("--segments", nargs="+", metavar="NAME",
                        help="text_segments/ folders to include (default: all present)")
    parser.add_argument("--batch-size", type=positive_int, default=64)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--shard-size", type=positive_int, default=1024, help=argparse.SUPPRESS)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    summary = update_cache(args.data, args.encoder, segments=args.segments,
                           batch_size=args.batch_size, device=args.device,
                           shard_size=args.shard_size, progress=not args.quiet)
    print(summary)


if __name__ == "__main__":
    main()
