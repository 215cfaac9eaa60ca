"""`segmo export CHECKPOINT --out DIR`: a Lightning checkpoint -> a model directory.

Works for every stage: the task class is read from the checkpoint (LightningCLI records it
as `_class_path` in the hyper-parameters) or given with `--task`; the task is rebuilt with
`load_from_checkpoint`, and its `export_model()` (a `Pretrained` module carrying its own
`meta`) is written with `save_pretrained`. Later stages and the pipeline load the
directory with `segmo.models.pretrained.load_pretrained`, without Lightning.

A checkpoint whose tensors are not all finite (a run that diverged) is refused, naming
the tensors; so is a file that is not a checkpoint of `segmo fit`. Each is one line
(`SegmoError`), which `segmo export` prints with exit status 2.

Example: `segmo export runs/rvq/synthetic/version_0/checkpoints/last.ckpt --out models/rvq`
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import torch

from segmo.errors import ArgumentParser, SegmoError
from segmo.models.hub import portable_path

SHOWN = 5  # non-finite tensors named in a message


def task_class_path(checkpoint: dict, path: str | Path) -> str:
    hparams = checkpoint.get("hyper_parameters") or {}
    class_path = hparams.get("_class_path")
    if not class_path:
        raise SegmoError(
            f"{path}: the checkpoint does not name its task class (it was not written by "
            "`segmo fit`); pass --task, e.g. --task segmo.tasks.tokenizer.RVQTask"
        )
    return class_path


def load_task(path: str | Path, task: str | None = None, map_location: str = "cpu"):
    """Rebuild the LightningModule saved in checkpoint `path` (class path `task` or recorded)."""
    # Lightning takes seconds to import: kept out of `segmo export --help` and bad arguments.
    from lightning.pytorch import LightningModule

    # Our own checkpoints hold hyper-parameters and generator states, not just tensors.
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the user's to fix
        raise SegmoError(f"{path}: not a readable checkpoint ({type(error).__name__}: {error})") from None
    if not isinstance(checkpoint, dict) or not isinstance(checkpoint.get("state_dict"), dict):
        raise SegmoError(f"{path}: not a Lightning checkpoint (no state_dict)")
    check_finite(checkpoint["state_dict"], path)
    class_path = task or task_class_path(checkpoint, path)
    module_name, _, class_name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError, ValueError) as error:
        raise SegmoError(f"--task / checkpoint class {class_path!r} cannot be imported: {error}") from None
    if not (isinstance(cls, type) and issubclass(cls, LightningModule)):
        raise SegmoError(f"{class_path!r} is not a LightningModule")
    if not hasattr(cls, "export_model"):
        raise SegmoError(f"{class_path!r} has no export_model(); it cannot be exported")
    return cls.load_from_checkpoint(path, map_location=map_location), class_path, checkpoint


def check_finite(state_dict: dict, path: str | Path) -> None:
    """Refuse a state dict whose floating-point tensors hold NaN or inf, naming them."""
    from segmo.tasks.base import non_finite_tensors  # imports Lightning (seconds), see above

    bad = non_finite_tensors(state_dict)
    if bad:
        more = f" (+{len(bad) - SHOWN} more)" if len(bad) > SHOWN else ""
        raise SegmoError(f"{path}: {len(bad)} of {len(state_dict)} tensors hold NaN/inf: "
                         f"{', '.join(bad[:SHOWN])}{more}; the run diverged; export an earlier "
                         "checkpoint")


def training_data(hparams: dict) -> dict:
    """What a model card says about the training data: the data folder (a portable path),
    its text features and segments, and the built-in corpus' version, seed and size."""
    root = hparams.get("root")
    if not root:
        return {}
    data = {"root": portable_path(root)}
    for key in ("text_features", "text_segments", "text_tokens"):
        if hparams.get(key):
            data[key] = hparams[key]
    corpus = Path(root) / "corpus.json"
    if corpus.is_file():
        try:
            info = json.loads(corpus.read_text())
            data["corpus"] = {k: info[k] for k in ("name", "version", "seed", "num_motions") if k in info}
        except (ValueError, OSError):
            pass  # the card then says less; a broken corpus.json is not the export's business
    return data


def export(checkpoint_path: str | Path, out: str | Path, task: str | None = None) -> Path:
    """Write the model directory of `checkpoint_path` to `out`; returns `out`."""
    module, class_path, checkpoint = load_task(checkpoint_path, task)
    model = module.export_model().eval()
    meta = {
        "task": class_path,
        "checkpoint": portable_path(checkpoint_path),
        "global_step": int(checkpoint.get("global_step", 0)),
    }
    data = training_data(checkpoint.get("datamodule_hyper_parameters") or {})
    if data:
        meta["data"] = data
    return model.save_pretrained(out, meta=meta)


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo export", description="export a training checkpoint to a model directory"
    )
    parser.add_argument("checkpoint", help="Lightning checkpoint (.ckpt) written by `segmo fit`")
    parser.add_argument("--out", required=True, help="model directory to write")
    parser.add_argument(
        "--task", default=None,
        help="task class path, e.g. segmo.tasks.tokenizer.RVQTask (default: recorded in the checkpoint)",
    )
    args = parser.parse_args(argv)
    if not Path(args.checkpoint).is_file():
        raise SegmoError(f"{args.checkpoint}: no such checkpoint file")
    print(export(args.checkpoint, args.out, args.task))


if __name__ == "__main__":
    main()
