"""Self-describing model directories: `config.json` + `model.safetensors`.

Stages are coupled by a path to such a directory (conventions rule 5). A model class
mixes in `Pretrained`, declares its `kind` and its config dataclass, and is rebuilt from
the directory alone with `from_pretrained`, without a Lightning checkpoint or YAML.

    config.json = {"kind": "rvq", "config": {...dataclass fields...}, "meta": {...},
                   "format": 1, "segmo_version": "0.1.0"}

`from_pretrained` takes a folder or a Hugging Face hub id (`segmo.models.hub`).

`meta` carries what is not a constructor argument but is needed to use the model:
skeleton name, fps, the text encoder a transformer was trained with, and so on.
Normalisation statistics are buffers of the model and live in the safetensors file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, ClassVar

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save

from segmo.errors import SegmoError
from segmo.files import atomic_open, write_atomic
from segmo.models.hub import (
    FORMAT,
    check_format,
    check_repo_id,
    push_folder,
    resolve,
    segmo_version,
)

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"

_REGISTRY: dict[str, type] = {}


def check_config_numbers(config: Any, sizes: tuple[str, ...], shares: tuple[str, ...]) -> None:
    """SegmoError naming the first field of a model config that cannot build a model: a
    size (`sizes`: widths, depths, counts) that is not a whole number >= 1, or a share
    (`shares`: dropout rates, decays) outside [0, 1)."""
    name = type(config).__name__
    for field in sizes:
        value = getattr(config, field)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise SegmoError(f"{name}: {field} must be a whole number >= 1, got {value!r}")
    for field in shares:
        value = getattr(config, field)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < 1:
            raise SegmoError(f"{name}: {field} must be a number in [0, 1), got {value!r}")


class Pretrained:
    """Mixin for `nn.Module`s that save and load themselves as a model directory."""

    kind: ClassVar[str]
    config_class: ClassVar[type]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "kind" in cls.__dict__:
            _REGISTRY[cls.kind] = cls

    def save_pretrained(self, directory: str | os.PathLike, meta: dict | None = None,
                        push_to_hub: bool = False, repo_id: str | None = None,
                        private: bool = False) -> Path:
        """Write `directory` (config.json + model.safetensors); with `push_to_hub`, upload
        it to the hub repository `repo_id` too."""
        if push_to_hub and not repo_id:
            raise SegmoError("save_pretrained: push_to_hub needs repo_id ('owner/name')")
        if push_to_hub:
            check_repo_id(repo_id)
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        with atomic_open(directory / WEIGHTS_FILE, "wb") as f:
            f.write(save(state))
        payload = {
            "kind": self.kind,
            "config": dataclasses.asdict(self.config),
            "meta": {**getattr(self, "meta", {}), **(meta or {})},
            "format": FORMAT,
            "segmo_version": segmo_version(),
        }
        write_atomic(directory / CONFIG_FILE, json.dumps(payload, indent=2) + "\n")
        if push_to_hub:
            push_folder(directory, repo_id, private=private)
        return directory

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, map_location: str = "cpu",
                        revision: str | None = None):
        """Rebuild the model of `directory` (a folder or a hub id; `revision`: the hub's
        branch, tag or commit); SegmoError names the file of any problem (a config that
        does not build this model, weights that are unreadable, do not fit the config or
        hold NaN/inf)."""
        directory = resolve(directory, revision)
        path = Path(directory) / CONFIG_FILE
        payload = read_config(directory)
        if payload["kind"] != cls.kind:
            raise SegmoError(f"{path}: holds a {payload['kind']!r} model, not a {cls.kind!r} model")
        if not isinstance(payload["config"], dict):
            raise SegmoError(f"{path}: 'config' must be an object of {cls.config_class.__name__} "
                             "fields")
        fields = {f.name for f in dataclasses.fields(cls.config_class)}
        unknown = sorted(set(payload["config"]) - fields)
        if unknown:
            raise SegmoError(f"{path}: unknown {cls.kind} config field(s) {unknown} (written by a "
                             "newer segmo, or edited by hand?)")
        try:
            config = cls.config_class(**payload["config"])
            # The weights' shapes are checked against a model without storage first: a
            # config edited to sizes its weights do not have must not take gigabytes.
            with torch.device("meta"):
                shell = cls(config)
        except (TypeError, ValueError, RuntimeError, NotImplementedError) as error:
            raise SegmoError(f"{path}: the config does not build a {cls.kind!r} model: "
                             f"{error}") from None
        check_weight_shapes(directory, {k: tuple(v.shape) for k, v in shell.state_dict().items()},
                            weight_shapes(directory))
        del shell
        model = cls(config).float()  # the weights' float32, whatever torch's default dtype
        model.meta = payload.get("meta", {})
        model.load_state_dict(read_weights(directory, model, map_location))
        return model.to(map_location).eval()


def weight_shapes(directory: str | os.PathLike) -> dict[str, tuple[int, ...]]:
    """The tensor shapes ``DIR/model.safetensors`` records, read from its header alone."""
    path = Path(directory) / WEIGHTS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the model directory has no weights file")
    try:
        with safe_open(str(path), framework="pt") as f:
            return {key: tuple(f.get_slice(key).get_shape()) for key in f.keys()}  # noqa: SIM118 - not a dict
    except (SafetensorError, OSError, ValueError) as error:
        raise SegmoError(f"{path}: not a readable safetensors file ({error})") from None


def check_weight_shapes(directory: str | os.PathLike, expected: dict[str, tuple[int, ...]],
                        found: dict[str, tuple[int, ...]]) -> None:
    """One SegmoError when the weights' tensors (``found``) are not those of the model the
    config builds (``expected``): missing, unexpected or of another shape."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    shapes = [k for k in expected if k in found and found[k] != expected[k]]
    if missing or unexpected or shapes:
        first = (f"{shapes[0]} is {found[shapes[0]]}, the config makes {expected[shapes[0]]}"
                 if shapes else f"e.g. {(missing or unexpected)[0]!r}")
        raise SegmoError(f"{Path(directory) / WEIGHTS_FILE}: the weights do not fit "
                         f"{Path(directory) / CONFIG_FILE}: {len(missing)} missing, "
                         f"{len(unexpected)} unexpected, {len(shapes)} of another shape ({first})")


