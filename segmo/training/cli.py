"""`segmo fit|validate|test --config configs/<stage>/<dataset>.yaml [--key=value ...]`.

A thin `LightningCLI`: the YAML names the task and the DataModule by `class_path`, so every
stage uses this same entry point. On top of Lightning's defaults it adds

- a run directory `runs/<stage>/<name>/version_<k>` (`--runs_dir`, `--run_name`; stage =
  the task's `stage` attribute, name = the config file's stem) holding the resolved
  `config.yaml`, CSV and TensorBoard logs and `checkpoints/` (`last.ckpt`, the state at
  the newest validation and at the end of training, and the best one by the task's
  `monitor` metric, lower is better; `segmo.training.runs.RunCheckpoint`);
- exact resume: `segmo fit ... --ckpt_path RUN/checkpoints/last.ckpt` continues in RUN
  (the same version directory; `segmo.training.runs`) with the data order, the loader's
  place in the epoch and the random states of the interrupted run, so it logs the losses
  an uninterrupted run logs (`segmo.data.sampling`, `segmo.tasks.base`); a checkpoint
  older than RUN's last.ckpt (``best``) continues in a new version beside RUN instead;
  ``--ckpt_path last`` / ``best`` name that checkpoint of the run's newest version;
- a checkpoint is read without unpickling code (`segmo.export.read_checkpoint`), and one
  of another task, or a model setting given that differs from the one it records (from
  which Lightning rebuilds the model), is refused, and so is a data setting of a resumed
  fit (`RESUMABLE_DATA` may change); `validate` and `test` need one;
- `--trainer.default_root_dir` is refused: the run directory is set by `--runs_dir` and
  `--run_name`, and Lightning would use default_root_dir only where no logger is given,
  which segmo always gives, so it would be silently ignored;
- one-line errors (`SegmoError`) for a bad config file, key, value or path
  (`segmo.training.config_errors`), which `segmo` prints as ``segmo fit: ...``, exit 2;
- a default seed of 0 (`--seed_everything`);
- ``--trainer.precision auto``: bf16-mixed where the CPU or GPU computes bf16 natively,
  32-true elsewhere (`segmo.training.trainer`);
- ``max_segments`` and ``text_tokens`` stated once, by the data:
  ``data.init_args.max_segments`` (the text segments a sample carries, padded to that many
  slots) and ``data.init_args.text_tokens`` (whether a sample carries the caption's word
  features) are linked to the transformer's ``model.init_args.max_segments`` and
  ``model.init_args.text_tokens``. Configs written before state it for the model too;
  they still run when both agree, and a model value that differs is an error naming its
  place (jsonargparse would silently replace it).

Example: `segmo fit --config configs/rvq/synthetic.yaml --data.root /tmp/c2000`.
"""

from __future__ import annotations

import importlib
import logging
import sys
import warnings
from pathlib import Path
from typing import Any

from jsonargparse import ArgumentError
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from segmo.errors import LARGEST_WHOLE_NUMBER, SegmoError
from segmo.export import read_checkpoint
from segmo.training.config_errors import check_config_files, config_error, where_set
from segmo.training.runs import RunCheckpoint, RunCSVLogger, named_checkpoint, resume_folder
from segmo.training.trainer import SegmoTrainer

SUBCOMMANDS = ("fit", "validate", "test")
# Stated once, by the data, and linked to the transformers (source, target).
# The tokenizer's seed (quantizer dropout, codebook seeding) is the data's (windows): one
# `--data.init_args.seed` trains another tokenizer seed.
LINKS = (("data.init_args.max_segments", "model.init_args.max_segments"),
         ("data.init_args.text_tokens", "model.init_args.text_tokens"),
         ("data.init_args.seed", "model.init_args.seed"))

# Data settings a resumed fit may change: how the same samples are read (num_workers,
# preload), where the corpus lies now (root: moved, or given relative to another folder;
# the checkpoint records nothing of its content to compare), checks that refuse a motion
# rather than change the samples (strict, max_abs_z), and the obsolete unit_length (unset
# and 4 mean the same). Any other changes the batches that the saved loader position
# counts (batch_size, window, seed, max_motions, ...) or, through LINKS, the model.
RESUMABLE_DATA = ("root", "num_workers", "preload", "strict", "max_abs_z", "unit_length")


