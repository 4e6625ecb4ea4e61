"""CTRC-constrained decoding: a ``LogitsProcessor`` that keeps a completion inside the CTRC grammar.

A language model writes a CTRC completion token by token; a small one (``small``: 27 M parameters,
trained from scratch) loses count of what it has placed and repeats an instance id, or writes a
number like ``10.0.141``: the whole layout then fails to parse (the 2 x H200 ablation: 79 % of test
outputs repeated an id). :class:`CTRCConstraint` masks the logits at the few places where the
format, or the prompt's **Object List**, decides what may come next, and leaves every other token
(positions, sizes, descriptions, the plan's wording) to the model:

| where (anchor in the text)          | what must follow (up to the next anchor)                      |
| ----------------------------------- | ------------------------------------------------------------- |
| plan line ``\\nN. Place``            | an id from the Object List not yet placed in the plan          |
| end of a plan line (``.``)           | ``\\nN+1. Place`` while ids are left, else the layout's start |
| ``"instance_id":``                  | ``root_zone`` first, then an id of the list not yet in the layout, |
|                                     | then the entry's next key                                     |
| ``"category":``                     | that id's category (``3_tissue_box_0`` -> ``tissue_box``)      |
| ``"parent_id":``                    | ``root_zone`` or an id placed earlier in the layout           |
| ``"relation_type":``                | ``near`` for a table-level object, else ``in`` / ``on``; then  |
|                                     | the description (free text, one JSON string)                  |
| ``"relative_bbox":`` / ``"bbox":``  | six JSON numbers (no leading zero, <= 4 integer digits), each  |
|                                     | ``relative_bbox`` max above its min; the root's ``bbox``: the  |
|                                     | prompt's **item_placement_zone** (a copy, not a choice)        |
| ``"relative_rotation_deg":``        | one number, then the next entry while ids are left, else the  |
|                                     | end of the objects array                                      |
| ``"item_placement_zone":``          | the prompt's zone (else four JSON numbers, max above min), ``}`` |
|                                     | and the end of text                                           |

Ids follow the MesaTask naming the data uses (``physcene.data.synth``): ``<index of the category in the
Object List>_<category>_<copy>``. A prompt without an Object List gets only the number grammar and the
``root_zone``/``near`` rules; one without an **item_placement_zone** leaves the zone to the model (the
2 x H200 ``small`` SFT model wrote a wrong zone in 512 of 512 anchor prompts, median 7.6 cm off: it
has not learnt to copy numbers from its prompt). The mask is the model's own distribution restricted
to what is allowed: under greedy decoding it changes nothing unless the model's first choice breaks
the format (then the best allowed token wins); under sampling the allowed tokens among the ``top_k``
most likely keep their relative probabilities.

Why not a grammar library (``xgrammar``, ``outlines``, ``lm-format-enforcer``): a JSON schema can
restrict ``instance_id`` to the listed ids, but "each id exactly once" and "a parent placed before
its child" are not context-free in any compact form, and those are what a small model gets wrong.
The rules here are a regular expression per anchor; the text since the anchor must stay a prefix of
its language (``regex``'s partial matching, already a transformers dependency), which a lazily built
DFA of the pattern answers at one move per token.

One module per part: :mod:`~physcene.train.constrained.grammar` (the rules, derived from
:mod:`physcene.ctrc.grammar`), :mod:`~physcene.train.constrained.automaton` (a rule's pattern as a
DFA), :mod:`~physcene.train.constrained.processor` (:class:`CTRCConstraint` and its
:class:`ConstraintStats`), :mod:`~physcene.train.constrained.sampling` (the warpers, the vocabulary
index, the rejection draw).
"""

from physcene.train.constrained.grammar import (
    Rule,
    active_rule,
    constraint_rule,
    last_anchor,
    listed_instance_ids,
    prompt_zone,
)
from physcene.train.constrained.processor import ConstraintStats, CTRCConstraint
from physcene.train.constrained.sampling import sampling_warpers

__all__ = ["CTRCConstraint", "ConstraintStats", "Rule", "active_rule", "constraint_rule", "last_anchor",
           "listed_instance_ids", "prompt_zone", "sampling_warpers"]
