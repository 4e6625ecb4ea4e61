"""The ``endpoint:URL`` generator: any OpenAI-compatible chat server with the paper's zero-shot prompt.

The request is the paper's Prompt 3 (:func:`physcene.ctrc.zero_shot_prompt`) filled with the
instruction, the placement zone and the object list of the procedural plan; the reply (MesaTask
flat JSON between ``<json>`` tokens) is read by :func:`physcene.ctrc.parse`. The HTTP client is the
eval judges' (:func:`physcene.eval.endpoint.post_chat`: retries, and an API key that never follows a
redirect to another host). A local vLLM or llama.cpp server serving an
open model works as well as a hosted API (docs/generate.md).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from tqdm.auto import tqdm

from physcene.eval.endpoint import EndpointError, post_chat, reply_text, warn_if_plain_http
from physcene.generation.procedural import GenerationError

__all__ = ["API_KEY_ENV", "chat_url", "endpoint_replies"]

API_KEY_ENV = "PHYSCENE_GENERATOR_API_KEY"
"""Environment variable holding the endpoint's API key (sent as a bearer token when set)."""


def chat_url(url: str) -> str:
    """``url``'s chat-completions address (``/chat/completions`` appended unless present); plain http
    to another machine gets one warning on stderr (:func:`physcene.eval.endpoint.warn_if_plain_http`)."""
    base = url.strip().rstrip("/")
    if not base.startswith(("http://", "https://")):
        raise GenerationError(f"generator endpoint:{url}: the URL must start with http:// or https:// "
                              "(e.g. endpoint:http://127.0.0.1:8000/v1)")
    warn_if_plain_http(base)
    return base if base.endswith("/chat/completions") else base + "/chat/completions"


def endpoint_replies(url: str, prompts: Sequence[str], *, model: str = "default", temperature: float = 0.7,
                     seed: int = 0, timeout_s: float = 120.0, retries: int = 1,
                     progress: bool = True) -> list[str]:
    """The assistant's reply to each prompt, in order. An endpoint that does not answer (after
    ``retries`` more tries) or refuses the request is one :class:`GenerationError`."""
    endpoint = chat_url(url)
    out = []
    for k, prompt in enumerate(tqdm(prompts, desc="endpoint", unit="scene", disable=not progress)):
        payload = {"model": model, "temperature": temperature, "seed": seed + k,
                   "messages": [{"role": "user", "content": prompt}]}
        try:
            response = post_chat(endpoint, payload, api_key=os.environ.get(API_KEY_ENV), timeout_s=timeout_s,
                                 retries=retries, backoff_s=0.5)
        except EndpointError as exc:
            raise GenerationError(f"generator endpoint:{url}: {exc.reason}") from None
        out.append(reply_text(response))
    return out
