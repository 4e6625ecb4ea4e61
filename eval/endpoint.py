"""The endpoint judge: the paper's Prompts 4 and 5 (verbatim) to any OpenAI-compatible
chat-completions endpoint with image input, over the front + perspective renders.

:class:`EndpointJudge` parses the JSON scores (:func:`parse_judge_reply`), retries with
exponential backoff (:func:`post_chat`) and caches answers on disk by content hash. Like the
rule judge (:mod:`physcene.eval.judges`) it returns ``{"CwT": .., "OSR": .., "PPI": .., "LCR": ..,
"OV": .., "avg": ..}``, or ``{"error": reason}`` (and ``avg`` NaN) instead of raising.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from physcene.eval.judges import EvalCase, JudgeError
from physcene.eval.metrics import CRITERIA, ScenePhysics
from physcene.scene import Scene

__all__ = ["SYSTEM_PROMPT", "USER_PROMPT", "EndpointJudge", "chat_url", "parse_judge_reply", "post_chat",
           "reply_text"]

SYSTEM_PROMPT = """You are an expert evaluator for 3D desktop scene layouts. Your task is to analyze desktop scenes and provide a detailed assessment based on specific criteria. Please carefully examine the provided front and perspective views of the desktop scene, along with the task description. 
Analyze how well the scene layout aligns with the intended task. Consider both the visible objects and their arrangement in relation to the task requirements. 
You must provide numerical scores (1-10) for each criterion along with brief explanations to justify your ratings. 
Be objective and consistent in your evaluation across different scenes."""  # noqa: E501, W291

USER_PROMPT = """You are an expert at evaluating desktop scene layouts. Given both a front and a perspective view of a desktop scene, and a description of the tasks that can be performed on the desktop, please rate the scene`s quality on a scale from 1 (poor) to 10 (excellent) according to the following criteria. For each criterion, consider both views:  

1. **Consistency with Task:** Does the scene layout (objects present, their arrangement and relevance) align well with the provided task description (environment, objects, goals)? 
- High score (7-10): All key objects are present, their arrangement is entirely logical and directly contributes to the task. The scene perfectly reflects the task requirements. 
- Mid score (4-6): Most key objects are present and generally align with the task, but there might be minor inconsistencies or some less relevant elements. 
- Low score (1-3): Significant deviations from the task description. Important objects are missing, or the arrangement is largely unrelated or illogical for the task.  

2. **Object Size Reasonableness:** Are the sizes of the objects in the scene highly realistic, both relative to each other and to the overall desktop environment? Are they consistent across all objects? 
- High score (7-10): All objects have highly realistic and perfectly proportionate sizes. No inconsistencies are noticeable. 
- Mid score (4-6): Most objects have reasonable sizes, but there might be slight or occasional inaccuracies in proportion for some items. 
- Low score (1-3): Multiple or glaring inconsistencies in object sizes. Some objects are obviously and significantly too large or too small, severely impacting realism.  

3. **Placement Plausibility & Intersections:** Are objects placed stably and naturally on surfaces (e.g., not floating)? Are there any signs of unnatural intersection or penetration between objects? Objects should appear physically grounded and interact realistically. 
- High score (7-10): All objects rest naturally and stably on surfaces. No aphysical interactions or intersections are visible. Objects are well-supported. 
- Mid score (4-6): Most objects are placed plausibly, but there might be minor, subtle issues like slight floating or minimal, non-critical intersections. 
- Low score (1-3): Obvious or frequent issues with object placement. Objects float, unnaturally overlap, or clearly penetrate each other, indicating a lack of physical realism.  

4. **Layout Coherence & Realism:** Does the overall arrangement look highly functional, convincingly realistic, and typical for the task context? Does it avoid being overly staged, unnaturally sparse, or chaotically cluttered? 
- High score (7-10): Layout is highly functional, convincingly realistic, and well-suited for the described task. The scene feels authentic and natural. 
- Mid score (4-6): The layout is generally coherent and functional, but might lack some fine-tuning for optimal realism or could appear somewhat staged. 
- Low score (1-3): Layout is chaotic, illogical, too empty, overly cluttered, or looks clearly artificial and unrealistic for the task.

5. **Object Visibility:** Are important objects mentioned in the task easily and unambiguously identifiable in at least one of the views? Are they sufficiently well-lit and resolved? 
- High score (7-10): All key objects are clearly and unambiguously visible and identifiable. Their details are well-resolved. 
- Mid score (4-6): Most important objects are visible, but some might require closer inspection to identify. 
- Low score (1-3): Critical objects are very difficult to identify, or completely missing from view, hindering task understanding.  

**Task Description:**  

{task_description}

**Please provide a single score (1-10) for each criterion.** 
**Strictly output in the following JSON format with no additional text:**  

{  
    "Evaluation": [ 
        {
            "criterion": "Consistency with Task", 
            "explanation": "Your detailed explanation here", 
            "score": X
        }, 
        {  
            "criterion": "Object Size Reasonableness", 
            "explanation": "Your detailed explanation here", 
            "score": X
        }, 
        {  
            "criterion": "Placement Plausibility & Intersections", 
            "explanation": "Your detailed explanation here", 
            "score": X
        }, 
        {  
            "criterion": "Layout Coherence & Realism", 
            "explanation": "Your detailed explanation here", 
            "score": X 
        }, 
        {  
            "criterion": "Object Visibility", 
            "explanation": "Your detailed explanation here", 
            "score": X 
        }
    ] 
}  

**Where X is an integer score from 1 to 10. Do not output anything else.**"""  # noqa: E501, W291

# Criterion names as Prompt 5 spells them -> the paper's table abbreviations.
_CRITERION_KEYS = {"consistency with task": "CwT", "object size reasonableness": "OSR",
                   "placement plausibility & intersections": "PPI", "layout coherence & realism": "LCR",
                   "object visibility": "OV"}


def parse_judge_reply(text: str) -> dict:
    """Scores from a judge reply in Prompt 5's JSON format (code fences and chatter tolerated).
    Returns the five criteria and ``avg``, or ``{"error": reason, "avg": nan}``; never raises."""
    start, end = text.find("{"), text.rfind("}")
    if start < 0 or end <= start:
        return {"error": "no JSON object in the judge reply", "avg": float("nan")}
    try:
        data = json.loads(text[start:end + 1])
    except json.JSONDecodeError as exc:
        return {"error": f"judge reply is not valid JSON: {exc.msg} at char {exc.pos}", "avg": float("nan")}
    items = data.get("Evaluation") if isinstance(data, dict) else None
    if not isinstance(items, list):
        return {"error": "judge reply has no 'Evaluation' list", "avg": float("nan")}
    out = {}
    for item in items:
        if not isinstance(item, dict):
            continue
        key = _CRITERION_KEYS.get(str(item.get("criterion", "")).strip().lower())
        try:
            score = float(item.get("score"))
        except (TypeError, ValueError):
            continue
        if key and math.isfinite(score):
            out[key] = float(np.clip(score, 1.0, 10.0))
    missing = [c for c in CRITERIA if c not in out]
    if missing:
        return {"error": f"judge reply lacks scores for {missing}", "avg": float("nan")}
    out["avg"] = round(float(np.mean([out[c] for c in CRITERIA])), 4)
    return out


def chat_url(base_url: str) -> str:
    url = base_url.rstrip("/")
    if not url.startswith(("http://", "https://")):
        raise JudgeError(f"endpoint URL must start with http:// or https://, got {base_url!r}")
    return url if url.endswith("/chat/completions") else url + "/chat/completions"


def post_chat(url: str, payload: dict, *, api_key: str | None = None, timeout_s: float = 120.0,
              retries: int = 4, backoff_s: float = 1.0) -> dict:
    """POST a chat-completions request; retry on 429/5xx and network errors with exponential
    backoff (``backoff_s``·2^k). Returns the decoded response JSON; raises ``OSError`` when every
    try failed or the server refused the request (4xx other than 429)."""
    body = json.dumps(payload).encode()
    headers = {"Content-Type": "application/json"}
    if api_key:
        headers["Authorization"] = f"Bearer {api_key}"
    last: Exception | None = None
    for attempt in range(retries + 1):
        if attempt:
            time.sleep(backoff_s * 2 ** (attempt - 1))
        req = urllib.request.Request(url, data=body, headers=headers, method="POST")
        try:
            with urllib.request.urlopen(req, timeout=timeout_s) as resp:
                return json.loads(resp.read().decode())
        except urllib.error.HTTPError as exc:
            last = exc
            if exc.code != 429 and exc.code < 500:
                raise OSError(f"{url}: HTTP {exc.code}: {exc.read()[:200]!r}") from exc
        except (urllib.error.URLError, TimeoutError, ConnectionError, json.JSONDecodeError) as exc:
            last = exc
    raise OSError(f"{url}: no answer after {retries + 1} tries: {last}")


def reply_text(response: dict) -> str:
    """The assistant message text of a chat-completions response ('' if absent)."""
    try:
        content = response["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        return ""
    if isinstance(content, list):  # some servers return content parts
        return "".join(p.get("text", "") for p in content if isinstance(p, dict))
    return content if isinstance(content, str) else ""


@dataclass
class EndpointJudge:
    """VLM judge over an OpenAI-compatible ``/chat/completions`` endpoint (paper Prompts 4-5).

    ``base_url`` like ``http://127.0.0.1:8000/v1`` (``/chat/completions`` is appended unless
    present). The API key is read from the environment variable named ``api_key_env``.
    Answers are cached in ``cache_dir`` under the SHA-256 of the request body.
    """

    base_url: str
    model: str = "gpt-4o"
    api_key_env: str = "PHYSCENE_JUDGE_API_KEY"
    cache_dir: str | os.PathLike | None = None
    retries: int = 4
    backoff_s: float = 1.0
    timeout_s: float = 120.0
    temperature: float = 0.0
    image_size: tuple[int, int] = (512, 384)
    name: str = "endpoint"
    stats: dict = field(default_factory=lambda: {"requests": 0, "cache_hits": 0})

    def __post_init__(self):
        self.url = chat_url(self.base_url)

    def request(self, task_description: str, images: Sequence[bytes]) -> dict:
        """The chat-completions payload: Prompt 4 as system, Prompt 5 + the PNGs as user."""
        parts = [{"type": "text", "text": USER_PROMPT.replace("{task_description}", task_description)}]
        for png in images:
            data = base64.b64encode(png).decode()
            parts.append({"type": "image_url", "image_url": {"url": f"data:image/png;base64,{data}"}})
        return {"model": self.model, "temperature": self.temperature,
                "messages": [{"role": "system", "content": SYSTEM_PROMPT},
                             {"role": "user", "content": parts}]}

    def _cached(self, key: str) -> Path | None:
        if self.cache_dir is None:
            return None
        d = Path(self.cache_dir)
        d.mkdir(parents=True, exist_ok=True)
        return d / f"{key}.json"

    def ask(self, task_description: str, images: Sequence[bytes]) -> dict:
        """Scores for one (description, images) pair, from the cache when the same request was
        answered before."""
        payload = self.request(task_description, images)
        key = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
        path = self._cached(key)
        if path is not None and path.is_file():
            self.stats["cache_hits"] += 1
            return parse_judge_reply(json.loads(path.read_text())["reply"])
        self.stats["requests"] += 1
        try:
            response = post_chat(self.url, payload, api_key=os.environ.get(self.api_key_env),
                                 timeout_s=self.timeout_s, retries=self.retries, backoff_s=self.backoff_s)
        except OSError as exc:
            return {"error": str(exc), "avg": float("nan")}
        text = reply_text(response)
        scores = parse_judge_reply(text)
        if path is not None and "error" not in scores:  # only good answers are worth keeping
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps({"model": self.model, "reply": text}))
            os.replace(tmp, path)
        return scores

    def score(self, scene: Scene, case: EvalCase, physics: ScenePhysics | None = None) -> dict:
        """Render the front and perspective views and ask the endpoint."""
        from physcene.eval.render import png_bytes, render_image

        images = [png_bytes(render_image(scene, view, size=self.image_size))
                  for view in ("front", "perspective")]
        return self.ask(case.instruction or scene.instruction, images)
