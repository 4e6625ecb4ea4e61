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
import http.client
import ipaddress
import json
import math
import os
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from physcene.eval.judges import EvalCase, JudgeError
from physcene.eval.metrics import CRITERIA, ScenePhysics
from physcene.files import write_atomic
from physcene.scene import Scene

__all__ = ["SYSTEM_PROMPT", "USER_PROMPT", "AuthStrippingRedirectHandler", "EndpointError", "EndpointJudge",
           "chat_url", "is_loopback", "parse_judge_reply", "post_chat", "reply_text", "should_strip_auth",
           "warn_if_plain_http"]

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


def _no_score(reason: str) -> dict:
    return {"error": reason, "avg": float("nan")}


def parse_judge_reply(text) -> dict:
    """Scores from a judge reply in Prompt 5's JSON format (code fences and chatter tolerated).
    Returns the five criteria and ``avg``, or ``{"error": reason, "avg": nan}`` (no score: a failed
    judgement) for any reply that is not that: not a string, no JSON, JSON of another shape, a
    score that is not a finite number. Never raises."""
    if not isinstance(text, str):
        return _no_score(f"judge reply is not text but {type(text).__name__}")
    start, end = text.find("{"), text.rfind("}")
    if start < 0 or end <= start:
        return _no_score("no JSON object in the judge reply")
    try:
        data = json.loads(text[start:end + 1])
    except json.JSONDecodeError as exc:
        return _no_score(f"judge reply is not valid JSON: {exc.msg} at char {exc.pos}")
    except (ValueError, RecursionError) as exc:  # a 5,000-digit integer; brackets nested past the stack
        return _no_score(f"judge reply is not readable JSON: {type(exc).__name__}")
    items = data.get("Evaluation") if isinstance(data, dict) else None
    if not isinstance(items, list):
        return _no_score("judge reply has no 'Evaluation' list")
    out = {}
    for item in items:
        if not isinstance(item, dict):
            continue
        key = _CRITERION_KEYS.get(str(item.get("criterion", "")).strip().lower())
        score = item.get("score")
        if isinstance(score, bool) or not isinstance(score, (int, float, str)):
            continue
        try:
            score = float(score)
        except (ValueError, OverflowError):  # "eight"; an integer beyond the float range
            continue
        if key and math.isfinite(score):
            out[key] = float(np.clip(score, 1.0, 10.0))
    missing = [c for c in CRITERIA if c not in out]
    if missing:
        return _no_score(f"judge reply lacks scores for {missing}")
    out["avg"] = round(float(np.mean([out[c] for c in CRITERIA])), 4)
    return out


def chat_url(base_url: str) -> str:
    """``base_url``'s chat-completions address (``/chat/completions`` appended unless present). A
    plain-http address off this machine gets one warning on stderr (:func:`warn_if_plain_http`)."""
    url = str(base_url).strip().rstrip("/")
    if not url.startswith(("http://", "https://")) or not urllib.parse.urlsplit(url).hostname:
        raise JudgeError(f"endpoint URL must be http://host[:port]/... or https://..., got {base_url!r}")
    warn_if_plain_http(url)
    return url if url.endswith("/chat/completions") else url + "/chat/completions"


_WARNED: set[str] = set()


def is_loopback(host: str | None) -> bool:
    """Whether ``host`` names this machine (``localhost``, 127.0.0.0/8, ::1)."""
    if not host:
        return False
    if host.rstrip(".").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def warn_if_plain_http(url: str) -> bool:
    """One line on stderr (once per host and port) when ``url`` is plain http to another machine:
    its prompts, renders and API key cross the network unencrypted. Returns whether it warned."""
    parts = urllib.parse.urlsplit(url)
    where = f"{parts.hostname}:{parts.port or 80}"
    if parts.scheme != "http" or is_loopback(parts.hostname) or where in _WARNED:
        return False
    _WARNED.add(where)
    print(f"physcene: warning: endpoint {url} is plain http on another machine: requests and the API key "
          "travel unencrypted (use https://)", file=sys.stderr)
    return True


def should_strip_auth(old_url: str, new_url: str) -> bool:
    """Whether a redirect from ``old_url`` to ``new_url`` must drop the Authorization header: the
    scheme, host or port changed (requests' ``SessionRedirectMixin.should_strip_auth``, with its two
    allowances: http -> https on the default ports, and an explicit default port is no change)."""
    old, new = urllib.parse.urlsplit(old_url), urllib.parse.urlsplit(new_url)
    if old.hostname != new.hostname:
        return True
    if old.scheme == "http" and old.port in (80, None) and new.scheme == "https" and new.port in (443, None):
        return False
    default = ({"http": 80, "https": 443}.get(old.scheme), None)
    if old.scheme == new.scheme and old.port in default and new.port in default:
        return False
    return old.port != new.port or old.scheme != new.scheme


