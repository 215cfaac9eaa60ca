"""Deterministic, model-free text-segment extraction (spec §7, paper §3.3).

`RuleSegmenter` splits a motion caption into at most five temporally ordered segments
with a small verb lexicon and a table of connectives; no NLP model is involved, so the
result is reproducible and fast (about 6k captions per second on one busy core).

Rules, in the order they are applied:
1. Split at a connective (", then", "and then", "then", "after that", "followed by",
   "finally", "afterwards", "next", "before", "after", "and", ",", sentence ends) only
   when a verb phrase follows it (optionally after a subject such as "he" or "the man",
   adverbs, or "is"), and the text before it holds a verb. "up and down", "back and
   forth", "next to", "as if ..." therefore never split, and modifiers (speed,
   direction, side, counts, "as if ...") stay with their verb.
2. Simultaneous actions stay one segment: "while"/"as"/"at the same time" joins; a
   static posture before a plain "and" ("stands and waves", "is kneeling and praying",
   but not "stands and walks away" or "kneels and gets up") joins; a gerund after a plain "and"/"," in a finite sentence is a manner
   ("walks forward, waving") and joins. A movement taken back after a plain "and" is one
   gesture and joins: a raise lowered on the same thing named by a pronoun ("raises his
   arm and lowers it", "lifts the arm up and puts it down") and a dip risen back from
   ("squats down and stands back up"); but "raises his arm and then lowers it", "raises
   and lowers his arms" and "sits down and stands up" are two steps.
3. Execution order, not mention order: "A after B" puts B first (", after B" moves B
   before everything said before it in the sentence); "before B, A" puts B last.
4. A segment without its own subject gets the caption's subject back ("a person walks
   forward, turns around" -> "a person turns around"); a gerund segment in a finite
   caption is put in the third person ("runs after walking" -> "a person walks"), and a
   bare direction after "then" reuses the previous verb ("walks forward then back").
   A verb right after a direction/adverb/verb starts a new action even without a comma
   ("walks forward turns around"), unless it is usually a noun ("forward steps").
   "raises and lowers his arms" shares the object: two segments with "his arms" (only
   for two verbs joined by a bare "and" that both move a limb or both handle a thing:
   not "waves and kicks his right leg", "kicks twice and raises his arms").
5. At most `MAX_SEGMENTS`; the tail's clauses are merged into the last one with ", then ",
   the subject restored once ("a person sits, then lies down").
An opening "first," orders nothing and is left out of the segments.

Conventions chosen here: every segment has its final punctuation removed; a caption that
yields a single segment is returned as ``[caption.strip() minus final punctuation]``,
so an empty or whitespace-only caption gives ``[""]``. `segment` never raises on a str.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from segmo.text import lexicon

MAX_SEGMENTS = 5
# Raised whenever a rule change gives other segments for some captions, so that a segment
# folder made by older rules is not silently mixed with newer ones (`segment-texts`).
# 2: a movement and its return after a plain "and" are one segment; an opening "first,"
#    is left out (version 1: segmo up to commit de0c29e).
# 3: "squatting"/"squatted" are verbs; a subject after a determiner is looked for up to a
#    comma only ("after taking a seat, someone ..."); an object is shared only between two
#    verbs of one kind joined by a bare "and"; the clauses merged past MAX_SEGMENTS say
#    the subject once (version 2: segmo up to commit 43d2d98).
RULES_VERSION = 3


@runtime_checkable
class TextSegmenter(Protocol):
    """What every backend provides. `name` names the output folder (`text_segments/<name>`)."""

    name: str

    def segment(self, texts: list[str]) -> list[list[str]]:
        """One list of 1..MAX_SEGMENTS ordered segments per caption."""
        ...


_NOT_MODIFIERS = (lexicon.PRONOUNS | lexicon.DETERMINERS | lexicon.RELATIVE | lexicon.AUX
                  | {w for words, _ in lexicon.CONNECTIVES for w in words})
_TOKEN_RE = re.compile(r"[A-Za-z0-9]+(?:['’/\-][A-Za-z0-9]+)*|[^\sA-Za-z0-9]")


@dataclass
class _Tok:
    text: str
    low: str
    start: int  # character offsets into the caption
    end: int


@dataclass
class _Clause:
    """A run of tokens [start, end) describing one action, plus how it joins the previous one."""

    start: int
    end: int
    verb: int | None  # token index of its verb, None for a copied verb ("then back")
    own_subject: bool
    join: str  # kind of the connective before it: lead-*, weak, strong, sentence, before, after, simul
    wide: bool = False  # ", after ..." reaches back to the start of the sentence
    copied_verb: str = ""
    suffix: str = ""  # object shared from the next clause ("raises and lowers his arms")
    joined: list[int] = field(default_factory=list)  # verbs of clauses joined as one gesture


def _kinds(tok: _Tok) -> frozenset[str]:
    entry = lexicon.FORMS.get(tok.low)
    return entry[1] if entry else frozenset()


def _verb_kinds(toks: list[_Tok], k: int | None) -> frozenset[str]:
    """Kinds of the verb at k; an unknown verb is classed by its ending."""
    if k is None:
        return frozenset()
    low = toks[k].low
    if low in lexicon.FORMS:
        return lexicon.FORMS[low][1]
    return frozenset({"ing"} if low.endswith("ing") else {"past"} if low.endswith("ed") else {"3sg"})


def _is_adverb(low: str) -> bool:
    return low in lexicon.ADVERBS or (low.endswith("ly") and len(low) > 4 and low not in lexicon.FORMS)


def _guess_verb(low: str) -> bool:
    """An unknown word that looks inflected; only trusted right after a strong connective."""
    if low in lexicon.NOT_GUESSABLE or low in lexicon.DIRECTIONS or not low.isalpha() or len(low) < 4:
        return False
    return low.endswith(("ing", "ed")) or (low.endswith("s") and not low.endswith(("ss", "us")))


def _modifier(low: str) -> bool:
    """A word that may stand between a determiner and its noun ("old", "tall", "young")."""
    return low.isalpha() and low not in lexicon.FORMS and low not in _NOT_MODIFIERS


def _match_subject(toks: list[_Tok], k: int) -> int | None:
    """End index of a subject noun phrase starting at k ("he", "the old man", "a figure that")."""
    n = len(toks)
    if k >= n:
        return None
    low = toks[k].low
    if low in lexicon.PRONOUNS or (low in lexicon.SUBJECT_NOUNS and low not in lexicon.FORMS):
        end = k + 1
    elif low in lexicon.DETERMINERS:
        # only modifiers may stand between the determiner and its noun ("the old man"): a
        # comma or a verb ends the look-ahead ("after taking a seat, someone gets up")
        end = 0
        for m in range(k + 1, min(k + 4, n)):
            if toks[m].low in lexicon.SUBJECT_NOUNS:
                end = m + 1
                break
            if not _modifier(toks[m].low):
                return None
        if not end:
            return None
    else:
        return None
    while end < n and toks[end].low in lexicon.RELATIVE:
        end += 1
    return end


def _find_verb(toks: list[_Tok], j: int, join: str, main: frozenset[str], has_aux: bool):
    """(verb index or None, own subject, copy-the-verb) if a verb phrase starts at j, else None."""
    n = len(toks)
    k, own, aux = j, False, False
    end = _match_subject(toks, k)
    if end is not None and end < n:
        k, own = end, True
    while k < n and (toks[k].low in lexicon.AUX or _is_adverb(toks[k].low)):
        aux = aux or toks[k].low in lexicon.AUX
        k += 1
    if k >= n:
        return None
    kinds = _kinds(toks[k])
    if kinds:
        if join == "weak" and not own and not aux and "ing" not in kinds:
            # plain "and"/"," joins verbs of the same grammatical form only: "walks and
            # turns", but not "with arms raised and lowered"
            allowed = set(main) | ({"3sg", "past"} if has_aux or "ing" in main else set())
            if not kinds & allowed:
                return None
        return k, own, False
    if join != "weak" and _guess_verb(toks[k].low):
        return k, own, False
    if join in ("strong", "sentence") and not own and k == j and (toks[k].low in lexicon.COPYABLE or toks[k].low.isdigit()):
        return None, False, True
    return None


def _tokenize(text: str) -> list[_Tok]:
    return [_Tok(m.group(), m.group().lower(), m.start(), m.end()) for m in _TOKEN_RE.finditer(text)]


def _tokenize_actions(caption: str) -> list[_Tok]:
    """The caption's tokens without an opening "first," / "firstly," ("first, a man walks,
    then he runs"): it orders nothing, and left in place it hides the caption's subject."""
    toks = _tokenize(caption)
    if len(toks) > 2 and toks[0].low in ("first", "firstly") and toks[1].low == ",":
        return toks[2:]
    return toks


