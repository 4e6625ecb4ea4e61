"""Goal-oriented instructions: a template grammar, and the paper's Prompts 1-2 for an endpoint.

The paper's pipeline is caption-then-instruct: a VLM describes the scene from renders and its
scene graph (Prompt 1), then writes a user command under 30 words that implies the arrangement
without listing coordinates (Prompt 2). Offline, :func:`template_instruction` plays that role:
a per-scene-type grammar (goal, setting, mood, the scene's own hierarchies and key objects)
sampled with the record's RNG. With an OpenAI-compatible endpoint, :class:`EndpointInstructor`
runs Prompts 1-2 over the scene graph text (:func:`scene_graph_text`) through ``urllib``.
"""

from __future__ import annotations

import json
import os
import re
import urllib.error
import urllib.request
from dataclasses import dataclass

import numpy as np

from physcene.graph import ensure_hierarchy, near_references
from physcene.scene import TABLE, Scene

__all__ = [
    "EndpointInstructor",
    "MAX_WORDS",
    "PROMPT_DESCRIPTION",
    "PROMPT_INSTRUCTION",
    "check_instruction",
    "scene_graph_text",
    "template_instruction",
]

MAX_WORDS = 30

# The paper's Prompt 1 (description generation) and Prompt 2 (instruction generation), verbatim
# up to line breaks. Prompt 1 is sent with the scene graph only (no renders offline).
PROMPT_DESCRIPTION = (
    "The given images are the front view (in which the table is symmetric) and the scene graph. Only "
    "describe the layout on the tabletop; do not include the description of the table. Please describe the "
    "scene in detail, including the objects (do not describe the color/material/color of the object), their "
    "positions, and the overall layout of the desktop, including empty and densely packed are as Output the "
    "description in a paragraph between the token <description>, no more than 200 words.\n\n"
    "## Scene Graph\n{scene_graph}"
)
PROMPT_INSTRUCTION = (
    "<description>{description}<description>\n\n"
    "If I provide the assets and tabletops needed to place the task, how can I guide you through a short and "
    "concise instruction (less than 30 words) to arrange this layout (the layout that matches the above "
    "scenario description)?\n\n"
    'You said that the proposed instruction should not refer to the description, such as "as described", '
    '"Arrange items as described" and so on. Because in the real world, I only provide commands, assets, '
    "and desktops.\n\n"
    "Output the instruction between the token <instruction>"
)

