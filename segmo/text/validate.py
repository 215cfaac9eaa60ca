"""Reading an LLM's text-segment answer and checking it against its caption.

`parse_answer` finds ``{"segments": [...]}`` in an answer; `validate_segments` says why
the segments are not an acceptable split of the caption (spec §7), or returns None. Both
LLM backends re-ask with that reason and, after the last re-ask, fall back to the rules.

The checks, in order (each reason names the offending segment):
1. 1..max_segments segments, none empty, none much longer than the caption;
2. exists: every word of a segment is a caption word (up to inflection, `rules.lemma`)
   or light glue (a restored subject, "is", "then", ...);
3. content: every segment carries at least one content word ("it is it" carries none);
4. no duplicates beyond what the caption repeats (five copies of "a man walks" for a
   caption that says "walks" once fail; "jumps, jumps and jumps" may give three);
5. no action lost: every action verb of the caption (the verb lexicon, less light verbs
   such as "starts", "proceeds", "goes") is in some segment;
6. order: execution order, not mention order. The caption's actions are ordered by the
   rule extractor's connective rules (`rules.action_clauses`: "runs after walking" puts
   the walk first, "before sitting down, a man waves" the wave). Each segment is placed
   on the action(s) whose content words it shares most; an answer fails only when a
   later segment lies wholly before an earlier one, so splitting or merging actions and
   ambiguous segments ("a man walks" for a caption that walks twice) are accepted.
"""

from __future__ import annotations

import json
import re
import unicodedata
from collections import Counter

from pydantic import BaseModel, ConfigDict, ValidationError

from segmo.text import lexicon
from segmo.text.rules import MAX_SEGMENTS, action_clauses, lemma

# Words an answer may add to the caption's own: a restored subject and light glue.
ALLOWED_EXTRA = set("""a an the person man woman human someone somebody he she they it his her
their is are and then subject figure""".split())
# Words that carry no content of their own: a segment made only of these says nothing.
FUNCTION_WORDS = (ALLOWED_EXTRA | lexicon.AUX | lexicon.PRONOUNS | lexicon.DETERMINERS
                  | lexicon.SUBJECT_NOUNS | lexicon.RELATIVE
                  | set("""then and after before while as to of with in on at by for from its
                  also again so but or has have had does this that these those""".split()))
_SUBJECT_WORDS = ALLOWED_EXTRA | lexicon.AUX | lexicon.PRONOUNS | lexicon.DETERMINERS | lexicon.SUBJECT_NOUNS
# Verbs an answer may drop without losing an action ("proceeds to walk" -> "walks").
LIGHT_VERBS = set("""start begin continue proceed keep try seem appear go get come let need use
prepare make do take perform repeat end finish""".split())
_THINK_RE = re.compile(r"<think>.*?(</think>|$)", re.DOTALL | re.IGNORECASE)
# Words of any script: a segment's words in another one are not the caption's.
_WORD_RE = re.compile(r"[^\W\d_]+|[0-9]+")
# The longest answer read: a segment list is a few hundred characters; a reasoning model's
# <think> block some thousands.
MAX_ANSWER_CHARS = 50_000


class Answer(BaseModel):
    """The answer's shape, ``{"segments": [str, ...]}`` (other keys ignored; no coercion:
    a number is not a segment)."""

    model_config = ConfigDict(strict=True, extra="ignore")
    segments: list[str]


def answer_schema(max_segments: int = MAX_SEGMENTS) -> dict:
    """JSON schema of an answer, for servers that constrain their output to one
    (``response_format`` of type ``json_schema``, strict)."""
    return {"type": "object", "additionalProperties": False, "required": ["segments"],
            "properties": {"segments": {"type": "array", "minItems": 1, "maxItems": max_segments,
                                        "items": {"type": "string", "minLength": 1}}}}


