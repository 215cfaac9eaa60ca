"""`segmo export CHECKPOINT --out DIR`: a Lightning checkpoint -> a model directory.

Works for every stage: the task class is read from the checkpoint (LightningCLI records it
as `_class_path` in the hyper-parameters) or given with `--task`; the task is rebuilt with
`load_from_checkpoint`, and its `export_model()` (a `Pretrained` module carrying its own
`meta`) is written with `save_pretrained`. Later stages and the pipeline load the
directory with `segmo.models.pretrained.load_pretrained`, without Lightning.

The mask and residual tasks are rebuilt around the exported tokenizer they were trained
with, at the path the checkpoint records (absolute since `segmo fit` resolves it; older
checkpoints name it relative to the folder training ran in); `--tokenizer` names another.
The model directory is written whole (`segmo.files.replacing_folder`); a non-empty `--out`
that holds anything else than such a directory, or a model of another kind, is refused
unless `--overwrite`.

A checkpoint whose tensors are not all finite (a run that diverged) is refused, naming
the tensors; so is a file that is not a checkpoint of `segmo fit`, and a tokenizer that
cannot be found. Each is one line (`SegmoError`), which `segmo export` prints with exit
status 2.

Example: `segmo export runs/rvq/synthetic/version_0/checkpoints/last.ckpt --out models/rvq`
"""

from __future__ import annotations

import importlib
import pickle
from pathlib import Path

import torch

from segmo.errors import ArgumentParser, SegmoError
from segmo.files import foreign_entries, replaced_folder, replacing_folder
from segmo.models.hub import portable_path
from segmo.models.pretrained import CONFIG_FILE, WEIGHTS_FILE, read_config, read_json

SHOWN = 5  # non-finite tensors named in a message


def read_checkpoint(path: str | Path, argument: str = "", resume: bool = False) -> dict:
    """The contents of a checkpoint written by `segmo fit`, or one `SegmoError` naming the
    file (after ``argument``, e.g. "--ckpt_path", when given). With ``resume``, also what
    Lightning needs to resume from it or to score it (its global step and version).

    Read with ``weights_only=True``: tensors and plain values only, so that a file from
    elsewhere cannot run code while it is read (``weights_only=False`` unpickles anything;
    segmo's checkpoints hold nothing else, and Lightning reads them the same way), and
    memory-mapped where the file's format allows, so that checking one reads little."""
    where = f"{argument} {path}" if argument else str(path)
    try:
        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError:  # not in the zip format, which mmap needs
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the user's to fix
        if "GLOBAL" in str(error):  # torch's refusal of a class or function in the pickle
            raise SegmoError(f"{where}: holds Python objects other than tensors and plain values, "
                             "which segmo does not unpickle (they could run code); not a "
                             "checkpoint of `segmo fit`") from None
        detail = ("not a torch file" if isinstance(error, pickle.UnpicklingError)
                  else f"{type(error).__name__}: {(str(error).splitlines() or [''])[0]}")
        raise SegmoError(f"{where}: not a readable checkpoint ({detail})") from None
    if not isinstance(checkpoint, dict):
        raise SegmoError(f"{where}: not a Lightning checkpoint (a {type(checkpoint).__name__}, "
                         "not a dictionary)")
    needed = [("state_dict", dict)]
    if resume:
        needed += [("global_step", int), ("pytorch-lightning_version", str)]
    for key, kind in needed:
        value = checkpoint.get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise SegmoError(f"{where}: not a Lightning checkpoint (no {key})")
    if not isinstance(checkpoint.get("hyper_parameters", {}), dict):
        raise SegmoError(f"{where}: not a checkpoint of `segmo fit` (its hyper_parameters are "
                         "not a dictionary)")
    return checkpoint


def task_class_path(checkpoint: dict, path: str | Path) -> str:
    hparams = checkpoint.get("hyper_parameters") or {}
    class_path = hparams.get("_class_path")
    if not class_path:
        raise SegmoError(
            f"{path}: the checkpoint does not name its task class (it was not written by "
            "`segmo fit`); pass --task, e.g. --task segmo.tasks.tokenizer.RVQTask"
        )
    return class_path


def load_task(path: str | Path, task: str | None = None, map_location: str = "cpu",
              tokenizer: str | Path | None = None):
    """Rebuild the LightningModule saved in checkpoint `path` (class path `task` or recorded;
    a token-level task around the exported tokenizer `tokenizer` or the recorded one)."""
    # Lightning takes seconds to import: kept out of `segmo export --help` and bad arguments.
    from lightning.pytorch import LightningModule

    checkpoint = read_checkpoint(path)
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
    arguments = tokenizer_argument(checkpoint, path, tokenizer)
    try:
        module = cls.load_from_checkpoint(path, map_location=map_location, **arguments)
    except Exception as error:
        # jsonargparse, which rebuilds tasks trained by `segmo fit`, wraps the task's own
        # one-line error (a damaged tokenizer directory) in a page of its attempts.
        inner = error
        while inner is not None and not isinstance(inner, SegmoError):
            inner = inner.__cause__ or inner.__context__
        if inner is None:
            raise
        raise SegmoError(f"{path}: {inner}") from None
    return module, class_path, checkpoint