class SegmoCLI(LightningCLI):
    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_argument("--runs_dir", type=str, default="runs", help="root of all run directories")
        parser.add_argument(
            "--run_name", type=str | None, default=None,
            help="run directory name under runs_dir/<stage>/ (default: the config file's stem)",
        )
        # Applied to the tasks that take them (mask, residual); the others have none.
        for source, target in LINKS:
            parser.link_arguments(source, target)

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        return {k: v for k, v in LightningCLI.subcommands().items() if k in SUBCOMMANDS}

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        super().parse_arguments(parser, args)
        config = self.config.get(self.config.get("subcommand") or "", None)
        if config is None:
            return
        _check_linked(config, list(args or []))
        trainer = config.get("trainer") or {}
        for key in ("val_check_interval", "check_val_every_n_epoch"):
            value = trainer.get(key)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value <= 0:
                # Lightning divides by it at the first validation check
                raise SegmoError(f"--trainer.{key} {value}: expected a number > 0 (or null)")
        for key in ("data.init_args.seed", "model.init_args.seed"):
            value = config.get(key)  # the data's is linked to the model's, built first
            if isinstance(value, int) and not 0 <= value <= LARGEST_WHOLE_NUMBER:
                raise SegmoError(f"{key}={value} must be a whole number from 0 to 2^63 - 1")
        if self.config["subcommand"] == "fit" and trainer.get("limit_train_batches") in (0, 0.0):
            raise SegmoError("--trainer.limit_train_batches 0: trains nothing (and writes no "
                             "checkpoint); give a number > 0")
        seed = config.get("seed_everything")
        if isinstance(seed, int) and not isinstance(seed, bool) and not 0 <= seed <= 2**32 - 1:
            # numpy's global seed, which Lightning sets too, is 32 bits
            raise SegmoError(f"--seed_everything {seed}: expected a whole number from 0 to "
                             "4294967295 (or true for a random one)")
        if config.get("trainer", {}).get("default_root_dir") is not None:
            raise SegmoError(
                "--trainer.default_root_dir is not used by segmo: the run directory is "
                "RUNS_DIR/STAGE/RUN_NAME/version_K; set --runs_dir (and --run_name) instead")
        if not config.get("model") or not config["model"].get("class_path"):
            return  # Lightning says that a model is needed
        task = _task_class(config)
        run = _run_folder(config, task)
        ckpt_path = config.get("ckpt_path")
        if ckpt_path is None:
            return  # `validate` and `test` need one: `instantiate_trainer`, after the data
        if ckpt_path in ("last", "best"):
            ckpt_path = str(named_checkpoint(run, ckpt_path))
            config["ckpt_path"] = ckpt_path
        elif not Path(ckpt_path).is_file():
            raise SegmoError(f"--ckpt_path {ckpt_path}: no such checkpoint file (give a file, "
                             f"or 'last' or 'best' of the run in {run})")
        checkpoint = read_checkpoint(ckpt_path, "--ckpt_path", resume=True)
        _check_checkpoint_task(checkpoint, ckpt_path, config, task, list(args or []),
                               resuming=self.config["subcommand"] == "fit")
        if self.config["subcommand"] == "fit":
            _check_checkpoint_data(checkpoint, ckpt_path, config, list(args or []))

    def _run_directory(self) -> tuple[Path, str, str | None, int | None]:
        """(save_dir, name, version or None for the next free one, resume step or None)."""
        config = self.config[self.subcommand]
        ckpt_path = config.get("ckpt_path")
        if self.subcommand == "fit" and ckpt_path and Path(ckpt_path).is_file():
            folder = resume_folder(ckpt_path)
            if folder is not None:
                return folder
        folder = _run_folder(config, type(self.model))
        return folder.parent, folder.name, None, None

    def instantiate_trainer(self, **kwargs: Any):
        if self.datamodule is not None:
            # Read and check the data (values, text features) before the Trainer prints its
            # banners, so that a refused dataset is the only thing the user sees.
            self.datamodule.setup(self.subcommand)
        if self.subcommand != "fit" and self.config[self.subcommand].get("ckpt_path") is None:
            run = _run_folder(self.config[self.subcommand], type(self.model))
            raise SegmoError(f"--ckpt_path is needed: {self.subcommand} scores the model of a "
                             f"checkpoint (a file, or 'last' or 'best' of the run in {run}); "
                             "without one it would score an untrained model")
        check = getattr(self.model, "check_before_training", None)
        if check is not None:
            check(self.datamodule)  # before the Trainer's banners, as the data's checks
        trainer_config = self._get(self.config_init, "trainer", default={})
        save_dir, name, version, resume_step = self._run_directory()
        if resume_step is not None:
            # The run's config.yaml keeps the settings it started with, which its checkpoints
            # match; the resumed command's (a later max_steps, its ckpt_path) goes beside it.
            self.save_config_kwargs = {**self.save_config_kwargs,
                                       "config_filename": f"config-resumed-at-{resume_step}.yaml"}
        if trainer_config.get("logger") in (None, True):
            csv = RunCSVLogger(save_dir, name=name, version=version, resume_step=resume_step)
            # Both loggers write into the same version directory.
            tensorboard = TensorBoardLogger(save_dir, name=name, version=csv.version,
                                            default_hp_metric=False, purge_step=resume_step)
            kwargs["logger"] = [csv, tensorboard]
        kwargs["default_root_dir"] = str(save_dir / name)
        callbacks = list(trainer_config.get("callbacks") or [])
        monitor = getattr(self.model, "monitor", None)
        fitting = self.subcommand == "fit"
        if fitting and not any(isinstance(c, ModelCheckpoint) for c in callbacks):
            callbacks.append(
                RunCheckpoint(  # last.ckpt: the newest state, whether the metric improved or not
                    monitor=monitor,
                    mode="min",
                    save_last=True,
                    save_top_k=1,
                    # A resumed run overwrites last.ckpt (the file `segmo export` is given)
                    # instead of writing last-v1.ckpt beside the stale one: one run per folder.
                    enable_version_counter=False,
                    filename="best-{epoch:03d}-{step}" if monitor else "{epoch:03d}-{step}",
                    auto_insert_metric_name=False,
                )
            )
        kwargs["callbacks"] = callbacks
        return super().instantiate_trainer(**kwargs)


