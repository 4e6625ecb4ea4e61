"""EndpointJudge and the zero-shot generator against a real chat-completions server on loopback."""

from __future__ import annotations

import base64
import json
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import pytest
from loopback import LoopbackServer

from physcene.eval.endpoint import SYSTEM_PROMPT, EndpointJudge, parse_judge_reply
from physcene.eval.judges import EvalCase
from physcene.layout import read_layout

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "office_table.layout.json"
SCORES = {
    "Consistency with Task": 8,
    "Object Size Reasonableness": 9,
    "Placement Plausibility & Intersections": 7,
    "Layout Coherence & Realism": 8,
    "Object Visibility": 10,
}


class _ChatServer(LoopbackServer):
    """A minimal OpenAI-style /v1/chat/completions server; ``fail_first`` requests answer HTTP 500."""

    def __init__(self, fail_first: int = 0, reply: str | None = None):
        self.requests: list[dict] = []
        self.fail_first = fail_first
        self.reply = reply
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # keep pytest output clean
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                owner.requests.append(
                    {"path": self.path, "body": body, "auth": self.headers.get("Authorization")}
                )
                if self.path != "/v1/chat/completions":
                    self.send_error(404)
                    return
                if len(owner.requests) <= owner.fail_first:
                    self.send_error(500, "overloaded")
                    return
                text = (
                    owner.reply
                    if owner.reply is not None
                    else json.dumps(
                        {
                            "Evaluation": [
                                {"criterion": k, "explanation": "ok", "score": v} for k, v in SCORES.items()
                            ]
                        }
                    )
                )
                data = json.dumps(
                    {
                        "id": "x",
                        "object": "chat.completion",
                        "model": body["model"],
                        "choices": [
                            {
                                "index": 0,
                                "finish_reason": "stop",
                                "message": {"role": "assistant", "content": text},
                            }
                        ],
                    }
                ).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        super().__init__(Handler)


@pytest.fixture(scope="module")
def scene():
    return read_layout(EXAMPLE)


def test_endpoint_judge_sends_prompts_and_images_and_parses_scores(scene, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSCENE_JUDGE_API_KEY", "sk-test")
    with _ChatServer() as server:
        judge = EndpointJudge(server.url, model="judge-vlm", cache_dir=tmp_path, image_size=(160, 120))
        scores = judge.score(scene, EvalCase.from_reference(scene))
    assert scores == {"CwT": 8.0, "OSR": 9.0, "PPI": 7.0, "LCR": 8.0, "OV": 10.0, "avg": 8.4}
    (req,) = server.requests
    assert req["auth"] == "Bearer sk-test" and req["body"]["model"] == "judge-vlm"
    system, user = req["body"]["messages"]
    assert system == {"role": "system", "content": SYSTEM_PROMPT}
    text, front, persp = user["content"]
    assert scene.instruction in text["text"] and "{task_description}" not in text["text"]
    for part in (front, persp):
        url = part["image_url"]["url"]
        assert url.startswith("data:image/png;base64,")
        assert base64.b64decode(url.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert front != persp


def test_endpoint_judge_retries_after_500_and_hits_the_cache(scene, tmp_path):
    with _ChatServer(fail_first=2) as server:
        judge = EndpointJudge(server.url, cache_dir=tmp_path, backoff_s=0.01, image_size=(96, 72))
        first = judge.score(scene, EvalCase.from_reference(scene))
        assert len(server.requests) == 3 and first["avg"] == 8.4
        again = judge.score(scene, EvalCase.from_reference(scene))
        assert again == first and len(server.requests) == 3  # answered from the on-disk cache
        assert judge.stats == {"requests": 1, "cache_hits": 1}
        assert len(list(tmp_path.glob("*.json"))) == 1


def test_endpoint_failures_are_values(scene, tmp_path):
    with _ChatServer(fail_first=10) as server:
        judge = EndpointJudge(server.url, retries=1, backoff_s=0.01, image_size=(64, 48))
        out = judge.score(scene, EvalCase.from_reference(scene))
    assert "error" in out and "HTTP Error 500" in out["error"] or "500" in out["error"]
    with _ChatServer(reply="I think it is nice, 8/10") as server:
        out = EndpointJudge(server.url, image_size=(64, 48)).score(scene, EvalCase.from_reference(scene))
    assert out["error"] == "no JSON object in the judge reply"
    assert (
        "lacks scores"
        in parse_judge_reply('{"Evaluation": [{"criterion": "Object Visibility", "score": 3}]}')["error"]
    )
    fenced = (
        "```json\n" + json.dumps({"Evaluation": [{"criterion": k, "score": 11} for k in SCORES]}) + "\n```"
    )
    assert parse_judge_reply(fenced)["avg"] == 10.0  # clipped to the 1-10 scale


def test_zero_shot_generator_uses_prompt_3_and_parses_flat_json(scene):
    from physcene.eval.baselines import zero_shot_prompt
    from physcene.eval.harness import BenchmarkItem, generate

    flat = {
        "item_placement_zone": scene.zone.to_list(),
        "objects": [
            {
                "instance": "laptop_0",
                "z_rotation": 0.0,
                "size": [34, 24, 2],
                "position": [60, 30, 1],
                "description": "a laptop",
            },
            {
                "instance": "mug_0",
                "z_rotation": 0.0,
                "size": [11, 8, 9],
                "position": [95, 12, 4.5],
                "description": "a mug",
            },
        ],
    }
    item = BenchmarkItem(
        "s0", scene.scene_type, 3, scene.instruction, "", scene, EvalCase.from_reference(scene)
    )
    with _ChatServer(reply="<json>\n" + json.dumps(flat) + "\n<json>") as server:
        (out,) = generate([item], f"endpoint:{server.url}", progress=False)
    with _ChatServer(reply="sorry, no layout today") as server:
        (bad,) = generate([item], f"endpoint:{server.url}", progress=False)
    prompt = server.requests[0]["body"]["messages"][0]["content"]
    assert prompt == zero_shot_prompt(scene) and "<Objects cluster>" not in prompt and "laptop (1)" in prompt
    assert (
        sorted(o.category for o in out.objects) == ["laptop", "mug"] and out.instruction == scene.instruction
    )
    assert hasattr(bad, "reason")  # a ParseError value, not an exception


def test_eval_command_with_the_endpoint_judge(tmp_path, capsys):
    from physcene.cli import main

    with _ChatServer() as server:
        rc = main(["eval", "--n", "2", "--judge", "endpoint", "--out", str(tmp_path), "--quiet",
                   f"judge_url={server.url}", "render=0", "judge_image_size=[128,96]"])
    assert rc == 0 and len(server.requests) == 2  # one request per scene, two images each
    assert all(len(r["body"]["messages"][1]["content"]) == 3 for r in server.requests)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["methods"]["Reference"]["summary"]["judge"]["avg"] == 8.4
    assert len(list((tmp_path / "judge_cache").glob("*.json"))) == 2
