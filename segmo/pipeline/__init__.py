"""The inference API for notebooks and the `segmo generate/ground/bundle` commands.

    from segmo.pipeline import SegMo
    model = SegMo.from_pretrained("runs/demo/model")
"""

from segmo.pipeline.outputs import GenerationOutput, GroundingOutput
from segmo.pipeline.segmo import SegMo, SegMoConfig, edit_drift

__all__ = ["GenerationOutput", "GroundingOutput", "SegMo", "SegMoConfig", "edit_drift"]