# Grammar --------------------------------------------------------------------------------------
# scene type -> (settings, goals as noun phrases, goals as verb phrases)
_GOALS: dict[str, tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]] = {
    "coffee table": (
        ("coffee table", "living-room table", "lounge table"),
        (
            "a relaxed afternoon tea",
            "a cozy movie night",
            "guests dropping by",
            "a quiet reading hour",
            "a weekend brunch on the sofa",
            "a board-game evening",
        ),
        (
            "unwind with a book and a hot drink",
            "host friends for tea",
            "watch a film with snacks",
            "read magazines on a lazy Sunday",
            "serve coffee to visitors",
        ),
    ),
    "office table": (
        ("desk", "office desk", "workstation", "study desk"),
        (
            "a focused stretch of coding",
            "a late night of studying",
            "a day of video calls",
            "writing a report",
            "sketching ideas",
            "answering email over coffee",
        ),
        (
            "code for hours with reference materials within reach",
            "study for an exam",
            "take notes during meetings",
            "work comfortably on a laptop",
            "plan the week",
        ),
    ),
    "dressing table": (
        ("dressing table", "vanity", "makeup table"),
        (
            "a morning makeup routine",
            "getting ready for an evening out",
            "a skincare ritual",
            "doing my hair before work",
            "a tidy beauty corner",
        ),
        (
            "do my makeup quickly in the morning",
            "get ready for a party",
            "keep my skincare products at hand",
            "style my hair",
            "pick jewelry before going out",
        ),
    ),
    "dining table": (
        ("dining table", "dinner table", "family table"),
        (
            "a family dinner",
            "a casual lunch for two",
            "a festive dinner party",
            "Sunday breakfast",
            "a candlelit meal",
            "a buffet-style gathering",
        ),
        (
            "serve dinner for the family",
            "host a dinner party",
            "share a relaxed breakfast",
            "enjoy a romantic meal",
            "set out fruit and drinks for guests",
        ),
    ),
    "kitchen counter": (
        ("kitchen counter", "countertop", "kitchen worktop"),
        (
            "preparing a salad",
            "a quick breakfast",
            "baking on a Saturday",
            "making tea",
            "cooking a weeknight dinner",
            "a clean and efficient prep area",
        ),
        (
            "chop vegetables for dinner",
            "make breakfast in a hurry",
            "brew coffee and toast bread",
            "prepare fruit for the kids",
            "cook with everything within reach",
        ),
    ),
    "bathroom vanity": (
        ("bathroom vanity", "bathroom counter", "washbasin counter"),
        (
            "a morning routine",
            "a spa-like evening",
            "guests staying overnight",
            "brushing teeth and washing up",
            "a neat shared bathroom",
        ),
        (
            "get ready quickly in the morning",
            "relax with a long bath",
            "keep toiletries tidy around the sink",
            "share the sink with a partner",
            "welcome guests with fresh towels",
        ),
    ),
    "cashier counter": (
        ("cashier counter", "checkout counter", "shop counter"),
        ("a busy checkout shift", "a small café till", "a weekend market stall"),
        ("take payments quickly", "serve a queue of customers", "handle receipts and cash"),
    ),
    "nightstand": (
        ("nightstand", "bedside table"),
        ("a restful bedtime", "reading before sleep", "an early alarm"),
        ("read in bed before sleep", "keep essentials near the bed", "wake up on time"),
    ),
    "side table": (
        ("side table", "end table", "accent table"),
        ("a reading nook", "an evening by the sofa", "a calm corner"),
        ("read next to the armchair", "keep a drink and a lamp by the sofa", "relax in the evening"),
    ),
    "tv stand": (
        ("TV stand", "media console", "entertainment unit"),
        ("a movie night", "a gaming weekend", "a tidy living room"),
        ("play video games with friends", "watch films with good sound", "keep the media corner tidy"),
    ),
}
_MOODS = (
    "tidy",
    "cozy",
    "minimal",
    "practical",
    "inviting",
    "clutter-free",
    "well-organized",
    "relaxed",
    "functional",
    "neat",
    "warm",
    "efficient",
)
_VERBS = ("Set up", "Arrange", "Prepare", "Organize", "Lay out", "Make")
_REACH = ("within easy reach", "close at hand", "nearby", "where I can grab them", "ready to use")
_TEMPLATES = (
    "{Verb} a {mood} {setting} for {goal}{with}.",
    "{Verb} the {setting} so I can {verb_goal}{with}.",
    "I want to {verb_goal}; make the {setting} {mood}{with}.",
    "Help me {verb_goal} at a {mood} {setting}{with}.",
    "Get the {setting} ready for {goal}{with}.",
    "{Verb} a {mood} {setting} where I can {verb_goal}.",
)
_DIGITS = re.compile(r"\d")
_AN = re.compile(r"\b([Aa]) ([aeiou])")


def _phrases(scene: Scene) -> list[str]:
    """Things worth naming: the scene's hierarchies first, then its biggest table-level objects."""
    out = list(dict.fromkeys(scene.meta.get("group_phrases", [])))
    parents = {o.parent for o in scene.objects}
    roots = sorted(
        (o for o in scene.objects if o.parent in (None, TABLE) and o.instance_id not in parents),
        key=lambda o: -o.volume(),
    )
    for o in roots:
        name = o.category.replace("_", " ")
        phrase = f"the {name}"
        if phrase not in out:
            out.append(phrase)
    return out


def check_instruction(text: str) -> str | None:
    """Why ``text`` is not a valid instruction (too long, coordinates, empty), or None if it is."""
    words = text.split()
    if not words:
        return "empty"
    if len(words) >= MAX_WORDS:
        return f"{len(words)} words (must be under {MAX_WORDS})"
    if _DIGITS.search(text):
        return "contains digits (instructions never give coordinates or sizes)"
    return None


def template_instruction(scene: Scene, rng: np.random.Generator) -> str:
    """A goal-oriented instruction (< 30 words, no numbers) for ``scene`` from the grammar."""
    key = scene.scene_type.strip().lower().replace("_", " ")
    settings, goals, verb_goals = _GOALS.get(
        key, ((key or "table",), ("a tidy tabletop",), ("keep things tidy",))
    )
    phrases = _phrases(scene)
    pick = lambda seq: seq[int(rng.integers(len(seq)))]  # noqa: E731
    for _ in range(8):
        with_clause = ""
        if phrases and rng.random() < 0.8:
            k = min(len(phrases), 1 + int(rng.integers(2)))
            named = [phrases[int(i)] for i in sorted(rng.choice(min(len(phrases), 4), size=k, replace=False))]
            joined = " and ".join(named)
            with_clause = pick(
                (
                    f", with {joined} {pick(_REACH)}",
                    f", keeping {joined} {pick(_REACH)}",
                    f", including {joined}",
                )
            )
        text = pick(_TEMPLATES).format(
            Verb=pick(_VERBS),
            mood=pick(_MOODS),
            setting=pick(settings),
            goal=pick(goals),
            verb_goal=pick(verb_goals),
            **{"with": with_clause},
        )
        text = _AN.sub(lambda m: m.group(1) + "n " + m.group(2), text)
        text = text[0].upper() + text[1:]
        if check_instruction(text) is None:
            return text
    return f"{pick(_VERBS)} a {pick(_MOODS)} {pick(settings)} for {pick(goals)}."


