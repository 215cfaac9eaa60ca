"""segmo: segment-aligned text to 3D human motion generation.

    from segmo import SegMo, SamplingOptions
    model = SegMo.from_pretrained("runs/demo/model")
    out = model.generate(["a person walks forward, then waves"], lengths=[120])
    out = model.generate(["a person waves"], [80], sampling=SamplingOptions(steps=20))
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    # Lazy, so that `import segmo` (and `segmo --help`) does not import torch.
    if name == "SegMo":
        from segmo.pipeline import SegMo

        return SegMo
    if name == "SamplingOptions":
        from segmo.generation.sampling import SamplingOptions

        return SamplingOptions
    raise AttributeError(f"module 'segmo' has no attribute {name!r}")