def _task_class(config: Any) -> type:
    """The task class the parsed ``config`` names (its ``model.class_path``; jsonargparse
    has imported it already)."""
    module, _, name = str(config["model"]["class_path"]).rpartition(".")
    return getattr(importlib.import_module(module), name)


def _run_folder(config: Any, task: type) -> Path:
    """RUNS_DIR/STAGE/RUN_NAME, absolute (stage: the task's `stage`; name: --run_name, else
    the last config file's stem). Absolute, as a resumed run's folder is (`checkpoint_run`):
    Lightning compares the checkpoint folder stored in a checkpoint with its own, and on a
    mismatch it forgets which file is last.ckpt."""
    name = config.get("run_name")
    if not name:
        files = config.get("config") or []
        name = Path(str(files[-1])).stem if files else "default"
    elif name in (".", "..") or Path(name).name != name:
        raise SegmoError(f"--run_name {name!r}: a folder name (no '/' or '..'); the run folder "
                         "is RUNS_DIR/STAGE/RUN_NAME")
    runs_dir = Path(config.get("runs_dir") or "runs")
    if runs_dir.exists() and not runs_dir.is_dir():
        raise SegmoError(f"--runs_dir {runs_dir}: exists and is not a directory")
    stage = getattr(task, "stage", task.__name__.lower())
    return runs_dir.resolve() / stage / name


def _check_checkpoint_task(checkpoint: dict, ckpt_path: str, config: Any, task: type,
                           argv: list[str], resuming: bool) -> None:
    """A checkpoint of another task than the config's, or a model setting given that differs
    from the checkpoint's (on the command line, or when ``resuming`` a fit in a config file
    too: validating with another recipe's file is common and changes nothing): one
    SegmoError. Lightning builds the model from the settings a checkpoint records (they
    replace the config's), so either would silently train or score another model than the
    one asked for."""
    hparams = checkpoint.get("hyper_parameters") or {}
    recorded = hparams.get("_class_path")
    if recorded:
        try:
            same = _task_class({"model": {"class_path": recorded}}) is task
        except (ImportError, AttributeError, ValueError):
            same = False
        if not same:
            raise SegmoError(
                f"--ckpt_path {ckpt_path}: a checkpoint of {recorded}, but the config trains "
                f"{config['model']['class_path']}; give a checkpoint of this stage")
    given = config["model"].get("init_args") or {}
    for key, saved in hparams.items():
        if key.startswith("_") or key not in given:
            continue
        places = [place for place, _ in where_set(f"model.init_args.{key}", argv)
                  if resuming or place.startswith("argument ")]
        if places and _setting(key, given[key]) != _setting(key, saved):
            advice = "leave it as it was, or start a new run" if resuming else "leave it out"
            raise SegmoError(
                f"{places[0]}: model.init_args.{key}={given[key]!r}, but --ckpt_path "
                f"{ckpt_path} was trained with {saved!r}, and the model is built from its "
                f"checkpoint's settings; {advice}")


