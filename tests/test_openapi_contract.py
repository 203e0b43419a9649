"""The OpenAPI document against the live server, with schemathesis and every
check: status codes, content types, response schemas, and that bodies the
schema allows are accepted and bodies it forbids are refused. A document
changed to describe a wrong answer must fail the same run."""

import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
SCHEMATHESIS = Path(sys.executable).parent / "schemathesis"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def post(url, body, headers):
    req = urllib.request.Request(url, json.dumps(body).encode(), {"content-type": "application/json", **headers})
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.loads(r.read())


TOKEN = "contract-test-token"


@pytest.fixture(scope="module", params=["open", "tokens"])
def server(request, tmp_path_factory):
    """The server as it runs by default, and with tokens on (the run then sends one)."""
    port = free_port()
    store = tmp_path_factory.mktemp("contract") / "store.redb"
    env = dict(os.environ)
    flags = []
    if request.param == "tokens":
        env["WORLDPACK_TOKENS"] = f"tester:{TOKEN}"
        flags = ["--rate-per-tenant", "100000"]
    proc = subprocess.Popen([BIN, "serve", "--model", "fixtures/small", "--store", str(store), "--addr", f"127.0.0.1:{port}", "--steps", "2", *flags],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    url = f"http://127.0.0.1:{port}"
    headers = {"authorization": f"Bearer {TOKEN}"} if request.param == "tokens" else {}
    for _ in range(300):
        try:
            urllib.request.urlopen(urllib.request.Request(url + "/v1/health", headers=headers), timeout=1)
            break
        except OSError:
            if proc.poll() is not None:
                pytest.fail(f"the server exited: {proc.stderr.read()}")
            time.sleep(0.1)
    # A session with frames before the run; the run makes its own through the document's links.
    assert post(url + "/v1/sessions", {"synthetic": {"seed": 3}}, headers)["frames"] == 1
    yield url, headers
    proc.terminate()
    proc.wait(timeout=30)


def schemathesis(schema, url, headers, *extra):
    auth = [a for k, v in headers.items() for a in ("--header", f"{k}: {v}")]
    args = [str(SCHEMATHESIS), "--config-file", str(ROOT / "tests" / "schemathesis.toml"), "--no-color", "run", schema, "--url", url,
            "--checks", "all", "--max-examples", "25", "--workers", "1", "--seed", "20261123", "--request-timeout", "300", *auth, *extra]
    return subprocess.run(args, capture_output=True, text=True, timeout=900)


def test_the_server_keeps_its_documented_contract(server):
    url, headers = server
    out = schemathesis(url + "/openapi.json", url, headers)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
    assert "Tested: 16" in out.stdout, out.stdout[-3000:]


def test_a_document_that_describes_a_wrong_answer_fails(server, tmp_path):
    url, headers = server
    with urllib.request.urlopen(url + "/openapi.json") as r:
        doc = json.loads(r.read())
    # The server answers the live session count as an integer; claim a string.
    doc["components"]["schemas"]["Health"]["properties"]["sessions"] = {"type": "string"}
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps(doc))
    out = schemathesis(str(wrong), url, headers, "--include-path", "/v1/health")
    assert out.returncode != 0, out.stdout[-3000:]
    assert "Response violates schema" in out.stdout, out.stdout[-3000:]
