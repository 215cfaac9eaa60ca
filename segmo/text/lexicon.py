"""Word lists behind `RuleSegmenter`: a verb lexicon with its inflections, the other word
classes the rules look at, and the connectives with their kinds.

Kept apart from `segmo.text.rules` so that the rules read as rules; the lists are data.
"""

from __future__ import annotations

# ---------------------------------------------------------------- verb lexicon
# Regular verbs, base form. Words that are mostly nouns/directions in captions
# ("left", "hand", "back", "forward", "figure") are left out on purpose.
REGULAR = """
walk jog run sprint march stroll stride step stomp tiptoe sneak limp shuffle stagger stumble
trip fall jump hop skip leap bounce land climb crawl roll flip tumble slide slip glide skate
ski swim fly turn rotate spin twirl pivot circle twist lean bend bow crouch squat kneel sit
stand lie rise get go come move return stop pause halt wait rest stay remain start begin
continue proceed keep try perform do make take wave clap point reach grab pick place put
lift raise lower drop throw toss catch push pull carry hold kick punch hit strike box jab
block dodge duck swing shake nod stretch extend fold cross flex flap wiggle wobble sway rock
dance balance lunge look glance stare watch touch tap pat rub scratch wipe brush wash clean
drink eat play shoot aim fight wrestle hug salute gesture signal beckon shrug open close
answer talk call yell sing pray juggle dribble pass stir pour cut chop sweep mop paint draw
write type sew knit fish row paddle pedal drive ride steer imitate mimic act pretend
shiver tremble jiggle bob swat slap stab thrust sprawl collapse recover regain straighten
crank hammer saw dig shovel lay descend ascend mount dismount enter exit leave sidestep
backpedal retreat approach accelerate decelerate slow speed hurry rush dash charge chase
flail swirl wind unwind cartwheel somersault spread relax tilt arch curl hunch slouch
squeeze shove trudge wander pace jerk kneel hover sneeze cough stamp grasp release shoot
bring set drag spin lift flick swipe swat sway knock shield cover hide clean comb dust
compensate counterbalance end avoid stroke receive let bump search repeat gain protect assume
inspect beat change support check curve use circulate evade find yank stoop give listen form
show need knee drift prepare practice practise simulate demonstrate execute complete reverse
side-step
"""
# "base 3sg past participle gerund" where the regular rules fail
IRREGULAR = {
    e.split()[0]: tuple(e.split()[1:])
    for e in """
run runs ran run running | sit sits sat sat sitting | stand stands stood stood standing |
lie lies lay lain lying | lay lays laid laid laying | fall falls fell fallen falling |
rise rises rose risen rising | get gets got gotten getting | go goes went gone going |
come comes came come coming | take takes took taken taking | make makes made made making |
do does did done doing | throw throws threw thrown throwing |
catch catches caught caught catching | hold holds held held holding |
hit hits hit hit hitting | strike strikes struck struck striking |
swing swings swung swung swinging | shake shakes shook shaken shaking |
bend bends bent bent bending | spin spins spun spun spinning |
kneel kneels knelt knelt kneeling | fly flies flew flown flying |
swim swims swam swum swimming | leap leaps leapt leapt leaping |
begin begins began begun beginning | keep keeps kept kept keeping | put puts put put putting |
cut cuts cut cut cutting | set sets set set setting | bring brings brought brought bringing |
drink drinks drank drunk drinking | eat eats ate eaten eating | sing sings sang sung singing |
write writes wrote written writing | draw draws drew drawn drawing |
drive drives drove driven driving | ride rides rode ridden riding |
shoot shoots shot shot shooting | sweep sweeps swept swept sweeping |
wind winds wound wound winding | dig digs dug dug digging | slide slides slid slid sliding |
spread spreads spread spread spreading | hide hides hid hidden hiding |
stride strides strode stridden striding | leave leaves left left leaving |
seem seems seemed seemed seeming | sneak sneaks snuck snuck sneaking | let lets let let letting
""".split("|")
}
# Words an inflection would make that are really nouns/directions in captions.
NOT_VERB_FORMS = {"left", "leaves", "lay"}
DOUBLED = set("""jog step trip hop skip flip slip stop pat rub tap nod flap bob drop
shrug grab jab swat slap chop mop knit dig plan drag stab side-step clap hug stir sidestep squat""".split())
STATIC = {"stand", "sit", "kneel", "lie", "stay", "remain", "hover", "wait", "rest", "balance"}
# after a static posture these start a new action, not a simultaneous one ("stands and walks away")
MOVING = set("""walk run jog sprint march jump hop skip leap crawl climb fall step stride limp stumble go
come leave turn spin rise get stand sit lie kneel squat crouch""".split())
PARTICLES = {"up", "down", "back", "over", "onto", "off", "out"}
# One gesture, one segment: a verb that takes back what the one before did. A raise
# lowered on the same thing named by a pronoun ("raises his arm and lowers it"; RETURNS_WITH
# need "down"/"back": "puts it down", not "puts it on the table"), or a dip risen back from
# ("squats down and stands back up"; not "sits down and stands up", two postures).
RAISING = {"raise", "lift"}
RETURNS = {"lower", "drop"}
RETURNS_WITH = {"put", "bring", "return", "move"}
RETURN_PARTICLES = {"down", "back"}
BACK_REFERENCES = {"it", "them"}
DIPS = {"squat", "crouch", "bend", "duck", "stoop"}
RISES = {"stand", "get", "come", "rise", "straighten"}
# Verbs coordinated right before another ("raises and lowers his arms") take its object
# only when both are of one kind: both move a limb, or both handle a thing ("catches and
# throws the ball"). "waves and kicks his right leg" waves no leg, and "stretches and
# performs a squat" stretches no squat.
LIMB_MOTIONS = set("""raise lift lower swing bend move extend stretch rotate twist shake open
close cross fold flex spread straighten flap wiggle""".split())
HANDLING = set("""pick put drop throw toss catch push pull grab hold rub wipe tap touch
release""".split())