def _check_checkpoint_data(checkpoint: dict, ckpt_path: str, config: Any, argv: list[str]) -> None:
    """A data setting of a resumed fit that differs from the one its checkpoint records
    (other than those of `RESUMABLE_DATA`): one SegmoError naming where it is set. The
    saved loader position counts batches of the recorded order, and the linked settings
    (`LINKS`) would change the model that the checkpoint's weights are loaded into (a
    size-mismatch traceback) or its seed."""
    saved = checkpoint.get("datamodule_hyper_parameters") or {}
    given = (config.get("data") or {}).get("init_args") or {}
    for key, recorded in saved.items():
        if key.startswith("_") or key in RESUMABLE_DATA or key not in given:
            continue
        if _setting(key, given[key]) != _setting(key, recorded):
            where = (where_set(f"data.init_args.{key}", argv) or [("data.init_args", None)])[0][0]
            raise SegmoError(
                f"{where}: data.init_args.{key}={given[key]!r}, but --ckpt_path {ckpt_path} "
                f"was trained with {recorded!r}; a resumed run continues its checkpoint's data "
                "order and model, so leave it as it was, or start a new run")


def _setting(key: str, value: Any) -> Any:
    """A model setting in a form that compares as the user means it: sequences as lists,
    the tokenizer as an absolute path."""
    if isinstance(value, (list, tuple)):
        return [_setting(key, v) for v in value]
    if key == "tokenizer" and isinstance(value, str):
        return str(Path(value).resolve())
    return value


def _check_linked(config: Any, argv: list[str]) -> None:
    """A value given for a link's target (configs written before the link) that is not
    the linked one: one `SegmoError` naming where it is set."""
    for source, target in LINKS:
        linked = config.get(target)
        if linked is None:
            continue
        name = target.rsplit(".", 1)[-1]
        for where, given in where_set(target, argv):
            if given is not None and given.strip() != str(linked):
                raise SegmoError(f"{where}: {target}={given.strip()}, but the model takes "
                                 f"{name} from {source} ({linked}); set that one instead")


def _segmo_error(error: BaseException) -> SegmoError | None:
    """The `SegmoError` that ``error`` wraps and quotes (jsonargparse does so with errors
    raised while it builds the task or the DataModule), or Lightning's own refusal of a
    trainer setting (``--trainer.max_steps -5``) as one; else None."""
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    inner, seen = error, 0
    while inner is not None and seen < 10:
        if isinstance(inner, SegmoError):
            return inner if inner is error or str(inner) in str(error) else None
        if isinstance(inner, MisconfigurationException):
            return SegmoError(f"trainer: {inner}")
        inner, seen = inner.__cause__ or inner.__context__, seen + 1
    return None


def main(argv: list[str] | None = None) -> SegmoCLI:
    """Run `fit`, `validate` or `test`; argv starts with the sub-command. Returns the CLI
    (its `trainer`, `model`, `datamodule`), which tests inspect. Expected failures raise
    `SegmoError` with a one-line message."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] not in SUBCOMMANDS and argv[0] not in ("-h", "--help"):
        raise SegmoError(f"segmo.training.cli: expected one of {SUBCOMMANDS}, got {argv[0]!r}")
    check_config_files(argv)
    # "Seed set to 0" would be the first of two lines of every error; config.yaml records it.
    logging.getLogger("lightning.fabric.utilities.seed").setLevel(logging.WARNING)
    with warnings.catch_warnings():
        # Called as `segmo fit ...`, sys.argv holds the same arguments as argv, which
        # LightningCLI would warn about.
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        # The frozen tokenizer inside the token-level tasks is in eval mode on purpose.
        warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode")
        try:
            return SegmoCLI(
                args=argv,
                trainer_class=SegmoTrainer,
                subclass_mode_model=True,
                subclass_mode_data=True,
                seed_everything_default=0,
                # Each run gets its own version directory; a re-run there may rewrite the copy.
                save_config_kwargs={"overwrite": True},
                # Parse errors raise (and become one line below) instead of printing usage.
                parser_kwargs={"exit_on_error": False},
            )
        except ArgumentError as error:
            raise config_error(str(error), argv) from None
        except Exception as error:
            found = _segmo_error(error)
            if found is None or found is error:
                raise
            raise found from None


if __name__ == "__main__":
    main()
