"""The tokenizer task's former home, kept for class paths written before it moved.

Checkpoints record their task as ``_class_path`` (``segmo export`` imports it), and run
directories' ``config.yaml`` name it too: ``segmo.tasks.rvq.RVQTask`` must keep working.
New configs name `segmo.tasks.tokenizer.RVQTask`.
"""

from segmo.tasks.tokenizer import RVQTask

__all__ = ["RVQTask"]