def tokenizer_argument(checkpoint: dict, path: str | Path, tokenizer: str | Path | None) -> dict:
    """The tokenizer argument to rebuild the task with: {"tokenizer": `tokenizer`} (checked),
    none for the recorded one when it is found; a SegmoError saying which to pass when not."""
    recorded = (checkpoint.get("hyper_parameters") or {}).get("tokenizer")
    if tokenizer is not None:
        if recorded is None:
            raise SegmoError(f"--tokenizer: {path} is a checkpoint of a task without a tokenizer")
        if not (Path(tokenizer) / CONFIG_FILE).is_file():
            raise SegmoError(f"--tokenizer {tokenizer}: not an exported tokenizer directory (no "
                             f"{CONFIG_FILE})")
        return {"tokenizer": str(Path(tokenizer).resolve())}
    if recorded is None or (Path(recorded) / CONFIG_FILE).is_file():
        return {}
    where = ("" if Path(recorded).is_absolute() else
             f" (relative to the folder `segmo fit` ran in, not to {Path.cwd()})")
    raise SegmoError(f"{path}: the tokenizer it was trained with, {recorded}{where}, is not an "
                     f"exported tokenizer directory; pass --tokenizer DIR")


def check_finite(state_dict: dict, path: str | Path) -> None:
    """Refuse a state dict whose floating-point tensors hold NaN or inf, naming them."""
    from segmo.tasks.base import non_finite_tensors  # imports Lightning (seconds), see above

    bad = non_finite_tensors(state_dict)
    if bad:
        more = f" (+{len(bad) - SHOWN} more)" if len(bad) > SHOWN else ""
        raise SegmoError(f"{path}: {len(bad)} of {len(state_dict)} tensors hold NaN/inf: "
                         f"{', '.join(bad[:SHOWN])}{more}; the run diverged; export an earlier "
                         "checkpoint")


def training_data(hparams: dict, resolved_root: str | None = None) -> dict:
    """What a model card says about the training data: the data folder (a portable path),
    its text features and segments, and the built-in corpus' version, seed and size.

    `resolved_root` is the folder as the fit saw it (an absolute path, recorded in the
    checkpoint), read in place of `root` when `root` is relative to another directory."""
    root = hparams.get("root")
    if not root:
        return {}
    data = {"root": portable_path(root)}
    for key in ("text_features", "text_segments", "text_tokens"):
        if hparams.get(key):
            data[key] = hparams[key]
    corpus = Path(resolved_root if isinstance(resolved_root, str) else root) / "corpus.json"
    if corpus.is_file():
        try:
            info = read_json(corpus)
            data["corpus"] = {k: info[k] for k in ("name", "version", "seed", "num_motions") if k in info}
        except (SegmoError, OSError):
            pass  # the card then says less; a broken corpus.json is not the export's business
    return data


def export(checkpoint_path: str | Path, out: str | Path, task: str | None = None,
           tokenizer: str | Path | None = None, overwrite: bool = False) -> Path:
    """Write the model directory of `checkpoint_path` to `out`, replacing it whole; returns
    `out`. Without `overwrite`, a non-empty `out` must be a model directory of the same
    kind holding nothing else (exporting again is fine)."""
    out = Path(out)
    if not overwrite:
        check_replaceable(out)
    module, class_path, checkpoint = load_task(checkpoint_path, task, tokenizer=tokenizer)
    from segmo.tasks.base import DATA_ROOT_KEY  # Lightning is imported by now
    model = module.export_model().eval()
    if not overwrite:
        check_same_kind(out, model.kind)
    meta = {
        "task": class_path,
        "checkpoint": portable_path(checkpoint_path),
        "global_step": int(checkpoint.get("global_step", 0)),
    }
    data = training_data(checkpoint.get("datamodule_hyper_parameters") or {},
                         checkpoint.get(DATA_ROOT_KEY))
    if data:
        meta["data"] = data
    with replacing_folder(out) as tmp:
        model.save_pretrained(tmp, meta=meta)
    return out


def check_replaceable(out: Path) -> None:
    """Refuse an `out` whose replacement by a model directory would delete files: one that
    is not a model directory, or one holding files of the user's besides the model."""
    if out.exists() and not out.is_dir():
        raise SegmoError(f"{out} exists and is not a folder")
    if not out.is_dir() or not any(out.iterdir()):
        return
    try:
        read_config(out)
    except (OSError, SegmoError):
        raise SegmoError(f"{out} is not empty and holds no segmo model ({CONFIG_FILE}); pass "
                         "overwrite=True (--overwrite) to replace it") from None
    extra = foreign_entries(out, [CONFIG_FILE, WEIGHTS_FILE])
    if extra:
        raise SegmoError(f"{out} holds another model and {', '.join(extra)}, which the export "
                         "would delete; pass overwrite=True (--overwrite) or choose another folder")


def check_same_kind(out: Path, kind: str) -> None:
    """Refuse an `out` holding a model of another kind than `kind`: exporting the mask
    checkpoint to `models/rvq` (a slip copying a README line) deleted the tokenizer."""
    if not (out / CONFIG_FILE).is_file():
        return
    existing = read_config(out)["kind"]
    if existing != kind:
        raise SegmoError(f"{out} holds a {existing!r} model; exporting a {kind!r} model there "
                         "would delete it; pass overwrite=True (--overwrite) or choose another "
                         "folder")


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(
        prog="segmo export", description="export a training checkpoint to a model directory"
    )
    parser.add_argument("checkpoint", help="Lightning checkpoint (.ckpt) written by `segmo fit`")
    parser.add_argument("--out", type=replaced_folder, required=True,
                        help="model directory to write")
    parser.add_argument(
        "--task", default=None,
        help="task class path, e.g. segmo.tasks.tokenizer.RVQTask (default: recorded in the checkpoint)",
    )
    parser.add_argument(
        "--tokenizer", default=None,
        help="exported tokenizer of a mask or residual checkpoint (default: the one recorded "
             "in the checkpoint)",
    )
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a folder that holds something else than this model")
    args = parser.parse_args(argv)
    if not Path(args.checkpoint).is_file():
        raise SegmoError(f"{args.checkpoint}: no such checkpoint file")
    print(export(args.checkpoint, args.out, args.task, args.tokenizer, args.overwrite))


if __name__ == "__main__":
    main()