def _match_connective(toks: list[_Tok], i: int) -> tuple[int, str, bool]:
    """Longest run of connectives at i: (end index, strongest kind, starts with a comma)."""
    j, kind = i, ""
    while True:
        for words, k in lexicon.CONNECTIVES:
            if tuple(t.low for t in toks[j : j + len(words)]) == words:
                after = toks[j + len(words)].low if j + len(words) < len(toks) else ""
                if (words == ("as",) and after in ("if", "though", "well")) or (words == ("next",) and after == "to"):
                    continue
                j += len(words)
                kind = max(kind, k, key=lambda x: lexicon.PRECEDENCE.index(x) if x else -1)
                break
        else:
            return j, kind, bool(j > i and toks[i].low == ",")


def _has_verb(toks: list[_Tok], a: int, b: int) -> bool:
    return any(_kinds(t) or _guess_verb(t.low) for t in toks[a:b])


def _asyndeton(prev: _Tok, tok: _Tok) -> bool:
    """Whether `tok`, a 3sg verb right after `prev`, starts a new action with no connective."""
    if tok.low in lexicon.NOUNISH:  # "takes five forward steps", "draws circles"
        return False
    return prev.low in lexicon.DIRECTIONS - {"to"} or _is_adverb(prev.low) or "3sg" in _kinds(prev)


