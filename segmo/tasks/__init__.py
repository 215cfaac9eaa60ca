"""LightningModules, one per training stage: losses, logging, optimisers.

A task takes plain data (numbers, strings) as constructor arguments and builds its network
from them, so that `Task.load_from_checkpoint` needs nothing else. Every task exposes
`export_model() -> Pretrained module`, which `segmo export` writes as a model directory,
and may declare `stage` (run directory `runs/<stage>/<name>`) and `monitor` (the metric
that picks the best checkpoint, lower is better). All derive from `segmo.tasks.base.Task`
(non-finite guards, random states in checkpoints).
"""
