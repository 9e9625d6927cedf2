"""The tuning page's HTTP server under malformed requests and load
(docs/robustness.md): raw bytes on a socket, never a browser. Every malformed
request gets a 4xx JSON answer (digits parsed strictly, sizes and nesting
capped), never a 500 or a hung connection; 50 clients that connect at once are
all queued (a real listen backlog) and answered without a reset.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

TIMEOUT_S = 30.0  # a loaded machine answers in milliseconds; a hung handler would take REQUEST_TIMEOUT_S or more


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    """A real tuning server in this process, on the hover scenario (its view 160x120)."""
    from sim.scenario import load
    from tether.runner import build_simulation
    from viz.tuning import TuningServer, TuningSession

    folder = tmp_path_factory.mktemp("tune")
    scenario = load("hover", ["video.width=160", "video.height=120"])
    session = TuningSession(scenario, build_simulation, view_fps=1.0, speed=1.0, save_path=folder / "saved.toml")
    server = TuningServer(session, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    session.start()
    server.host_header = f"127.0.0.1:{server.port}".encode()
    yield server
    server.shutdown()
    server.server_close()
    session.stop()


def exchange(port: int, data: bytes) -> tuple[int, bytes]:
    """Send ``data``, close the writing side, read the whole answer: (status, body)."""
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as s:
        s.sendall(data)
        s.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := s.recv(65536):
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def request(page, method: bytes, target: bytes, body: bytes = b"", headers: bytes | None = None) -> bytes:
    if headers is None:
        headers = b"Content-Length: %d\r\n" % len(body)
    return method + b" " + target + b" HTTP/1.1\r\nHost: " + page.host_header + b"\r\n" + headers + b"\r\n" + body


def assert_refused(status: int, body: bytes, *words: str) -> None:
    assert status == 400, (status, body[:300])
    answer = json.loads(body)
    assert answer["ok"] is False
    for word in words:
        assert word in answer["error"], (word, answer["error"])


CHANGES = b'{"changes": {"speed_mps": %s}}'

MALFORMED = {
    "Content-Length in superscript digits": (b"POST", b"/api/params", b"{}", "Content-Length: \xc2\xb2\r\n".encode(),
                                             "Content-Length"),
    "Content-Length in Latin-1 superscript": (b"POST", b"/api/params", b"{}", b"Content-Length: \xb2\r\n",
                                              "Content-Length"),
    "Content-Length of 5000 digits": (b"POST", b"/api/params", b"{}", b"Content-Length: " + b"9" * 5000 + b"\r\n",
                                      "Content-Length"),
    "Content-Length with a plus": (b"POST", b"/api/params", b"{}", b"Content-Length: +2\r\n", "Content-Length"),
    "Content-Length with an underscore": (b"POST", b"/api/params", b"{}", b"Content-Length: 1_0\r\n",
                                          "Content-Length"),
    "two different Content-Lengths": (b"POST", b"/api/params", b"{}", b"Content-Length: 2\r\nContent-Length: 3\r\n",
                                      "Content-Length"),
    "Content-Length over the cap": (b"POST", b"/api/params", b"{}", b"Content-Length: 9000000\r\n", "too large"),
    "since in superscript digits": (b"GET", b"/api/status?since=%C2%B2", b"", None, "since"),
    "since of 5000 digits": (b"GET", b"/api/status?since=" + b"9" * 5000, b"", None, "since"),
    "since negative": (b"GET", b"/api/status?since=-5", b"", None, "since"),
    "since not a number": (b"GET", b"/api/status?since=abc", b"", None, "since"),
    "a JSON number of 5000 digits": (b"POST", b"/api/params", CHANGES % (b"9" * 5000), None, "digits"),
    "a JSON array nested 200000 deep": (b"POST", b"/api/params", b"[" * 200_000 + b"]" * 200_000, None, "nested"),
    "a JSON object nested 40 deep": (b"POST", b"/api/params", b'{"a": ' * 40 + b"1" + b"}" * 40, None, "nested"),
    "a TOML value nested 3000 deep": (b"POST", b"/api/params", b'{"changes": {"routes": "' + b"[" * 3000 + b'"}}',
                                      None, "strategy.routes"),
    "a body not UTF-8": (b"POST", b"/api/control", b"\xff\xfe\xfd", None, "not JSON"),
    "a camera that is a list": (b"POST", b"/api/control", b'{"action": "camera", "camera": [1, 2]}', None, ""),
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_requests_get_400_with_the_reason(name, page):
    method, target, body, headers, word = MALFORMED[name]
    start = time.monotonic()
    status, answer = exchange(page.port, request(page, method, target, body, headers))
    assert time.monotonic() - start < TIMEOUT_S
    assert_refused(status, answer, word)


def test_the_page_still_answers_after_the_malformed_ones(page):
    status, body = exchange(page.port, request(page, b"GET", b"/api/status?since=1000000000"))
    assert status == 200 and json.loads(body)["tick"] >= 0


# Answers a request may get: 200 (a valid one), 204 (favicon), 400, 403 (a foreign Host or Origin), 404, 414 and
# 431 (http.server's own size limits), 501 (a method the page does not have). Never 500: that is a bug.
ANSWERS = {200, 204, 400, 403, 404, 414, 431, 501}
TARGETS = [b"/", b"/api/status", b"/api/status?since=0", b"/api/params", b"/api/control", b"/api/save",
           b"/scenario.toml", b"/favicon.ico", b"/nothing"]
json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner,
                                                                                        max_size=4), max_leaves=20)
bodies = st.one_of(
    st.binary(max_size=200),
    json_values.map(lambda v: json.dumps(v).encode()),
    st.dictionaries(st.sampled_from(["changes", "action", "camera"]),
                    st.one_of(json_values, st.sampled_from(["pause", "resume", "step", "camera", "top"])),
                    max_size=3).map(lambda v: json.dumps(v).encode()),
    st.dictionaries(st.sampled_from(["speed_mps", "routes", "kp", "nothing"]), json_values, min_size=1,
                    max_size=2).map(lambda v: json.dumps({"changes": v}).encode()),
)
lengths = st.one_of(st.none(), st.text(max_size=12).map(lambda t: t.encode("utf-8")),
                    st.integers(min_value=0, max_value=300).map(lambda n: str(n).encode()))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(method=st.sampled_from([b"GET", b"POST", b"PUT", b"HEAD", b"G\xc3\xa9T"]),
       target=st.one_of(st.sampled_from(TARGETS), st.binary(max_size=40).map(lambda b: b"/" + b.replace(b" ", b""))),
       query=st.one_of(st.just(b""), st.binary(max_size=20).map(lambda b: b"?since=" + b.replace(b" ", b"+"))),
       length=lengths, body=bodies, host=st.booleans())
def test_fuzzed_raw_requests_never_get_a_500(page, method, target, query, length, body, host):
    target = target.replace(b"\r", b"").replace(b"\n", b"") + query.replace(b"\r", b"").replace(b"\n", b"")
    if target.startswith((b"/stream", b"/frame")):  # endless or waiting streams of the view, not requests
        target = b"/nothing"
    headers = b"" if length is None else b"Content-Length: " + length.replace(b"\r", b"").replace(b"\n", b"") + b"\r\n"
    data = request(page, method, target, body, headers)
    if not host:
        data = data.replace(b"Host: " + page.host_header, b"Host: example.com")
    status, answer = exchange(page.port, data)
    assert status in ANSWERS, (status, answer[:300], data[:300])
    if status >= 400 and method != b"HEAD":  # every refusal is JSON with its reason
        refusal = json.loads(answer)
        assert refusal["ok"] is False and refusal["error"], refusal


def test_fifty_clients_at_once_are_queued_and_answered(page):
    """50 connections made while the server accepts none (the kernel queues them up to the
    listen backlog; http.server's default of 5 has the others wait and time out), then 50
    requests, all answered, none reset."""
    from viz.tuning import TuningServer

    idle = TuningServer(page.session, "127.0.0.1", 0)  # listening, not accepting yet
    host = f"127.0.0.1:{idle.port}".encode()
    connections, errors, statuses = [], [], []
    serving = None
    try:
        for _ in range(50):
            try:
                connections.append(socket.create_connection(("127.0.0.1", idle.port), timeout=1.0))
            except OSError as err:
                errors.append(f"connect: {err!r}")
                break
        assert not errors, f"{len(errors)} of 50 not queued: {errors[:3]}"
        serving = threading.Thread(target=idle.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
        serving.start()
        body = b'{"changes": {"speed_mps": 0.4}}'
        data = b"POST /api/params HTTP/1.1\r\nHost: " + host + b"\r\nContent-Length: %d\r\n\r\n" % len(body) + body
        barrier = threading.Barrier(50)

        def client(sock: socket.socket) -> None:
            try:
                sock.settimeout(TIMEOUT_S)
                barrier.wait()
                sock.sendall(data)
                sock.shutdown(socket.SHUT_WR)
                reply = b""
                while chunk := sock.recv(65536):
                    reply += chunk
                statuses.append(int(reply.split()[1]))
            except OSError as err:
                errors.append(repr(err))

        threads = [threading.Thread(target=client, args=(sock,)) for sock in connections]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=TIMEOUT_S * 2)
        assert not errors, errors
        assert statuses == [200] * 50
    finally:
        for sock in connections:
            sock.close()
        if serving is not None:
            idle.shutdown()
        idle.server_close()
