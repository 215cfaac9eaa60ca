"""Run directories `runs/<stage>/<name>/version_<k>` and their logs across a resume.

A fresh `segmo fit` takes the next free version. ``--ckpt_path`` pointing into a run
directory (``.../version_<k>/checkpoints/*.ckpt``) at that run's newest state (a step no
earlier than its last.ckpt's) continues that run: the loggers write into the same version
directory, `metrics.csv` keeps the rows the interrupted run logged before the checkpoint's
step and drops the ones after it (the resumed run logs those steps again), and
TensorBoard purges its events from that step on. An older checkpoint of the run
(``--ckpt_path best``, an earlier periodic one) continues in the next free version
instead, so that the run's later checkpoints and logs are kept (`resume_folder`). So that the rows up
to a checkpoint are on disk when a run is killed, `RunCSVLogger` writes every row as it
is logged instead of every 100 steps.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

from lightning.fabric.loggers.csv_logs import _ExperimentWriter
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment
from lightning.pytorch.utilities import rank_zero_info

from segmo.errors import SegmoError
from segmo.export import read_checkpoint
from segmo.files import write_atomic


def checkpoint_run(ckpt_path: str | Path) -> tuple[Path, str, str] | None:
    """(save_dir, name, version) of the run directory holding ``ckpt_path``, or None when
    the checkpoint does not lie in ``SAVE_DIR/NAME/version_<k>/checkpoints/``."""
    path = Path(ckpt_path).resolve()
    run = path.parent.parent
    if path.parent.name != "checkpoints" or not run.name.startswith("version_"):
        return None
    return run.parent.parent, run.parent.name, run.name


def named_checkpoint(run: Path, which: str) -> Path:
    """``--ckpt_path last`` or ``best``: that checkpoint of the newest version of ``run``
    (RUNS_DIR/STAGE/NAME) that has one (Lightning would look only in the new run's own,
    empty, folder, and start from scratch with a warning)."""
    pattern = "last.ckpt" if which == "last" else "best-*.ckpt"
    # ASCII digits, as Lightning writes them: str.isdigit() takes 'version_²', which int()
    # refuses (a ValueError traceback).
    versions = sorted((p for p in run.glob("version_*") if p.name[8:].isascii()
                       and p.name[8:].isdigit()),
                      key=lambda p: int(p.name[8:]), reverse=True)
    for version in versions:
        found = sorted((version / "checkpoints").glob(pattern), key=lambda p: p.stat().st_mtime)
        if found:
            return found[-1]
    raise SegmoError(f"--ckpt_path {which}: no {pattern} in {run}/version_*/checkpoints/ "
                     "(a run of this config and --run_name under --runs_dir)")


def checkpoint_step(ckpt_path: str | Path) -> int:
    """The global step a checkpoint was written at (`read_checkpoint`: checked, memory-mapped)."""
    return read_checkpoint(ckpt_path, "--ckpt_path", resume=True)["global_step"]


def resume_folder(ckpt_path: str | Path) -> tuple[Path, str, str, int | None] | None:
    """(save_dir, name, version, resume step) of the run directory that a fit resumed from
    ``ckpt_path`` writes into, or None when the checkpoint lies in no run directory.

    The checkpoint's own version folder when the checkpoint holds that run's newest state
    (its step is no earlier than the folder's last.ckpt's, or there is none); else the next
    free version beside it, with resume step None (fresh logs): continuing in place from
    an older state would replace the run's last.ckpt and drop its later metrics and
    TensorBoard events."""
    run = checkpoint_run(ckpt_path)
    if run is None:
        return None
    save_dir, name, version = run
    step = checkpoint_step(ckpt_path)
    last = save_dir / name / version / "checkpoints" / "last.ckpt"
    try:
        newest = checkpoint_step(last) if last.is_file() else step
    except SegmoError:  # torn by a kill: which state is newer is unknown; keep both
        newest = step + 1
    if step >= newest:
        return save_dir, name, version, step
    taken = [int(p.name[8:]) for p in (save_dir / name).glob("version_*") if p.name[8:].isdigit()]
    branch = f"version_{max(taken) + 1}"
    rank_zero_info(f"--ckpt_path {ckpt_path}: step {step}, older than {last} (step {newest}); "
                   f"continuing in {save_dir / name / branch}, which keeps {version} as it is")
    return save_dir, name, branch, None


class RunCheckpoint(ModelCheckpoint):
    """`ModelCheckpoint` whose ``last.ckpt`` holds the state at every checkpoint check
    (each validation, or each epoch's end) and at the end of training.

    Lightning up to 2.5 rewrote last.ckpt at every check; 2.6 rewrites it only at a step
    where it also wrote a top-k checkpoint, so with a monitored metric that got worse,
    last.ckpt stayed at the last improvement: `segmo export .../last.ckpt` shipped old
    weights and ``--ckpt_path last`` resumed from there. After Lightning's own saving, this
    writes last.ckpt wherever it was not written at the current step."""

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        due = not self._should_skip_saving_checkpoint(trainer) and \
            not self._should_save_on_train_epoch_end(trainer)
        super().on_validation_end(trainer, pl_module)
        if due:
            self._save_last_if_older(trainer)

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        due = not self._should_skip_saving_checkpoint(trainer) and \
            self._should_save_on_train_epoch_end(trainer)
        super().on_train_epoch_end(trainer, pl_module)
        if due:
            self._save_last_if_older(trainer)

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        super().on_train_end(trainer, pl_module)
        if not self._should_skip_saving_checkpoint(trainer):
            self._save_last_if_older(trainer)

    def _save_last_if_older(self, trainer: Any) -> None:
        # Every save (top-k or last) records its step here, and Lightning writes last.ckpt
        # after each top-k one: an equal step means last.ckpt holds this state already.
        if self._last_global_step_saved != trainer.global_step:
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))


class _ResumedWriter(ExperimentWriter):
    """The metrics writer of a resumed run: keeps the interrupted run's rows before
    ``keep_below`` (instead of deleting the file, as Lightning's writer does)."""

    def __init__(self, log_dir: str, keep_below: int) -> None:
        self._keep_below = keep_below
        super().__init__(log_dir)

    def _check_log_dir_exists(self) -> None:
        path = Path(self.metrics_file_path)
        if not path.is_file():
            return
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            keys, rows = list(reader.fieldnames or []), []
            for row in reader:
                try:  # a row torn by the kill has no parsable step: dropped
                    if int(row.get("step") or "") < self._keep_below and None not in row:
                        rows.append(row)
                except ValueError:
                    continue
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
        write_atomic(path, out.getvalue())
        self.metrics_keys = keys


class RunCSVLogger(CSVLogger):
    """`CSVLogger` that writes each row when logged and, with ``resume_step``, continues
    the metrics of an interrupted run in the same version directory."""

    def __init__(self, save_dir: str | Path, name: str, version: int | str | None = None,
                 resume_step: int | None = None) -> None:
        super().__init__(save_dir, name=name, version=version, flush_logs_every_n_steps=1)
        self._resume_step = resume_step

    @property
    @rank_zero_experiment
    def experiment(self) -> _ExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = (ExperimentWriter(self.log_dir) if self._resume_step is None
                                else _ResumedWriter(self.log_dir, self._resume_step))
        return self._experiment

    def after_save_checkpoint(self, checkpoint_callback: Any) -> None:
        self.save()
