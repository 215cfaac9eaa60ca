"""Captions for synthetic motions and their ground-truth text segments.

Every caption is built from one phrase per executed segment (a finite form, "walks
forward slowly", and a gerund, "walking forward slowly"), a subject ("a man") and an
ordering template. Its ground truth lists, in execution order, each segment's phrase with
the subject restored ("a man walks forward slowly"), whatever order the caption uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from segmo.data.attributes import SPEED_THRESHOLDS
from segmo.synth.sequence import Segment

# (subject, re-mention, possessive)
SUBJECTS = (
    ("a person", "the person", "their"), ("a man", "he", "his"), ("a woman", "she", "her"),
    ("someone", "the person", "their"), ("the figure", "the figure", "its"),
    ("a human", "the human", "their"), ("the person", "the person", "their"),
)
TEMPLATES = ("then", "and_then", "after_that", "finally", "and", "first_then", "after",
             "followed_by", "before")
HELD_OUT_TEMPLATES = ("followed_by", "before")  # only in val/test captions
_COUNT = {1: "once", 2: "twice", 3: "three times", 4: "four times", 5: "five times"}


def _times(n: int | None, rng, optional: bool = True) -> str:
    if not n or (n == 1 and optional and rng.random() < 0.7):
        return ""
    return " " + (_COUNT[n] if n != 2 or rng.random() < 0.7 else "two times")


def _speed(v: float, slow: float, fast: float, rng) -> str:
    if v < slow:
        return " " + ("slowly" if rng.random() < 0.7 else "at a slow pace")
    if v > fast:
        return " " + ("quickly" if rng.random() < 0.6 else "fast")
    return ""


def _variants(action: str, p: dict, rng, poss: str) -> list[str]:
    """Finite-verb phrases for one action; the gerund is derived by `_gerund`."""
    if action == "walk_forward":
        m = _speed(p["speed"], *SPEED_THRESHOLDS["walk_forward"], rng)
        return [f"walks forward{m}", f"walks straight ahead{m}", f"walks{m}"]
    if action == "walk_backward":
        m = _speed(p["speed"], *SPEED_THRESHOLDS["walk_backward"], rng)
        return [f"walks backward{m}", f"walks backwards{m}", f"steps back{m}"]
    if action == "jog":
        return ["jogs forward", "jogs", "jogs ahead"]
    if action == "run":
        m = _speed(p["speed"], *SPEED_THRESHOLDS["run"], rng)
        return [f"runs forward{m}", f"runs{m}", f"runs ahead{m}"]
    if action == "side_step":
        d = p["direction"]
        return [f"steps to the {d}", f"side-steps to the {d}", f"shuffles sideways to the {d}"]
    if action == "walk_circle":
        turn = "counterclockwise" if p["direction"] == "left" else "clockwise"
        return ["walks in a circle", "walks around in a circle", f"walks in a circle {turn}"]
    if action == "turn":
        d = p["direction"]
        if p["angle"] == 180:
            return ["turns around", f"turns around to the {d}", "turns 180 degrees"]
        return [f"turns {d}", f"turns to the {d}", f"turns 90 degrees to the {d}"]
    if action == "spin":
        return ["spins around", "turns in a full circle", f"spins around to the {p['direction']}"]
    if action == "jump_in_place":
        c = _times(p["count"], rng)
        return [f"jumps in place{c}", f"jumps up and down{c}", f"jumps{c}"]
    if action == "jump_forward":
        c = _times(p["count"], rng)
        return [f"jumps forward{c}", f"leaps forward{c}", f"jumps ahead with both feet{c}"]
    if action == "hop":
        c = _times(p["count"], rng, optional=False)
        return [f"hops on {poss} {p['foot']} foot{c}", f"hops on one foot{c}", f"hops on the {p['foot']} leg{c}"]
    if action == "sit_down":
        return ["sits down", "takes a seat", "sits down slowly" if p["duration"] > 2.1 else "sits down"]
    if action == "stand_up":
        return ["stands up", "gets up", f"rises to {poss} feet"]
    if action == "squat":
        c = _times(p["count"], rng)
        return [f"squats{c}", f"squats down and stands back up{c}", f"does a squat{c}" if p["count"] == 1 else f"squats{c}"]
    if action == "crouch":
        return ["crouches down", "crouches", "crouches low and gets back up"]
    if action == "bow":
        deep = " deeply" if p["angle"] > 55 else ""
        return [f"bows{deep}", f"bows forward{deep}", f"bends forward at the waist{deep}"]
    if action == "stretch_arms_up":
        return [f"stretches {poss} arms up", f"raises both arms above {poss} head", "reaches up with both arms"]
    if action == "kick":
        s = p["side"]
        return [f"kicks with {poss} {s} foot", f"kicks {poss} {s} leg forward", f"does a {s} kick"]
    if action == "punch":
        c, s = _times(p.get("count"), rng), p["side"]
        return [f"punches with {poss} {s} hand{c}", f"punches forward with the {s} fist{c}", f"throws a {s} punch{c}"]
    if action == "wave":
        c = _times(p.get("count"), rng)
        if p["hand"] == "both":
            return [f"waves both hands{c}", f"waves with both arms{c}", f"waves both {poss} hands{c}"]
        s = p["hand"]
        return [f"waves {poss} {s} hand{c}", f"waves with {poss} {s} hand{c}", f"waves with the {s} arm{c}"]
    if action == "raise_arm":
        s = p["side"]
        return [f"raises {poss} {s} arm and lowers it", f"lifts the {s} arm up and puts it down",
                f"raises {poss} {s} hand and brings it back down"]
    if action == "clap":
        c = _times(p.get("count"), rng)
        return [f"claps{c}", f"claps {poss} hands{c}", f"claps {poss} hands together{c}"]
    if action == "stand_still":
        return ["stands still", "stands in place", "waits"]
    raise ValueError(f"captions: no phrases for action {action!r}")


_IRREGULAR = {"does": "doing", "gets": "getting", "runs": "running", "sits": "sitting",
              "jogs": "jogging", "steps": "stepping", "hops": "hopping", "side-steps": "side-stepping",
              "shuffles": "shuffling", "takes": "taking", "rises": "rising", "waves": "waving",
              "raises": "raising", "lowers": "lowering", "squats": "squatting", "leaps": "leaping",
              "claps": "clapping", "puts": "putting", "spins": "spinning", "stands": "standing",
              "reaches": "reaching", "stretches": "stretching", "punches": "punching",
              "crouches": "crouching", "brings": "bringing", "bends": "bending", "throws": "throwing"}


def _gerund(finite: str) -> str:
    """'walks forward and lowers it' -> 'walking forward and lowering it'."""
    words = finite.split(" ")
    out = []
    for i, w in enumerate(words):
        verb = i == 0 or (words[i - 1] == "and" and w.endswith("s") and w not in ("its", "hands"))
        out.append(_IRREGULAR.get(w, w[:-1] + "ing") if verb else w)
    return " ".join(out)


def segment_phrase(seg: Segment, rng, poss: str) -> str:
    """A finite phrase for a segment, with "while ..." for a simultaneous upper-body action."""
    variants = _variants(seg.action, seg.params, rng, poss)
    phrase = variants[int(rng.integers(len(variants)))]
    if seg.overlay is not None:
        upper = _variants(seg.overlay[0], seg.overlay[1], rng, poss)
        phrase += " while " + _gerund(upper[int(rng.integers(len(upper)))])
    return phrase


@dataclass
class Caption:
    text: str
    template: str
    segments: list[str]  # execution order, subject restored


def _compose(template: str, subj: tuple[str, str, str], fin: list[str], ger: list[str]) -> str:
    s, r, _ = subj
    k = len(fin)
    if k == 1:
        return f"{s} {fin[0]}."
    if template == "then":
        return f"{s} " + ", then ".join(fin) + "."
    if template == "and_then":
        return f"{s} " + " and then ".join(fin) + "."
    if template == "after_that":
        return f"{s} {fin[0]}. " + " ".join(f"after that, {r} {f}." for f in fin[1:])
    if template == "finally":
        return f"{s} " + ", then ".join(fin[:-1]) + f", and finally {fin[-1]}."
    if template == "and":
        return f"{s} " + (", ".join(fin[:-1]) + f" and {fin[-1]}.")
    if template == "first_then":
        return f"first, {s} {fin[0]}, then {r} " + ", then ".join(fin[1:]) + "."
    if template == "after":
        if k == 2:
            return f"{s} {fin[1]} after {ger[0]}."
        return f"after {ger[0]}, {s} " + ", then ".join(fin[1:]) + "."
    if template == "followed_by":
        return f"{s} {fin[0]}, " + ", ".join(f"followed by {g}" for g in ger[1:]) + "."
    if template == "before":
        return f"before {ger[-1]}, {s} " + ", then ".join(fin[:-1]) + "."
    raise ValueError(f"captions: unknown template {template!r}")


def make_captions(segments: list[Segment], rng: np.random.Generator, held_out: bool,
                  count: int = 3) -> list[Caption]:
    """`count` differently worded captions; `held_out` allows the held-out templates."""
    k = len(segments)
    allowed = ["single"] if k == 1 else [
        t for t in TEMPLATES if (held_out or t not in HELD_OUT_TEMPLATES) and not (t == "finally" and k < 3)]
    captions: list[Caption] = []
    for _attempt in range(count * 4):
        subj = SUBJECTS[int(rng.integers(len(SUBJECTS)))]
        if held_out and k > 1 and not captions and rng.random() < 0.6:
            template = HELD_OUT_TEMPLATES[int(rng.integers(len(HELD_OUT_TEMPLATES)))]
        else:
            template = allowed[int(rng.integers(len(allowed)))]
        fin = [segment_phrase(seg, rng, subj[2]) for seg in segments]
        text = _compose(template, subj, fin, [_gerund(f) for f in fin])
        if any(c.text == text for c in captions):
            continue
        captions.append(Caption(text, template, [f"{subj[0]} {f}" for f in fin]))
        if len(captions) == count:
            break
    return captions


# A small part-of-speech lexicon for the caption vocabulary (HumanML3D's `word/POS`).
_POS = {
    "DET": "a an the both", "PRON": "he she someone it its their his her that", "NUM": "once twice two three four five 90 180",
    "ADP": "to on in with at above from by", "CCONJ": "and", "SCONJ": "while after before",
    "ADV": "still slowly quickly fast forward backward backwards back then finally first ahead straight sideways up "
           "down deeply together low counterclockwise clockwise around",
    "ADJ": "left right slow full one",
}
_LEXICON = {w: pos for pos, words in _POS.items() for w in words.split()}
_NOUNS = set("person man woman figure human foot feet leg hand hands arm arms head seat circle pace "
             "degrees times place kick punch fist squat waist".split())


def pos_tag(text: str) -> str:
    """'a man waves.' -> 'a/DET man/NOUN waves/VERB' (punctuation dropped)."""
    tags = []
    for raw in text.replace(",", " ").replace(".", " ").split():
        w = raw.lower()
        pos = _LEXICON.get(w) or ("NOUN" if w in _NOUNS else
                                  "VERB" if w.endswith(("s", "ing", "ed")) else "OTHER")
        tags.append(f"{w}/{pos}")
    return " ".join(tags)
