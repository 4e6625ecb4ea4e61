"""``--generator endpoint:URL`` against a chat-completions server on loopback started by the test."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from physcene.cli import main
from physcene.layout import read_layout

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "office_table.layout.json"


@pytest.fixture
def server():
    """An OpenAI-style /v1/chat/completions server answering the example layout between <json> tokens
    (the paper's Prompt 3 reply format); ``requests`` records what it was sent."""
    requests: list[dict] = []
    reply = "Here it is.\n<json>\n" + EXAMPLE.read_text() + "\n<json>"

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

        def do_POST(self):
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            requests.append({"path": self.path, "body": body})
            data = json.dumps({"choices": [{"index": 0, "message": {"role": "assistant", "content": reply}}]})
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data.encode())

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/v1", requests
    httpd.shutdown()
    httpd.server_close()


def test_endpoint_generator_writes_the_servers_layouts(tmp_path, server):
    url, requests = server
    text = "a desk with a laptop, a mug on the saucer and a pen in the pen holder"
    code = main(["generate", text, "--generator", f"endpoint:{url}", "--endpoint-model", "qwen3-8b",
                 "--n", "2", "-o", str(tmp_path), "--no-render", "--quiet"])
    assert code == 0 and len(requests) == 2
    assert {r["path"] for r in requests} == {"/v1/chat/completions"}
    prompt = requests[0]["body"]["messages"][0]["content"]
    assert requests[0]["body"]["model"] == "qwen3-8b" and f'"{text}"' in prompt and "<json>" in prompt
    assert "pen holder (1)" in prompt  # the object list of the procedural plan
    for k in range(2):
        folder = tmp_path / f"sample_{k}"
        scene = read_layout(folder / "layout.json")
        assert "7_mug_0" in scene.ids() and scene.scene_type == "office table"
        assert "<json>" in (folder / "reply.txt").read_text()
        assert (folder / "completion.txt").read_text().startswith("**Sub-instruction:**")
        assert json.loads((folder / "check.json").read_text())["objects"] == len(scene.objects)


def test_an_unparsable_reply_is_reported_per_sample(tmp_path, monkeypatch):
    from physcene.generation import generate, samples

    monkeypatch.setattr(samples, "endpoint_replies",
                        lambda url, prompts, **kw: ["no layout, sorry"] * len(prompts))
    result = generate("a desk with a laptop", generator="endpoint:http://127.0.0.1:9/v1", out=tmp_path,
                      render=False)
    assert result[0].scene is None and "did not parse" in result[0].error
    assert (tmp_path / "sample_0" / "error.txt").is_file()
    assert main(["generate", "a desk with a laptop", "--generator", "endpoint:http://127.0.0.1:9/v1",
                 "-o", str(tmp_path), "--no-render", "--quiet"]) == 1


def test_an_unreachable_endpoint_is_one_line_and_exit_2(tmp_path, capsys):
    import socket

    with socket.socket() as s:  # a loopback port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/v1"
    code = main(["generate", "a desk with a laptop", "--generator", f"endpoint:{url}", "-o",
                 str(tmp_path / "out"), "--no-render", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert f"generator endpoint:{url}: no server answered" in err[0] and "after 2 tries" in err[0]