def read_weights(directory: str | os.PathLike, model: torch.nn.Module,
                 map_location: str = "cpu") -> dict[str, torch.Tensor]:
    """The tensors of ``DIR/model.safetensors``, checked against `model`'s state dict."""
    path = Path(directory) / WEIGHTS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the model directory has no weights file")
    try:
        state = load_file(str(path), device=map_location)
    except (SafetensorError, OSError, ValueError) as error:
        raise SegmoError(f"{path}: not a readable safetensors file ({error})") from None
    check_weight_shapes(directory, {k: tuple(v.shape) for k, v in model.state_dict().items()},
                        {k: tuple(v.shape) for k, v in state.items()})
    broken = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if broken:
        raise SegmoError(f"{path}: {len(broken)} tensor(s) hold NaN or inf (first: {broken[0]!r}); "
                         "the model comes from a diverged run")
    return state


def read_json(path: str | os.PathLike) -> dict:
    """A JSON object from `path`; SegmoError naming the file and line when it is not one."""
    path = Path(path)
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as error:
        raise SegmoError(f"{path}: not UTF-8 text ({error.reason})") from None
    except json.JSONDecodeError as error:
        raise SegmoError(f"{path}:{error.lineno}: not valid JSON ({error.msg})") from None
    except RecursionError:
        raise SegmoError(f"{path}: not a segmo JSON file (nested too deeply to read)") from None
    except ValueError as error:  # e.g. an integer of more than 4300 digits
        raise SegmoError(f"{path}: not a segmo JSON file ({str(error).split(';')[0]})") from None
    if not isinstance(payload, dict):
        raise SegmoError(f"{path}: expected a JSON object, got {type(payload).__name__}")
    return payload


def read_config(directory: str | os.PathLike) -> dict:
    """The payload of ``DIR/config.json``; SegmoError naming the file and key when it lacks
    'kind' or 'config', or 'kind' or 'meta' is of the wrong type."""
    path = Path(directory) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a segmo model directory (no {CONFIG_FILE})")
    payload = read_json(path)
    for key in ("kind", "config"):
        if key not in payload:
            raise SegmoError(f"{path}: missing key {key!r}")
    if not isinstance(payload["kind"], str):
        raise SegmoError(f"{path}: 'kind' must name a model kind, got {payload['kind']!r:.80}")
    if not isinstance(payload.get("meta", {}), dict):
        raise SegmoError(f"{path}: 'meta' must be an object, got {payload['meta']!r:.80}")
    check_format(payload, path)
    return payload


def load_pretrained(directory: str | os.PathLike, map_location: str = "cpu",
                    revision: str | None = None) -> torch.nn.Module:
    """Load any model directory (or hub id), dispatching on the `kind` in its config."""
    directory = resolve(directory, revision)
    kind = read_config(directory)["kind"]
    # Model classes register themselves on import; segmo/models/__init__.py imports them all.
    if kind not in _REGISTRY:
        raise SegmoError(f"{Path(directory) / CONFIG_FILE}: unknown model kind {kind!r}")
    return _REGISTRY[kind].from_pretrained(directory, map_location=map_location)