def inflect(base: str) -> dict[str, set[str]]:
    if base in IRREGULAR:
        s3, past, pp, ing = IRREGULAR[base]
        return {base: {"base"}, s3: {"3sg"}, past: {"past"}, pp: {"pp"}, ing: {"ing"}}
    if base.endswith(("s", "x", "z", "ch", "sh", "o")):
        s3 = base + "es"
    elif base.endswith("y") and base[-2] not in "aeiou":
        s3 = base[:-1] + "ies"
    else:
        s3 = base + "s"
    if base in DOUBLED:
        ing, past = base + base[-1] + "ing", base + base[-1] + "ed"
    elif base.endswith("ie"):
        ing, past = base[:-2] + "ying", base + "d"
    elif base.endswith("e") and not base.endswith(("ee", "ye", "oe")):
        ing, past = base[:-1] + "ing", base + "d"
    elif base.endswith("y") and base[-2] not in "aeiou":
        ing, past = base + "ing", base[:-1] + "ied"
    else:
        ing, past = base + "ing", base + "ed"
    return {base: {"base"}, s3: {"3sg"}, past: {"past", "pp"}, ing: {"ing"}}


def build_lexicon() -> tuple[dict[str, tuple[str, frozenset[str]]], dict[str, str]]:
    forms: dict[str, tuple[str, set[str]]] = {}
    third: dict[str, str] = {}
    for base in dict.fromkeys(REGULAR.split() + list(IRREGULAR)):
        for form, kinds in inflect(base).items():
            if form in NOT_VERB_FORMS:
                continue
            entry = forms.setdefault(form, (base, set()))
            entry[1].update(kinds)
        third[base] = next(f for f, k in inflect(base).items() if "3sg" in k)
    return {f: (b, frozenset(k)) for f, (b, k) in forms.items()}, third


FORMS, THIRD = build_lexicon()

# ---------------------------------------------------------------- other word classes
PRONOUNS = {"he", "she", "they", "it", "someone", "somebody", "everyone", "i", "we"}
DETERMINERS = {"a", "an", "the", "this", "that", "one", "some", "another", "our"}
SUBJECT_NOUNS = set("""person man woman human figure subject someone somebody individual guy
lady boy girl character people persons child kid actor player dancer humanoid avatar body
performer athlete men women""".split())
RELATIVE = {"that", "who", "which"}
AUX = {"is", "are", "was", "were", "be", "been", "being", "am"}
ADVERBS = set("""then also again still just first immediately now once twice very really
almost nearly simply slowly quickly soon later suddenly finally afterwards afterward
eventually next gradually repeatedly continuously""".split())
NOT_GUESSABLE = set("""his her their its this that these those steps times degrees meters
metres arms hands legs feet is was has as us its yes thus always sideways towards upwards
downwards backwards forwards afterwards outwards inwards onwards stairs series something
anything nothing everything thing ceiling""".split())
DIRECTIONS = set("""back backward backwards forward forwards left right around sideways away
up down to towards home""".split())
# after "then", these start an action that reuses the previous verb ("then two steps back")
COPYABLE = DIRECTIONS | set("a an one two three four five six another 1 2 3 4 5 6".split())
OBJECT_STARTERS = set("""his her their the a an both its one left right arms hands arm hand
leg legs something an object objects""".split())
# 3sg verb forms that are mostly plural nouns when they follow another word directly
NOUNISH = set("""steps strides circles punches gestures moves curves hops kicks jumps waves squats
lunges rounds stops bows dances swings rolls flips claps points lifts pushes pulls
throws catches""".split())
SIMULTANEOUS_PHRASES = ("at the same time", "simultaneously", "meanwhile", "in the meantime")

# connective token sequences -> kind; longer entries are tried first
CONNECTIVES: list[tuple[tuple[str, ...], str]] = sorted(
    [
        (("at", "the", "same", "time"), "simul"), (("in", "the", "meantime"), "simul"),
        (("after", "that"), "strong"), (("after", "this"), "strong"), (("after", "which"), "strong"),
        (("followed", "by"), "strong"), (("and",), "weak"), ((",",), "weak"), (("but",), "weak"),
        (("then",), "strong"), (("afterwards",), "strong"), (("afterward",), "strong"),
        (("finally",), "strong"), (("lastly",), "strong"), (("next",), "strong"),
        (("later",), "strong"), (("subsequently",), "strong"), (("thereafter",), "strong"),
        ((";",), "sentence"), ((".",), "sentence"), (("!",), "sentence"), (("?",), "sentence"),
        (("before",), "before"), (("after",), "after"), (("while",), "simul"),
        (("whilst",), "simul"), (("as",), "simul"), (("meanwhile",), "simul"),
        (("simultaneously",), "simul"), (("during",), "simul"),
    ],
    key=lambda item: -len(item[0]),
)
PRECEDENCE = ["weak", "strong", "sentence", "before", "after", "simul"]
LEADS = {"after": "after", "before": "before", "while": "simul", "whilst": "simul", "as": "simul"}
