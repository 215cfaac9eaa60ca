"""The motion tokenizer (`RVQVAE`): a 1-D convolutional auto-encoder around a residual
quantizer (`segmo.models.quantizer`).

Features (b, t, d) -> encoder (4x temporal downsampling) -> residual quantizer ->
decoder (4x nearest upsampling) -> features (b, t, d). Numbers follow MoMask (spec §3).
Model directories record it as kind "rvq"; it is trained by `segmo.tasks.tokenizer`
(`configs/rvq/`, run directories `runs/rvq/`) and a bundle keeps it in `tokenizer/`.

    >>> model = RVQVAE(RVQConfig(feature_dim=263, width=64, code_dim=32, codebook_size=16))
    >>> indices = model.encode(torch.randn(2, 64, 263))   # (2, 16, 6)
    >>> model.decode(indices).shape
    torch.Size([2, 64, 263])

A batch of motions of different lengths is encoded and decoded with `lengths`: each motion
at its own length, so that its latents and decoded frames are the same alone and beside a
longer one (`run_at_lengths`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from segmo.models.dropout import Dropout
from segmo.models.pretrained import Pretrained, check_config_numbers
from segmo.models.quantizer import ResidualQuantizer

# The encoder halves the frame rate this many times (a stride-2 convolution each), the
# decoder doubles it as often.
STRIDE_STAGES = 2
# Frames per motion token: token length n = t // FRAMES_PER_TOKEN. The one definition;
# data cropping, lengths, token spans and the length classes all read it.
FRAMES_PER_TOKEN = 2**STRIDE_STAGES


@dataclass
class RVQConfig:
    feature_dim: int
    width: int = 512
    code_dim: int = 512
    depth: int = 3  # residual blocks per resolution
    dilation_growth: int = 3  # dilations growth**(depth-1), ..., 1 in the encoder
    dropout: float = 0.2  # inside the residual blocks
    codebook_size: int = 512
    num_quantizers: int = 6
    quantizer_dropout: float = 0.2
    ema_decay: float = 0.99
    dead_code_threshold: float = 1.0

    def __post_init__(self) -> None:
        check_config_numbers(self, ("feature_dim", "width", "code_dim", "depth", "dilation_growth",
                                    "codebook_size", "num_quantizers"),
                             ("dropout", "quantizer_dropout", "ema_decay"))


@dataclass
class RVQOutput:
    """What `RVQVAE.forward` returns.

    reconstruction: (b, t, d) z-scored features.
    indices: (b, n, q) long, −1 for layers dropped by quantizer dropout.
    commitment_loss: () mean over kept layers.
    perplexity: (q,) per-layer code perplexity of the batch, NaN for dropped layers.
    code_usage: (q,) per-layer fraction of codes used in the batch, NaN if dropped.
    """

    reconstruction: Tensor
    indices: Tensor
    commitment_loss: Tensor
    perplexity: Tensor
    code_usage: Tensor


class ResidualBlock(nn.Module):
    """x + dropout(conv_k1(relu(dilated_conv_k3(relu(x))))), length-preserving."""

    def __init__(self, width: int, dilation: int, dropout: float) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.ReLU(),
            nn.Conv1d(width, width, 3, padding=dilation, dilation=dilation),
            nn.ReLU(),
            nn.Conv1d(width, width, 1),
            Dropout(dropout),
        )

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


def _resnet(width: int, dilations: list[int], dropout: float) -> nn.Sequential:
    return nn.Sequential(*(ResidualBlock(width, d, dropout) for d in dilations))


class Encoder(nn.Module):
    """(b, d, t) -> (b, code_dim, t // 4)."""

    def __init__(self, config: RVQConfig) -> None:
        super().__init__()
        width = config.width
        # Largest dilation first: wide context before the fine detail, as in MoMask.
        dilations = [config.dilation_growth**i for i in reversed(range(config.depth))]
        layers: list[nn.Module] = [nn.Conv1d(config.feature_dim, width, 3, padding=1), nn.ReLU()]
        for _ in range(STRIDE_STAGES):
            layers += [nn.Conv1d(width, width, 4, stride=2, padding=1), _resnet(width, dilations, config.dropout)]
        layers.append(nn.Conv1d(width, config.code_dim, 3, padding=1))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x)


