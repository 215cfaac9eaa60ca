"""Training stage 1: the residual VQ-VAE tokenizer (spec §3; `configs/rvq/`, stage "rvq").

Loss = SmoothL1(reconstruction) + position_weight · SmoothL1 on the root-relative joint
positions + root_weight · SmoothL1 on the root's four features (angular velocity, linear
velocity, height) + commitment_weight · commitment. The root term is not MoMask's (its
default 0 keeps the reference's loss): in the plain average the root is 4 of 263 features,
and a tokenizer trained without it keeps a leap's pose but loses much of its forward
velocity (docs/quality.md, "The tokenizer's root"). The DataModule provides z-scored motions
(random windows in training, whole masked clips in validation), the normalisation
statistics, which are copied into the model so that the exported directory is
self-sufficient, and the skeleton, which must match the task's.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor

from segmo.models.tokenizer import RVQVAE, RVQConfig, RVQOutput
from segmo.motion.features import features_to_joints, joint_errors
from segmo.motion.skeleton import SkeletonName, get_skeleton
from segmo.tasks.base import Task


class RVQTask(Task):
    """Trains `RVQVAE` on batches {"motion" (b, t, d) z-scored, "mask" (b, t) bool}."""

    stage: ClassVar[str] = "rvq"
    monitor: ClassVar[str] = "val/mpjpe_mm"

    def __init__(
        self,
        skeleton: SkeletonName = "t2m",
        width: int = 512,
        code_dim: int = 512,
        depth: int = 3,
        dilation_growth: int = 3,
        dropout: float = 0.2,
        codebook_size: int = 512,
        num_quantizers: int = 6,
        quantizer_dropout: float = 0.2,
        ema_decay: float = 0.99,
        dead_code_threshold: float = 1.0,
        lr: float = 2e-4,
        betas: tuple[float, float] = (0.9, 0.99),
        weight_decay: float = 0.0,
        warmup_steps: int = 2000,
        milestones: list[int] = [150_000, 250_000],  # noqa: B006 - jsonargparse needs a plain default
        gamma: float = 0.05,
        position_weight: float = 0.5,
        root_weight: float = 0.0,
        commitment_weight: float = 0.02,
        seed: int = 0,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.skeleton = get_skeleton(skeleton)
        self.model = RVQVAE(
            RVQConfig(
                feature_dim=self.skeleton.feature_dim,
                width=width,
                code_dim=code_dim,
                depth=depth,
                dilation_growth=dilation_growth,
                dropout=dropout,
                codebook_size=codebook_size,
                num_quantizers=num_quantizers,
                quantizer_dropout=quantizer_dropout,
                ema_decay=ema_decay,
                dead_code_threshold=dead_code_threshold,
            )
        )
        # Drives quantizer dropout and codebook (re-)seeding; saved in checkpoints.
        self.generator = torch.Generator().manual_seed(seed)

    # -- set-up ------------------------------------------------------------------------------

    def setup(self, stage: str) -> None:
        datamodule = self.datamodule
        if datamodule is None:
            return
        self.check_skeleton()
        # Ranks draw different windows; offset the generator so they also differ in what
        # they would pick (rank 0's picks are the ones broadcast).
        self.generator.manual_seed(self.hparams.seed + self.global_rank)
        if stage == "fit":
            # A resumed run then overwrites these with the checkpoint's (identical) buffers.
            self.model.set_statistics(
                torch.as_tensor(datamodule.mean, dtype=torch.float32),
                torch.as_tensor(datamodule.std, dtype=torch.float32),
            )

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["rvq_generator_state"] = self.generator.get_state()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        if "rvq_generator_state" in checkpoint:
            self.generator.set_state(checkpoint["rvq_generator_state"])

    # -- losses ------------------------------------------------------------------------------

    def losses(self, motion: Tensor, out: RVQOutput, mask: Tensor) -> dict[str, Tensor]:
        """Named loss terms over the valid frames of motion (b, t, d), mask (b, t)."""
        parts = self.skeleton.feature_slices()
        positions, root = parts["positions"], parts["root"]
        target, prediction = motion[mask], out.reconstruction[mask]  # (frames, d)
        terms = {
            "recon": F.smooth_l1_loss(prediction, target),
            "positions": F.smooth_l1_loss(prediction[:, positions], target[:, positions]),
            "root": F.smooth_l1_loss(prediction[:, root], target[:, root]),
            "commitment": out.commitment_loss,
        }
        h = self.hparams
        terms["loss"] = (
            terms["recon"] + h.position_weight * terms["positions"] + h.root_weight * terms["root"]
            + h.commitment_weight * terms["commitment"]
        )
        return terms

    def _forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, RVQOutput]:
        motion = batch["motion"]
        mask = batch.get("mask")
        if mask is None:
            mask = torch.ones(motion.shape[:2], dtype=torch.bool, device=motion.device)
        return motion, mask, self.model(motion, mask=mask, generator=self.generator)

    def _log_codebooks(self, prefix: str, out: RVQOutput, **kwargs: Any) -> None:
        for layer in range(self.model.num_quantizers):
            if math.isnan(float(out.perplexity[layer])):
                continue  # layer dropped for this batch
            self.log(f"{prefix}/perplexity_q{layer}", out.perplexity[layer], **kwargs)
            self.log(f"{prefix}/code_usage_q{layer}", out.code_usage[layer], **kwargs)

    # -- steps -------------------------------------------------------------------------------

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        motion, mask, out = self._forward(batch)
        terms = self.losses(motion, out, mask)
        b = motion.shape[0]
        loss = terms.pop("loss")
        self.log("train/loss", loss, prog_bar=True, batch_size=b)
        self.log_dict({f"train/{k}": v for k, v in terms.items()}, batch_size=b)
        self.log("train/lr", self.trainer.optimizers[0].param_groups[0]["lr"], batch_size=b)
        self._log_codebooks("train", out, batch_size=b)
        return loss

    def _evaluate(self, prefix: str, batch: dict[str, Tensor]) -> None:
        motion, mask, out = self._forward(batch)
        terms = self.losses(motion, out, mask)
        frames = int(mask.sum())
        self.log_dict({f"{prefix}/{k}": v for k, v in terms.items()}, batch_size=frames, sync_dist=True)
        errors = self.mpjpe_mm(motion, out.reconstruction, mask)
        self.log(f"{prefix}/mpjpe_mm", errors.pop("mpjpe_mm"), prog_bar=True, batch_size=frames,
                 sync_dist=True)
        self.log_dict({f"{prefix}/{k}": v for k, v in errors.items()}, batch_size=frames, sync_dist=True)
        self._log_codebooks(prefix, out, batch_size=frames, sync_dist=True)

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate("val", batch)

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate("test", batch)

    def mpjpe_mm(self, motion: Tensor, reconstruction: Tensor, mask: Tensor) -> dict[str, Tensor]:
        """Joint position errors (mm) over valid frames of z-scored (b, t, d) features.

        "mpjpe_mm" aligns the root joints of each frame first, as MoMask's evaluation does
        (pose error); "mpjpe_global_mm" keeps the root trajectory integrated from the
        velocity features, so its drift counts as well.
        """
        real = features_to_joints(self.model.denormalize(motion.float()), self.skeleton)
        fake = features_to_joints(self.model.denormalize(reconstruction.float()), self.skeleton)
        to_mm = self.skeleton.unit * 1000.0
        aligned, drift = joint_errors(real, fake)  # (b, t) each
        return {"mpjpe_mm": aligned[mask].mean() * to_mm, "mpjpe_global_mm": drift[mask].mean() * to_mm}

    # -- export ------------------------------------------------------------------------------

    def export_model(self) -> RVQVAE:
        self.model.meta = {"skeleton": self.skeleton.name, "fps": self.skeleton.fps}
        return self.model