class AuthStrippingRedirectHandler(urllib.request.HTTPRedirectHandler):
    """urllib's redirect handler copies every header, the API key included, to wherever the
    server points: this one drops Authorization when the redirect leaves the scheme, host and port
    the key was meant for (:func:`should_strip_auth`)."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):
        new = super().redirect_request(req, fp, code, msg, headers, newurl)
        if new is not None and should_strip_auth(req.full_url, new.full_url):
            new.remove_header("Authorization")
        return new


_OPENER = urllib.request.build_opener(AuthStrippingRedirectHandler)


class EndpointError(OSError):
    """A chat-completions request that got no answer: ``"{url}: {reason}"``. ``reached``: False when
    no server answered at all (connection refused, unknown host, timeout), True when one answered
    with an error."""

    def __init__(self, url: str, reason: str, *, reached: bool):
        super().__init__(f"{url}: {reason}")
        self.url, self.reason, self.reached = url, reason, reached


def post_chat(url: str, payload: dict, *, api_key: str | None = None, timeout_s: float = 120.0,
              retries: int = 4, backoff_s: float = 1.0) -> dict:
    """POST a chat-completions request; retry on 429/5xx and network errors with exponential
    backoff (``backoff_s``·2^k). Returns the decoded response JSON; raises :class:`EndpointError`
    (an ``OSError``) when every try failed or the server refused the request (4xx other than 429).
    The API key goes only to ``url``'s scheme, host and port, never to where a redirect points."""
    body = json.dumps(payload).encode()
    headers = {"Content-Type": "application/json"}
    if api_key:
        headers["Authorization"] = f"Bearer {api_key}"
    reason, reached = "", False
    for attempt in range(retries + 1):
        if attempt:
            time.sleep(backoff_s * 2 ** (attempt - 1))
        req = urllib.request.Request(url, data=body, headers=headers, method="POST")
        try:
            with _OPENER.open(req, timeout=timeout_s) as resp:
                return json.loads(resp.read().decode())
        except urllib.error.HTTPError as exc:
            reason, reached = f"HTTP {exc.code} {exc.reason}", True
            if exc.code != 429 and exc.code < 500:
                raise EndpointError(url, f"{reason}: {exc.read()[:200]!r}", reached=True) from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            reason, reached = f"the answer is not JSON ({exc})", True
        except urllib.error.URLError as exc:
            reason, reached = f"no server answered ({exc.reason})", False
        except (TimeoutError, ConnectionError, http.client.HTTPException) as exc:
            reason, reached = f"no answer ({type(exc).__name__}: {exc})", False
    tries = "1 try" if retries == 0 else f"{retries + 1} tries"
    raise EndpointError(url, f"{reason} after {tries}", reached=reached)


def reply_text(response: dict) -> str:
    """The assistant message text of a chat-completions response ('' if absent)."""
    try:
        content = response["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        return ""
    if isinstance(content, list):  # some servers return content parts
        return "".join(p["text"] for p in content if isinstance(p, dict) and isinstance(p.get("text"), str))
    return content if isinstance(content, str) else ""


@dataclass
class EndpointJudge:
    """VLM judge over an OpenAI-compatible ``/chat/completions`` endpoint (paper Prompts 4-5).

    ``base_url`` like ``http://127.0.0.1:8000/v1`` (``/chat/completions`` is appended unless
    present). The API key is read from the environment variable named ``api_key_env``. A request
    that gets no answer is ``{"error": .., "avg": nan, "request_failed": True}``; a reply without
    scores ``{"error": .., "avg": nan}``.
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
        return Path(self.cache_dir) / f"{key}.json"

    def ask(self, task_description: str, images: Sequence[bytes]) -> dict:
        """Scores for one (description, images) pair, from the cache when the same request was
        answered before."""
        payload = self.request(task_description, images)
        key = hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
        path = self._cached(key)
        if path is not None and path.is_file():
            try:
                cached = json.loads(path.read_text())["reply"]
            except (OSError, ValueError, KeyError, TypeError):  # an unreadable entry is asked again
                cached = None
            if isinstance(cached, str):
                self.stats["cache_hits"] += 1
                return parse_judge_reply(cached)
        self.stats["requests"] += 1
        try:
            response = post_chat(self.url, payload, api_key=os.environ.get(self.api_key_env),
                                 timeout_s=self.timeout_s, retries=self.retries, backoff_s=self.backoff_s)
        except EndpointError as exc:
            # ``request_failed`` (not a reply that does not parse): the harness stops on the first one
            return {"error": str(exc), "avg": float("nan"), "request_failed": True}
        text = reply_text(response)
        scores = parse_judge_reply(text)
        if path is not None and "error" not in scores:  # only good answers are worth keeping
            # the folder is made only once there is an answer to keep
            write_atomic(path, json.dumps({"model": self.model, "reply": text}))
        return scores

    def score(self, scene: Scene, case: EvalCase, physics: ScenePhysics | None = None) -> dict:
        """Render the front and perspective views and ask the endpoint."""
        from physcene.eval.render import png_bytes, render_image

        images = [png_bytes(render_image(scene, view, size=self.image_size))
                  for view in ("front", "perspective")]
        return self.ask(case.instruction or scene.instruction, images)
