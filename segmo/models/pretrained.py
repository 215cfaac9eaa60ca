"""Self-describing model directories: `config.json` + `model.safetensors`.

Stages are coupled by a path to such a directory (conventions rule 5). A model class
mixes in `Pretrained`, declares its `kind` and its config dataclass, and is rebuilt from
the directory alone with `from_pretrained`, without a Lightning checkpoint or YAML.

    config.json = {"kind": "rvq", "config": {...dataclass fields...}, "meta": {...}}

`meta` carries what is not a constructor argument but is needed to use the model:
skeleton name, fps, the text encoder a transformer was trained with, and so on.
Normalisation statistics are buffers of the model and live in the safetensors file.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any, ClassVar

import torch
from safetensors.torch import load_file, save_file

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"

_REGISTRY: dict[str, type] = {}


def _atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


class Pretrained:
    """Mixin for `nn.Module`s that save and load themselves as a model directory."""

    kind: ClassVar[str]
    config_class: ClassVar[type]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "kind" in cls.__dict__:
            _REGISTRY[cls.kind] = cls

    def save_pretrained(self, directory: str | os.PathLike, meta: dict | None = None) -> Path:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{WEIGHTS_FILE}.")
        os.close(fd)
        save_file(state, tmp)
        os.replace(tmp, directory / WEIGHTS_FILE)
        payload = {
            "kind": self.kind,
            "config": dataclasses.asdict(self.config),
            "meta": {**getattr(self, "meta", {}), **(meta or {})},
        }
        _atomic_write_text(directory / CONFIG_FILE, json.dumps(payload, indent=2) + "\n")
        return directory

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, map_location: str = "cpu"):
        payload = read_config(directory)
        if payload["kind"] != cls.kind:
            raise ValueError(
                f"{Path(directory) / CONFIG_FILE}: holds a {payload['kind']!r} model, "
                f"not a {cls.kind!r} model"
            )
        model = cls(cls.config_class(**payload["config"]))
        model.meta = payload.get("meta", {})
        state = load_file(str(Path(directory) / WEIGHTS_FILE), device=map_location)
        model.load_state_dict(state)
        return model.to(map_location).eval()


def read_config(directory: str | os.PathLike) -> dict:
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a segmo model directory (no {CONFIG_FILE})")
    payload = json.loads(path.read_text())
    for key in ("kind", "config"):
        if key not in payload:
            raise ValueError(f"{path}: missing key {key!r}")
    return payload


def load_pretrained(directory: str | os.PathLike, map_location: str = "cpu") -> torch.nn.Module:
    """Load any model directory, dispatching on the `kind` recorded in its config."""
    kind = read_config(directory)["kind"]
    if kind not in _REGISTRY:
        # Model classes register themselves on import.
        import segmo.models.registry  # noqa: F401
    if kind not in _REGISTRY:
        raise ValueError(f"{Path(directory) / CONFIG_FILE}: unknown model kind {kind!r}")
    return _REGISTRY[kind].from_pretrained(directory, map_location=map_location)
