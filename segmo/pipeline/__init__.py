"""The inference API for notebooks and the `segmo generate/ground/bundle` commands.

    from segmo.pipeline import SegMo
    model = SegMo.from_pretrained("runs/demo/model")
"""

from segmo.generation.editing import edit_drift
from segmo.pipeline.bundle import SegMoConfig
from segmo.pipeline.outputs import GenerationOutput, GroundingOutput
from segmo.pipeline.segmo import SegMo

__all__ = ["GenerationOutput", "GroundingOutput", "SegMo", "SegMoConfig", "edit_drift"]