def parse_answer(text: str) -> list[str] | None:
    """Segments from a model answer, or None if there is no ``{"segments": [str, ...]}`` in it.

    Tolerates ``<think>...</think>`` blocks (Qwen3), code fences and text around the JSON.
    An answer longer than MAX_ANSWER_CHARS is not read (None); the caller names that reason.
    """
    if len(text) > MAX_ANSWER_CHARS:  # each '{' is a parse: quadratic in a hostile answer
        return None
    text = _THINK_RE.sub("", text)
    text = re.sub(r"```(?:json)?", "", text)
    decoder = json.JSONDecoder()
    for match in re.finditer(r"\{", text):
        try:
            obj, _ = decoder.raw_decode(text, match.start())
        except (json.JSONDecodeError, RecursionError):
            continue
        try:
            segments = Answer.model_validate(obj).segments
        except ValidationError:
            continue
        return [s.replace("#", " ").strip().rstrip(".!?;,").strip() for s in segments]
    return None


def _content(text: str) -> list[str]:
    """Lemmas of the content words of `text`, in order."""
    return [lemma(w) for w in _WORD_RE.findall(text) if w.lower() not in FUNCTION_WORDS]


def _same(segment: str) -> tuple[str, ...]:
    """What two segments share when they are copies of each other: their lemmas, less the
    subject and auxiliary ("a man walks" = "he walks", but not "walks forward again")."""
    return tuple(lemma(w) for w in _WORD_RE.findall(segment) if w.lower() not in _SUBJECT_WORDS)


def _actions(caption: str) -> set[str]:
    """Base forms of the caption's action verbs (light verbs left out)."""
    verbs = {lexicon.FORMS[w.lower()][0] for w in _WORD_RE.findall(caption) if w.lower() in lexicon.FORMS}
    return verbs - LIGHT_VERBS


def _order_problem(caption: str, segments: list[str]) -> str | None:
    """Why the segments contradict the caption's execution order, or None."""
    clauses = action_clauses(caption)
    if len(clauses) < 2:
        return None
    units = [set(_content(c)) for c in clauses]
    placed: list[tuple[int, int, str]] = []  # (first, last) action a segment may describe
    for s in segments:
        words = set(_content(s))
        # Jaccard, so that a short action ("then forward again") is not outscored by a
        # long one that merely shares the verb
        scores = [len(words & u) / len(words | u) for u in units]
        best = max(scores)
        if best == 0:
            continue
        ranks = [k for k, score in enumerate(scores) if score == best]
        placed.append((ranks[0], ranks[-1], s))
    for i, (first, _, earlier) in enumerate(placed):
        for _, last, later in placed[i + 1 :]:
            if last < first:
                return (f"segments out of execution order: {later!r} happens before "
                        f"{earlier!r} in the caption (order of execution, not of mention)")
    return None


def validate_segments(caption: str, segments: list[str] | None, max_segments: int = MAX_SEGMENTS,
                      length_margin: int = 40) -> str | None:
    """Why `segments` is not an acceptable answer for `caption`, or None if it is (see the
    module docstring for the checks)."""
    if segments is None:
        return 'no JSON object {"segments": [...]} found'
    if not 1 <= len(segments) <= max_segments:
        return f"expected 1 to {max_segments} segments, got {len(segments)}"
    caption_words = [lemma(w) for w in _WORD_RE.findall(caption)]
    allowed = set(caption_words) | ALLOWED_EXTRA
    for s in segments:
        if not s.strip():
            return "empty segment"
        if len(s) > len(caption) + length_margin:
            return f"segment longer than the caption: {s!r:.120}"
        if any(unicodedata.category(c) in ("Cc", "Cs") for c in s):  # NUL, a lone surrogate
            return f"segment {s!r:.120} holds control characters"
        foreign = [w for w in _WORD_RE.findall(s) if lemma(w) not in allowed and w.lower() not in allowed]
        if foreign:
            return f"segment {s!r:.120} uses words not in the caption: {foreign[:5]}"
        if not _content(s):
            return f"segment {s!r:.120} names no action or detail of the caption"
    available = Counter(caption_words)
    for key, copies in Counter(map(_same, segments)).items():
        if copies > 1 and any(available[w] < copies for w in key if w not in FUNCTION_WORDS):
            text = next(s for s in segments if _same(s) == key)
            return f"segment {text!r} is repeated {copies} times but the caption says it fewer times"
    said = {w for s in segments for w in _content(s)}
    lost = sorted(_actions(caption) - said)
    if lost:
        return f"the segments lose the caption's action(s) {lost}"
    return _order_problem(caption, segments)