class Decoder(nn.Module):
    """(b, code_dim, n) -> (b, d, 4 n); the encoder in reverse."""

    def __init__(self, config: RVQConfig) -> None:
        super().__init__()
        width = config.width
        dilations = [config.dilation_growth**i for i in range(config.depth)]
        layers: list[nn.Module] = [nn.Conv1d(config.code_dim, width, 3, padding=1), nn.ReLU()]
        for _ in range(STRIDE_STAGES):
            layers += [
                _resnet(width, dilations, config.dropout),
                nn.Upsample(scale_factor=2, mode="nearest"),
                nn.Conv1d(width, width, 3, padding=1),
            ]
        layers += [
            nn.Conv1d(width, width, 3, padding=1),
            nn.ReLU(),
            nn.Conv1d(width, config.feature_dim, 3, padding=1),
        ]
        self.layers = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x)


def run_at_lengths(net: nn.Module, x: Tensor, lengths: Tensor, out_steps: int) -> Tensor:
    """net over x (b, c, s), each sample cut to its own length first → (b, c', out_steps),
    zero past each sample's output. lengths (b,) in steps of x, each in [1, s].

    A convolution near a sample's end reads the batch's padding (zero features, or zero
    codes for index −1) through its biases, which would change the last frames of the
    shorter samples with their batch-mates' lengths. Cut, a sample's output is its output
    alone. Samples of one length share one call, so an equal-length batch costs what
    one call over the padded batch costs.
    """
    if bool((lengths == x.shape[-1]).all()):
        return net(x)
    out = None
    for length in lengths.unique().tolist():
        rows = (lengths == length).nonzero().flatten()
        y = net(x[rows, :, :length])
        if out is None:
            out = y.new_zeros(x.shape[0], y.shape[1], out_steps)
        out[rows, :, : y.shape[-1]] = y
    return out


def _check_lengths(lengths: Tensor, b: int, t: int, unit: int, caller: str) -> None:
    """lengths (b,) frames, multiples of `unit` in [unit, t], or ValueError."""
    if lengths.shape != (b,) or lengths.dtype.is_floating_point or lengths.dtype == torch.bool:
        raise ValueError(f"RVQVAE.{caller}: expected lengths ({b},) integer frames, got "
                         f"{tuple(lengths.shape)} {lengths.dtype}")
    if bool(((lengths < unit) | (lengths > t) | (lengths % unit != 0)).any()):
        raise ValueError(f"RVQVAE.{caller}: lengths must be multiples of {unit} in [{unit}, {t}], "
                         f"got {lengths.tolist()}")