def _last_verb(toks: list[_Tok], clause: _Clause) -> str:
    """The verb an elliptic "then two steps back" reuses: the previous clause's own verb."""
    return toks[clause.verb].text if clause.verb is not None else clause.copied_verb


def _first_verb(toks: list[_Tok]) -> int | None:
    """The first lexicon verb, or an unknown verb right after the subject ("a man shows")."""
    n = len(toks)
    first = next((k for k in range(n) if _kinds(toks[k])), None)
    k = _match_subject(toks, 0)
    if k is None:
        return first
    while k < n and (toks[k].low in lexicon.AUX or _is_adverb(toks[k].low)):
        k += 1
    if k < n and (first is None or k < first) and _guess_verb(toks[k].low):
        return k
    return first


def _split(toks: list[_Tok]) -> list[_Clause]:
    n = len(toks)
    first = _first_verb(toks)
    lead = lexicon.LEADS.get(toks[0].low) if n and first is not None else None
    if lead and toks[1].low in ("that", "this", "which"):
        lead = None
    main_verb = first
    if lead and first is not None:
        main_verb = next((k for k in range(first + 1, n) if _kinds(toks[k]) - {"ing", "pp"}), first)
    main = _verb_kinds(toks, main_verb)
    has_aux = main_verb is not None and main_verb > 0 and toks[main_verb - 1].low in lexicon.AUX
    start = 1 if lead and lead != "simul" else 0
    clauses = [_Clause(start, n, first, False, f"lead-{lead}" if lead else "")]
    i = first + 1 if first is not None else n
    while i < n:
        cur = clauses[-1]
        j, kind, comma = _match_connective(toks, i)
        if not kind and lead and len(clauses) == 1 and _match_subject(toks, i) is not None:
            j, kind = i, "weak"  # "after walking a man runs": the main clause starts here
        elif not kind and "3sg" in main and "3sg" in _kinds(toks[i]) and _asyndeton(toks[i - 1], toks[i]):
            j, kind = i, "weak"  # "walks forward takes a turn": a comma left out
        if kind and j < n and _has_verb(toks, cur.start, i):
            found = _find_verb(toks, j, kind, main, has_aux)
            if found is not None:
                verb, own, copy = found
                cur.end = i
                copied = _last_verb(toks, cur) if copy else ""
                if copy and not copied:
                    i += 1
                    continue
                clauses.append(_Clause(j, n, verb, own, kind, comma and kind == "after", copied))
                i = (verb if verb is not None else j) + 1
                continue
        i = max(j, i + 1)
    return clauses


