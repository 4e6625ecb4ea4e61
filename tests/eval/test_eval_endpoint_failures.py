"""Endpoints that fail: an unreachable generator or judge is one error and a non-zero exit; a server
failing every k-th request leaves a run whose report counts the failures; the API key does not follow
a redirect to another port; plain http off this machine warns. Servers run on loopback."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
from http.server import BaseHTTPRequestHandler
from pathlib import Path

import pytest
from loopback import LoopbackServer

from physcene.eval.endpoint import (
    EndpointError,
    is_loopback,
    parse_judge_reply,
    post_chat,
    reply_text,
    should_strip_auth,
    warn_if_plain_http,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "office_table.layout.json"
SCORES = json.dumps({"Evaluation": [{"criterion": c, "score": s} for c, s in (
    ("Consistency with Task", 8), ("Object Size Reasonableness", 9),
    ("Placement Plausibility & Intersections", 7), ("Layout Coherence & Realism", 8),
    ("Object Visibility", 10))]})


def _flat_layout() -> str:
    """The example layout as the paper's Prompt-3 reply (MesaTask flat JSON between <json> tokens)."""
    return "<json>\n" + EXAMPLE.read_text() + "\n<json>"


class Server(LoopbackServer):
    """A chat-completions server on loopback. ``reply``: the assistant text; ``fail_every``: every
    k-th request answers HTTP 500; ``redirect`` (set after start): answer every POST with 301 to
    this URL. Each request is recorded with its method, path and Authorization header."""

    def __init__(self, reply: str = SCORES, *, fail_every: int = 0):
        self.requests: list[dict] = []
        self.redirect: str | None = None
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def _answer(self):
                owner.requests.append({"method": self.command, "path": self.path,
                                       "auth": self.headers.get("Authorization")})
                if owner.redirect and self.command == "POST":
                    self.send_response(301)
                    self.send_header("Location", owner.redirect)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                if fail_every and len(owner.requests) % fail_every == 0:
                    self.send_error(500, "overloaded")
                    return
                message = {"role": "assistant", "content": reply}
                data = json.dumps({"choices": [{"message": message}]}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def do_POST(self):
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                self._answer()

            do_GET = _answer  # where urllib follows a 301 to (as a GET)

        super().__init__(Handler)


def _closed_port() -> int:
    """A loopback port nothing listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("which", ["generator", "judge"])
def test_an_unreachable_endpoint_is_one_error_and_a_nonzero_exit(which, tmp_path):
    url = f"http://127.0.0.1:{_closed_port()}/v1"
    args = ["--generator", f"endpoint:{url}"] if which == "generator" else ["--judge", "endpoint",
                                                                           f"judge_url={url}"]
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "physcene.cli", "eval", "--n", "2", "--out", str(out),
                          "--quiet", "endpoint_retries=0", "render=0", "judge_image_size=[64,48]", *args],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode != 0
    # Warp's own line about a missing CUDA driver is the machine's, not the command's
    lines = [line for line in run.stderr.strip().splitlines() if not line.startswith("Warp CUDA warning")]
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert url in lines[0] and "no server answered" in lines[0] and which in lines[0]
    assert not (out / "results.json").exists() and not (out / "report.md").exists()
    assert not (out / "judge_cache").exists()


def test_the_api_key_does_not_follow_a_redirect_to_another_port():
    with Server() as second, Server() as first:
        first.redirect = f"{second.url}/chat/completions"
        response = post_chat(f"{first.url}/chat/completions", {"model": "m"}, api_key="sk-secret", retries=0)
    assert reply_text(response) == SCORES  # the redirect was followed
    assert first.requests == [{"method": "POST", "path": "/v1/chat/completions", "auth": "Bearer sk-secret"}]
    assert second.requests == [{"method": "GET", "path": "/v1/chat/completions", "auth": None}]


def test_a_redirect_on_the_same_host_and_port_keeps_the_key():
    with Server() as server:
        server.redirect = f"http://127.0.0.1:{server.port}/v2/chat/completions"
        post_chat(f"{server.url}/chat/completions", {"model": "m"}, api_key="sk-secret", retries=0)
    assert [r["auth"] for r in server.requests] == ["Bearer sk-secret", "Bearer sk-secret"]
    assert server.requests[1]["path"] == "/v2/chat/completions"


@pytest.mark.parametrize("old, new, strip", [
    ("http://127.0.0.1:8000/v1", "http://127.0.0.1:8000/v2", False),
    ("http://127.0.0.1:8000/v1", "http://127.0.0.1:8001/v1", True),  # another port
    ("https://api.example.com/v1", "https://evil.example.net/v1", True),  # another host
    ("https://api.example.com/v1", "http://api.example.com/v1", True),  # a downgrade to plain http
    ("http://api.example.com/v1", "https://api.example.com/v1", False),  # the upgrade requests allows
    ("https://api.example.com:443/v1", "https://api.example.com/v2", False),  # the default port, spelled
])
def test_should_strip_auth_as_requests_decides(old, new, strip):
    assert should_strip_auth(old, new) is strip


def test_a_server_failing_every_third_generation_is_counted_in_the_report_and_terminal(tmp_path, capsys):
    from physcene.cli import main

    with Server(_flat_layout(), fail_every=3) as server:
        rc = main(["eval", "--n", "6", "--generator", f"endpoint:{server.url}", "--out", str(tmp_path),
                   "--quiet", "endpoint_retries=0", "render=0"])
    assert rc == 0 and len(server.requests) == 6
    terminal = capsys.readouterr().out
    line = "Zero-shot LLM (v1): 2 of 6 generations failed (no answer from the endpoint)"
    assert line in terminal and line in (tmp_path / "report.md").read_text()
    method = json.loads((tmp_path / "results.json").read_text())["methods"]["Zero-shot LLM (v1)"]
    assert method["summary"]["generation_failures"] == 2 and "parse_errors" not in method["summary"]
    failed = [s for s in method["scenes"] if "generation_error" in s["extra"]]
    assert [s["id"] for s in failed] == [method["scenes"][2]["id"], method["scenes"][5]["id"]]
    assert all("HTTP 500" in s["extra"]["generation_error"] and s["judge"]["avg"] is None for s in failed)
    assert method["summary"]["judge_failures"] == 0  # the four layouts that arrived were judged
    assert len(list((tmp_path / "layouts" / "zero-shot_llm_v1").glob("*.json"))) == 4


def test_a_judge_failing_every_third_request_is_counted(tmp_path, capsys):
    from physcene.cli import main

    with Server(fail_every=3) as server:
        rc = main(["eval", "--n", "4", "--judge", "endpoint", f"judge_url={server.url}", "--out",
                   str(tmp_path), "--quiet", "endpoint_retries=0", "render=0", "judge_image_size=[64,48]"])
    assert rc == 0 and len(server.requests) == 4
    line = "Reference: 1 of 4 judgements gave no scores"
    assert line in capsys.readouterr().out and line in (tmp_path / "report.md").read_text()
    summary = json.loads((tmp_path / "results.json").read_text())["methods"]["Reference"]["summary"]
    assert summary["judge_failures"] == 1 and summary["judge"]["avg"] == 8.4


def test_a_judge_that_never_gives_scores_is_an_error(tmp_path, capsys):
    from physcene.cli import main

    with Server("I like it, 8/10") as server:
        rc = main(["eval", "--n", "2", "--judge", "endpoint", f"judge_url={server.url}", "--out",
                   str(tmp_path), "--quiet", "render=0", "judge_image_size=[64,48]"])
    err = capsys.readouterr().err
    assert rc == 2 and "judge endpoint: none of 2 judgements gave scores" in err
    assert "no JSON object in the judge reply" in err and not (tmp_path / "report.md").exists()


def test_the_first_failed_generation_stops_the_run(tmp_path):
    from physcene.eval.harness import EvalError, generate, load_benchmark

    items = load_benchmark("test", n=3, progress=False)
    with Server(_flat_layout(), fail_every=1) as server:
        with pytest.raises(EvalError, match=r"generator endpoint:.*HTTP 500 .* after 2 tries"):
            generate(items, f"endpoint:{server.url}", retries=1, progress=False)
    assert len(server.requests) == 2  # one request, retried once, then the run stops


def test_endpoint_errors_say_whether_a_server_answered():
    with pytest.raises(EndpointError) as refused:
        post_chat(f"http://127.0.0.1:{_closed_port()}/v1/chat/completions", {}, retries=0)
    assert not refused.value.reached and "after 1 try" in str(refused.value)
    with Server(fail_every=1) as server, pytest.raises(EndpointError) as failed:
        post_chat(f"{server.url}/chat/completions", {}, retries=1, backoff_s=0.01)
    assert failed.value.reached and "HTTP 500" in str(failed.value) and len(server.requests) == 2


def test_plain_http_off_this_machine_warns_once(capsys):
    assert warn_if_plain_http("http://10.11.12.13:8000/v1")
    assert not warn_if_plain_http("http://10.11.12.13:8000/v1/chat/completions")  # the same server: once
    for quiet in ("https://10.11.12.14/v1", "http://127.0.0.1:8000/v1", "http://localhost/v1", "http://[::1]:80/v1"):
        assert not warn_if_plain_http(quiet)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "http://10.11.12.13:8000/v1" in err[0] and "unencrypted" in err[0]
    assert is_loopback("127.0.0.2") and is_loopback("LOCALHOST.") and not is_loopback("example.com")


MALFORMED = [None, 5, 1.5, b"{}", [], {}, "", "{", "}", "{}", "[]", "null", '{"Evaluation": 5}',
             '{"Evaluation": [1, "x", null, []]}', '{"Evaluation": {"score": 5}}', "{" * 100_000 + "}",
             '{"a": ' + "[" * 100_000 + "]" * 100_000 + "}", '{"Evaluation": [{"criterion": 5, "score": 5}]}',
             '{"Evaluation": [{"criterion": "Object Visibility", "score": 1' + "0" * 400 + "}]}",
             '{"Evaluation": [{"criterion": "Object Visibility", "score": ' + "9" * 5000 + "}]}",
             '{"Evaluation": [{"criterion": "Object Visibility", "score": NaN}]}',
             '{"Evaluation": [{"criterion": "Object Visibility", "score": [8]}]}',
             '{"Evaluation": [{"criterion": "Object Visibility", "score": true}]}',
             '{"Evaluation": [{"criterion": "Object Visibility", "score": "eight"}]}',
             "\ud800{\x00}", "```json\n{\"Evaluation\": []}\n```"]


@pytest.mark.parametrize("reply", MALFORMED, ids=range(len(MALFORMED)))
def test_parse_judge_reply_returns_no_score_for_any_malformed_reply(reply):
    out = parse_judge_reply(reply)
    assert set(out) == {"error", "avg"} and out["error"] and math.isnan(out["avg"])


def test_reply_text_of_odd_responses():
    for response in (None, [], "x", {"choices": []}, {"choices": [{"message": None}]},
                     {"choices": [{"message": {"content": [{"text": None}, 5, {"text": "a"}]}}]}):
        assert isinstance(reply_text(response), str)
