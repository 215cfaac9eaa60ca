"""The built-in synthetic motion-language corpus (`segmo synth`).

`build_corpus(out, num_motions, seed)` writes a HumanML3D-layout dataset with exact
ground truth (`segments/<id>.json`); `sample_motion(rng)` generates one motion;
`ACTIONS` is the action library.
"""

from segmo.synth.actions import ACTIONS
from segmo.synth.corpus import build_corpus, main
from segmo.synth.sequence import SynthMotion, sample_motion

__all__ = ["ACTIONS", "build_corpus", "main", "sample_motion", "SynthMotion"]
