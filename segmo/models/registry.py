"""Imports every model module so that `load_pretrained` knows every kind."""

import importlib

for _module in (
    "segmo.models.rvq",
    "segmo.models.mask_transformer",
    "segmo.models.residual_transformer",
    "segmo.models.length_estimator",
    "segmo.evaluation.evaluator",
    "segmo.evaluation.action_order",
):
    try:
        importlib.import_module(_module)
    except ModuleNotFoundError as error:  # a stage not built yet in this checkout
        if error.name != _module:
            raise
