"""`segmo fit|validate|test --config configs/<stage>/<dataset>.yaml [--key=value ...]`.

A thin `LightningCLI`: the YAML names the task and the DataModule by `class_path`, so every
stage uses this same entry point. On top of Lightning's defaults it adds

- a run directory `runs/<stage>/<name>/version_<k>` (`--runs_dir`, `--run_name`; stage =
  the task's `stage` attribute, name = the config file's stem) holding the resolved
  `config.yaml`, CSV and TensorBoard logs and `checkpoints/` (`last.ckpt` and the best
  one by the task's `monitor` metric, lower is better);
- a default seed of 0 (`--seed_everything`).

Example: `segmo fit --config configs/rvq/synthetic.yaml --data.root /tmp/c2000`.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

SUBCOMMANDS = ("fit", "validate", "test")


class SegmoCLI(LightningCLI):
    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_argument("--runs_dir", type=str, default="runs", help="root of all run directories")
        parser.add_argument(
            "--run_name", type=str | None, default=None,
            help="run directory name under runs_dir/<stage>/ (default: the config file's stem)",
        )

    @staticmethod
    def subcommands() -> dict[str, set[str]]:
        return {k: v for k, v in LightningCLI.subcommands().items() if k in SUBCOMMANDS}

    def _run_directory(self) -> tuple[Path, str]:
        config = self.config[self.subcommand]
        stage = getattr(self.model, "stage", type(self.model).__name__.lower())
        name = config.get("run_name")
        if not name:
            files = config.get("config") or []
            name = Path(str(files[-1])).stem if files else "default"
        return Path(config.get("runs_dir") or "runs") / stage, name

    def instantiate_trainer(self, **kwargs: Any):
        trainer_config = self._get(self.config_init, "trainer", default={})
        save_dir, name = self._run_directory()
        if trainer_config.get("logger") in (None, True):
            csv = CSVLogger(save_dir, name=name)
            # Both loggers write into the same version directory.
            tensorboard = TensorBoardLogger(
                save_dir, name=name, version=csv.version, default_hp_metric=False
            )
            kwargs["logger"] = [csv, tensorboard]
        if trainer_config.get("default_root_dir") is None:
            kwargs["default_root_dir"] = str(save_dir / name)
        callbacks = list(trainer_config.get("callbacks") or [])
        monitor = getattr(self.model, "monitor", None)
        fitting = self.subcommand == "fit"
        if fitting and not any(isinstance(c, ModelCheckpoint) for c in callbacks):
            callbacks.append(
                ModelCheckpoint(
                    monitor=monitor,
                    mode="min",
                    save_last=True,
                    save_top_k=1,
                    filename="best-{epoch:03d}-{step}" if monitor else "{epoch:03d}-{step}",
                    auto_insert_metric_name=False,
                )
            )
        kwargs["callbacks"] = callbacks
        return super().instantiate_trainer(**kwargs)


def main(argv: list[str] | None = None) -> SegmoCLI:
    """Run `fit`, `validate` or `test`; argv starts with the sub-command. Returns the CLI
    (its `trainer`, `model`, `datamodule`), which tests inspect."""
    if argv and argv[0] not in SUBCOMMANDS and argv[0] not in ("-h", "--help"):
        raise SystemExit(f"segmo.training.cli: expected one of {SUBCOMMANDS}, got {argv[0]!r}")
    with warnings.catch_warnings():
        # Called as `segmo fit ...`, sys.argv holds the same arguments as argv, which
        # LightningCLI would warn about.
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        # The frozen tokenizer inside the token-level tasks is in eval mode on purpose.
        warnings.filterwarnings("ignore", message=r"Found \d+ module\(s\) in eval mode")
        return SegmoCLI(
            args=argv,
            subclass_mode_model=True,
            subclass_mode_data=True,
            seed_everything_default=0,
            # Each run gets its own version directory; a re-run there may rewrite the copy.
            save_config_kwargs={"overwrite": True},
        )


if __name__ == "__main__":
    main()
