"""segmo: segment-aligned text to 3D human motion generation.

    from segmo import SegMo
    model = SegMo.from_pretrained("runs/demo/model")
    out = model.generate(["a person walks forward, then waves"], lengths=[120])
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    # Lazy, so that `import segmo` (and `segmo --help`) does not import torch.
    if name == "SegMo":
        from segmo.pipeline import SegMo

        return SegMo
    raise AttributeError(f"module 'segmo' has no attribute {name!r}")