def _undoes(toks: list[_Tok], prev_base: str, verb_base: str, c: _Clause) -> bool:
    """Whether clause c takes back what the previous clause did, as one gesture: a raise
    lowered on the same thing, named by a pronoun right after the verb ("... and lowers it",
    "... and brings it back down"), or a dip risen back from ("squats down and stands back
    up", "crouches low and gets back up")."""
    if c.verb is None:
        return False
    rest = [t.low for t in toks[c.verb + 1 : c.end]]
    if prev_base in lexicon.DIPS:
        return verb_base in lexicon.RISES and "back" in rest and "up" in rest
    if prev_base not in lexicon.RAISING or not rest or rest[0] not in lexicon.BACK_REFERENCES:
        return False
    return verb_base in lexicon.RETURNS or (
        verb_base in lexicon.RETURNS_WITH and bool(set(rest[1:]) & lexicon.RETURN_PARTICLES))


def _same_kind(first: str, second: str) -> bool:
    """Whether verb `first` takes the object of `second` when coordinated right before it."""
    return any(first in kind and second in kind for kind in (lexicon.LIMB_MOTIONS, lexicon.HANDLING))


def _merge(caption: str, toks: list[_Tok], clauses: list[_Clause], main: frozenset[str]) -> list[_Clause]:
    """Join simultaneous clauses (rule 2) and share objects between bare verbs (rule 4)."""
    units: list[_Clause] = []
    for c in clauses:
        prev = units[-1] if units else None
        if prev is None:
            units.append(c)
            continue
        text = " ".join(t.low for t in toks[c.start : c.end])
        verb_kinds = _kinds(toks[c.verb]) if c.verb is not None else frozenset()
        prev_base = lexicon.FORMS[toks[prev.verb].low][0] if prev.verb is not None and _kinds(toks[prev.verb]) else ""
        verb_base = lexicon.FORMS[toks[c.verb].low][0] if verb_kinds else ""
        static = (
            prev_base in lexicon.STATIC
            and verb_base not in lexicon.MOVING
            and c.verb is not None
            and not any(t.low in lexicon.PARTICLES for t in toks[c.verb + 1 : c.verb + 2])
            and not any(t.low in lexicon.PARTICLES for t in toks[prev.verb + 1 : prev.end])
            and c.join == "weak"
            and not c.own_subject
        )
        manner = c.join == "weak" and not c.own_subject and verb_kinds == {"ing"} and "ing" not in main
        undo = c.join == "weak" and not c.own_subject and _undoes(toks, prev_base, verb_base, c)
        if (
            c.join == "simul"
            or prev.join == "lead-simul" and len(units) == 1
            or static
            or manner
            or undo
            or (c.join in ("weak", "simul") and any(p in text for p in lexicon.SIMULTANEOUS_PHRASES))
        ):
            prev.end = c.end
            if undo:
                prev.joined.append(c.verb)
            continue
        # "raises and lowers his arms": nothing but "and" between the verbs (not "kicks
        # twice and raises his arms", "claps, raises his arm"), and verbs of one kind
        direct = (prev.verb is not None and c.verb is not None
                  and [t.low for t in toks[prev.verb + 1 : c.verb]] == ["and"])
        if (
            direct and not c.own_subject and _same_kind(prev_base, verb_base)
            and c.verb + 1 < c.end and toks[c.verb + 1].low in lexicon.OBJECT_STARTERS
        ):
            prev.suffix = " " + caption[toks[c.verb + 1].start : toks[c.end - 1].end]
        units.append(c)
    return units