class RVQVAE(nn.Module, Pretrained):
    """Residual VQ-VAE over z-scored motion features.

    Buffers `mean`, `std` (d,) hold the normalisation statistics of the training data so
    that a model directory is self-sufficient; `normalize`/`denormalize` apply them. The
    model itself always works on z-scored features.
    """

    kind = "rvq"
    config_class = RVQConfig

    def __init__(self, config: RVQConfig) -> None:
        super().__init__()
        self.config = config
        self.meta: dict = {}
        self.encoder = Encoder(config)
        self.quantizer = ResidualQuantizer(
            num_quantizers=config.num_quantizers,
            codebook_size=config.codebook_size,
            code_dim=config.code_dim,
            ema_decay=config.ema_decay,
            dead_code_threshold=config.dead_code_threshold,
            quantizer_dropout=config.quantizer_dropout,
        )
        self.decoder = Decoder(config)
        self.register_buffer("mean", torch.zeros(config.feature_dim))
        self.register_buffer("std", torch.ones(config.feature_dim))

    @property
    def codebook_size(self) -> int:
        return self.config.codebook_size

    @property
    def num_quantizers(self) -> int:
        return self.config.num_quantizers

    @property
    def code_dim(self) -> int:
        return self.config.code_dim

    def set_statistics(self, mean: Tensor, std: Tensor) -> None:
        """Copy the data's normalisation statistics (d,) into the buffers."""
        d = self.config.feature_dim
        if mean.shape != (d,) or std.shape != (d,):
            raise ValueError(
                f"RVQVAE.set_statistics: expected mean and std of shape ({d},), "
                f"got {tuple(mean.shape)} and {tuple(std.shape)}"
            )
        self.mean.copy_(mean)
        self.std.copy_(std)

    def normalize(self, features: Tensor) -> Tensor:
        """Raw features (..., d) -> z-scored."""
        return (features - self.mean) / self.std

    def denormalize(self, features: Tensor) -> Tensor:
        """z-scored features (..., d) -> raw features."""
        return features * self.std + self.mean

    def _check_features(self, features: Tensor, caller: str) -> None:
        if features.ndim != 3 or features.shape[-1] != self.config.feature_dim:
            raise ValueError(
                f"RVQVAE.{caller}: expected features (b, t, {self.config.feature_dim}), "
                f"got {tuple(features.shape)}"
            )
        if features.shape[1] % FRAMES_PER_TOKEN:
            raise ValueError(
                f"RVQVAE.{caller}: t={features.shape[1]} frames is not a multiple of "
                f"{FRAMES_PER_TOKEN}; crop the motion first"
            )

    def forward(
        self,
        features: Tensor,
        mask: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> RVQOutput:
        """Auto-encode z-scored features (b, t, d); mask (b, t) bool, True = valid.

        In training mode the codebooks learn and quantizer dropout applies; `generator`
        (CPU) drives those random choices.
        """
        self._check_features(features, "forward")
        latent = self.encoder(features.transpose(1, 2)).transpose(1, 2)  # (b, n, c)
        token_mask = None if mask is None else mask[:, ::FRAMES_PER_TOKEN]
        out = self.quantizer(latent, mask=token_mask, generator=generator)
        reconstruction = self.decoder(out.quantized.transpose(1, 2)).transpose(1, 2)
        return RVQOutput(
            reconstruction=reconstruction,
            indices=out.indices,
            commitment_loss=out.commitment_loss,
            perplexity=out.perplexity,
            code_usage=out.code_usage,
        )

    def latents(self, features: Tensor, lengths: Tensor | None = None) -> Tensor:
        """z-scored features (b, t, d), t a multiple of 4 -> the encoder's latents
        (b, t // 4, code_dim) before quantization (what the cpd/kmeans motion segmenters
        split); `quantize` turns them into indices.

        lengths (b,) frames (multiples of 4) of a zero-padded batch: each motion is encoded
        at its own length (`run_at_lengths`), its latents past length // 4 are zero.
        """
        self._check_features(features, "latents")
        x = features.transpose(1, 2)
        if lengths is None:
            return self.encoder(x).transpose(1, 2)
        b, t, _ = features.shape
        _check_lengths(lengths, b, t, FRAMES_PER_TOKEN, "latents")
        return run_at_lengths(self.encoder, x, lengths, t // FRAMES_PER_TOKEN).transpose(1, 2)

    @torch.no_grad()
    def encode(self, features: Tensor) -> Tensor:
        """z-scored features (b, t, d), t a multiple of 4 -> indices (b, t // 4, q) long."""
        self._check_features(features, "encode")  # an error names the method called
        return self.quantize(self.latents(features))

    @torch.no_grad()
    def quantize(self, latents: Tensor) -> Tensor:
        """Latents (b, n, code_dim) -> indices (b, n, q) long: each layer takes the code
        nearest to what the layers before it left."""
        b, n, c = latents.shape
        residual = latents.float().reshape(b * n, c)
        indices = []
        for layer in range(self.num_quantizers):
            index = self.quantizer.nearest(layer, residual)
            residual = residual - self.quantizer.codebooks[layer][index]
            indices.append(index)
        return torch.stack(indices, dim=-1).reshape(b, n, self.num_quantizers)

    def decode(self, indices: Tensor, lengths: Tensor | None = None) -> Tensor:
        """indices (b, n, q') with q' ≤ q, −1 = zero code -> z-scored features (b, 4 n, d).

        lengths (b,) frames (multiples of 4) of a padded batch: each motion is decoded from
        its own length // 4 tokens (`run_at_lengths`), its frames past length are zero.
        """
        if indices.ndim != 3:
            raise ValueError(f"RVQVAE.decode: expected indices (b, n, q), got {tuple(indices.shape)}")
        codes = self.quantizer.codes(indices).to(self.mean.dtype).transpose(1, 2)  # (b, c, n)
        if lengths is None:
            return self.decoder(codes).transpose(1, 2)
        b, n, _ = indices.shape
        _check_lengths(lengths, b, n * FRAMES_PER_TOKEN, FRAMES_PER_TOKEN, "decode")
        steps = lengths // FRAMES_PER_TOKEN
        return run_at_lengths(self.decoder, codes, steps, n * FRAMES_PER_TOKEN).transpose(1, 2)