def scene_graph_text(scene: Scene) -> str:
    """The scene graph in the paper's text form (Appendix example): near relations between
    table-level objects, within-stack relations, and each object's coarse place."""
    scene = ensure_hierarchy(scene)
    lines = ["# ========== Stack-level Horizontal Relationships =========="]
    for iid, ref in near_references(scene).items():
        if ref is not None:
            lines.append(f"({iid}, {ref[1]}, {ref[0]})")
    lines.append("# ========== Within-Stack Relationships ==========")
    for o in scene.objects:
        if o.parent not in (None, TABLE):
            lines.append(f"({o.instance_id}, {o.relation}, {o.parent})")
    lines.append("# ========== Object Absolute Properties ==========")
    cx, cy = scene.zone.center
    for o in scene.objects:
        dy, dx = (o.center[1] - cy) / scene.zone.depth, (o.center[0] - cx) / scene.zone.width
        fy = "behind" if dy > 1 / 6 else "front" if dy < -1 / 6 else ""
        fx = "right" if dx > 1 / 6 else "left" if dx < -1 / 6 else ""
        where = "_".join(p for p in (fy, fx) if p) or "center"
        lines.append(f"({o.instance_id}, is at, {where})")
    return "\n".join(lines)


@dataclass(frozen=True, kw_only=True)
class EndpointInstructor:
    """Caption-then-instruct through an OpenAI-compatible ``/chat/completions`` endpoint.

    ``base_url`` e.g. ``http://localhost:8000/v1``; the key is read from the environment
    variable named by ``api_key_env`` (never stored). Errors raise :class:`RuntimeError` naming
    the endpoint; a reply without the ``<instruction>`` tokens or over 30 words raises too, so
    the caller can fall back to the grammar.
    """

    base_url: str
    model: str
    api_key_env: str = "OPENAI_API_KEY"
    timeout_s: float = 60.0
    temperature: float = 0.7

    def _chat(self, prompt: str) -> str:
        body = json.dumps(
            {
                "model": self.model,
                "temperature": self.temperature,
                "messages": [{"role": "user", "content": prompt}],
            }
        ).encode()
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(self.api_key_env)
        if key:
            headers["Authorization"] = f"Bearer {key}"
        url = self.base_url.rstrip("/") + "/chat/completions"
        request = urllib.request.Request(url, data=body, headers=headers, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as reply:
                data = json.loads(reply.read().decode("utf-8"))
            return str(data["choices"][0]["message"]["content"])
        except (urllib.error.URLError, TimeoutError, KeyError, IndexError, ValueError) as exc:
            raise RuntimeError(f"endpoint {url}: {exc}") from exc

    @staticmethod
    def _between(text: str, token: str) -> str | None:
        parts = text.split(f"<{token}>")
        if len(parts) >= 2 and parts[1].strip():
            return re.sub(rf"</?{token}>", "", parts[1]).strip()
        return None

    def describe(self, scene: Scene) -> str:
        """Prompt 1: a < 200-word description of the layout."""
        reply = self._chat(PROMPT_DESCRIPTION.format(scene_graph=scene_graph_text(scene)))
        return self._between(reply, "description") or reply.strip()

    def instruct(self, scene: Scene) -> tuple[str, str]:
        """(description, instruction) via Prompts 1 and 2."""
        description = self.describe(scene)
        reply = self._chat(PROMPT_INSTRUCTION.format(description=description))
        instruction = self._between(reply, "instruction")
        if instruction is None:
            raise RuntimeError(f"endpoint {self.base_url}: no <instruction> in reply {reply[:120]!r}")
        problem = check_instruction(instruction)
        if problem:
            raise RuntimeError(f"endpoint {self.base_url}: instruction rejected ({problem}): {instruction!r}")
        return description, instruction