def _main_clause(clauses: list[_Clause]) -> _Clause:
    """The clause whose subject and tense the caption's segments share: the first, or after
    a lead ("after walking, ...") the first later clause naming its subject ("after lifting
    the arm and putting it down, a man claps"), else the one right after the lead."""
    if not clauses[0].join.startswith("lead-") or len(clauses) == 1:
        return clauses[0]
    return next((c for c in clauses[1:] if c.own_subject), clauses[1])


def _order(units: list[_Clause]) -> list[_Clause]:
    """Execution order (rule 3)."""
    order: list[_Clause] = []
    deferred: _Clause | None = None  # "before B, A ...": B goes after the first sentence
    sentence_start, prev_pos = 0, 0
    for idx, u in enumerate(units):
        if idx == 0 and u.join == "lead-before" and len(units) > 1:
            deferred = u
            continue
        if u.join == "sentence" and deferred is not None:
            order.append(deferred)
            deferred = None
        if u.join == "after" and order:
            pos = sentence_start if u.wide else prev_pos
            order.insert(pos, u)
            prev_pos = pos
            continue
        if u.join == "sentence":
            sentence_start = len(order)
        order.append(u)
        prev_pos = len(order) - 1
    if deferred is not None:
        order.append(deferred)
    return order


def _strip(text: str) -> str:
    """Surrounding white space and final punctuation off, nothing else."""
    return text.strip().rstrip(".,;:!? \t\n")


class RuleSegmenter:
    """Deterministic rule-based segmenter, the default backend (see the module docstring).

    Example:
        >>> RuleSegmenter().segment(["a man runs after walking."])
        [['a man walks', 'a man runs']]
    """

    name = "rule"

    def __init__(self, max_segments: int = MAX_SEGMENTS) -> None:
        if max_segments < 1:
            raise ValueError(f"RuleSegmenter: max_segments must be >= 1, got {max_segments}")
        self.max_segments = max_segments

    def segment(self, texts: list[str]) -> list[list[str]]:
        return [self.segment_one(t) for t in texts]

    def segment_one(self, caption: str) -> list[str]:
        """Ordered segments of one caption; ``[caption minus final punctuation]`` if one action."""
        if not isinstance(caption, str):
            raise TypeError(f"RuleSegmenter.segment: captions must be str, got {type(caption).__name__}")
        toks = _tokenize_actions(caption)
        if not toks:
            return [_strip(caption)]
        clauses = _split(toks)
        first = clauses[0].verb
        main_clause = _main_clause(clauses)
        main = _verb_kinds(toks, main_clause.verb)
        units = _order(_merge(caption, toks, clauses, main))
        if len(units) <= 1 or first is None:
            return [_strip(caption)]
        subject, aux = self._subject(toks, main_clause)
        texts = [(u, self._text(caption, toks, u, subject, aux, main, u is main_clause)) for u in units]
        texts = [(u, text) for u, text in texts if text]
        segments = [text for _, text in texts]
        if len(segments) > self.max_segments:
            # the tail's clauses are joined as they are, the subject said once: "a person
            # sits, then lies down", not "a person sits, then a person lies down"
            k = self.max_segments - 1
            tail = [self._text(caption, toks, u, "", aux, main, u is main_clause) for u, _ in texts[k + 1 :]]
            segments = segments[:k] + [", then ".join([segments[k], *filter(None, tail)])]
        return segments or [_strip(caption)]

    @staticmethod
    def _subject(toks: list[_Tok], clause: _Clause) -> tuple[str, str]:
        """The caption's subject ("A person") and auxiliary ("is"), from its main clause."""
        if clause.verb is None:
            return "", ""
        aux = next((t.text for t in toks[clause.start : clause.verb] if t.low in lexicon.AUX), "")
        end = _match_subject(toks, clause.start)
        if end is None or end > clause.verb:
            # no recognised noun phrase: trust a short run of plain words ("some one walks")
            words = toks[clause.start : clause.verb]
            short = 0 < len(words) <= 3 and all(t.low.isalpha() and not _is_adverb(t.low) for t in words)
            if not short or any(t.low in lexicon.AUX or _guess_verb(t.low) for t in words):
                return "", aux
            end = clause.verb
        while end > clause.start and toks[end - 1].low in lexicon.RELATIVE:
            end -= 1
        return " ".join(t.text for t in toks[clause.start : end]), aux

    @staticmethod
    def _text(caption: str, toks: list[_Tok], u: _Clause, subject: str, aux: str, main, is_main: bool) -> str:
        if u.start >= u.end:
            return ""
        body = caption[toks[u.start].start : toks[u.end - 1].end]
        verb_tok = toks[u.verb] if u.verb is not None else None
        if u.copied_verb:
            body = f"{u.copied_verb} {body}"
        elif verb_tok is not None and u.suffix:
            body = body + u.suffix
        gerund = verb_tok is not None and _kinds(verb_tok) == {"ing"}
        if verb_tok is not None and gerund and not u.own_subject and "3sg" in main and verb_tok.low in lexicon.FORMS:
            # "runs after walking" -> "walks": one tense across the segments of a caption
            # (and across a joined gesture: "raising his arm and lowering it")
            for k in sorted([u.verb, *u.joined], reverse=True):
                tok = toks[k]
                if _kinds(tok) != {"ing"} or tok.low not in lexicon.FORMS:
                    continue
                third = lexicon.THIRD[lexicon.FORMS[tok.low][0]]
                a, b = tok.start - toks[u.start].start, tok.end - toks[u.start].start
                body = body[:a] + third + body[b:]
            gerund = False
        first_word = toks[u.start].low
        if not u.own_subject and "3sg" in main and first_word in ("being", "having"):
            # "after being pushed" -> "is pushed"
            n0 = len(toks[u.start].text)
            body = ("is" if first_word == "being" else "has") + body[n0:]
        if u.own_subject or is_main or not subject:
            return _strip(body)
        prefix = f"{subject} {aux}" if aux and gerund else subject
        return _strip(f"{prefix} {body[:1].lower()}{body[1:]}")


def action_clauses(caption: str) -> list[str]:
    """The caption's actions as its own clause texts, in execution order.

    These are the clauses `RuleSegmenter` turns into segments, before it rewrites them
    (restored subjects, tense), with an elided verb put back ("then forward again" ->
    "walks forward again"): ``"a man runs after walking"`` gives ``["walking", "a man
    runs"]``. The LLM validator checks an answer's order against them. A single action
    gives one clause.
    """
    toks = _tokenize_actions(caption)
    if not toks:
        return []
    clauses = _split(toks)
    main_clause = _main_clause(clauses)
    units = _order(_merge(caption, toks, clauses, _verb_kinds(toks, main_clause.verb)))
    return [" ".join(filter(None, (u.copied_verb, caption[toks[u.start].start : toks[u.end - 1].end])))
            for u in units if u.start < u.end]


def lemma(word: str) -> str:
    """A crude lemma for comparing words across inflections ("ran" -> "run", "steps" -> "step").

    Lexicon verbs map to their base form; other words lose a plural/verb ending. Used to
    check that an LLM answer is made of the caption's words.
    """
    low = word.lower()
    if low in lexicon.FORMS:
        return lexicon.FORMS[low][0]
    for suffix, repl in (("ies", "y"), ("ing", ""), ("ed", ""), ("es", ""), ("s", "")):
        if low.endswith(suffix) and len(low) - len(suffix) >= 3:
            low = low[: -len(suffix)] + repl
            break
    if len(low) > 3 and low[-1] == low[-2] and low[-1] not in "lsz":
        low = low[:-1]  # "stepp(ing)" -> "step"
    return low[:-1] if len(low) > 3 and low.endswith("e") else low
