"""A planner asking the same question back to back while the robot streams, against a real node
process: every answer is a valid answer of a map version the node had (never a newer one), a
reused answer says so, the node computed far fewer answers than it gave, and once the stream
stops the next answer is of the current map (with every streamed keyframe integrated)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from clients.harness import NodeProcess, sim_stream
from protocol.errors import RemoteError
from protocol.messages import Error, Frame, Points

pytestmark = pytest.mark.slow

SEED, N_PATH, STEP, W, H = 5, 240, 6, 80, 60
TIMEOUT_S = 120.0
QUESTION = ["find the chair"]


@pytest.fixture(scope="module")
def node(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    root = tmp_path_factory.mktemp("e2e_planner")
    args = ["--set", "window.max_keyframes=60", "--set", "poll_interval_s=0.02", "--set", "serve_model=false"]
    proc = NodeProcess(root / "maps", log_path=root / "node.log", extra_args=args)
    with proc:
        proc.wait_ready()
        yield proc


def frames() -> list[Frame]:
    stream = sim_stream(SEED, N_PATH, W, H, depth=True)
    return [stream.frame(k, stream.render(k)) for k in range(0, N_PATH, STEP)]


def test_planner_during_a_stream_then_a_current_answer(node: NodeProcess) -> None:
    all_frames = frames()
    first, rest = all_frames[:8], all_frames[8:]
    with node.client(timeout_s=TIMEOUT_S, retries=0) as client:
        replies = [r.reply for r in client.send_frames(first, window=4)]
        assert not any(isinstance(r, Error) for r in replies), replies
        deadline = time.monotonic() + TIMEOUT_S
        while True:  # the first answer: once the encoder is loaded and the first keyframes integrated
            try:
                client.query_points(QUESTION, max_points=100)
                break
            except RemoteError:
                assert time.monotonic() < deadline, "no answer before the deadline"
                time.sleep(0.1)

    answers: list[Points] = []
    stop = threading.Event()

    def planner() -> None:
        with node.client(timeout_s=TIMEOUT_S, retries=0) as c:
            while not stop.is_set():
                answers.append(c.query_points(QUESTION, max_points=100))

    thread = threading.Thread(target=planner, daemon=True)
    with node.client(timeout_s=TIMEOUT_S, retries=0) as client:
        before = client.status().extra["answers"]
        thread.start()
        replies = []
        for frame in rest:  # a 30 Hz camera
            replies.append(client.send_frame(frame))
            time.sleep(1 / 30)
        deadline = time.monotonic() + TIMEOUT_S
        while len(answers) < 20:  # a slow machine: let the planner ask a few more (the map settles)
            assert time.monotonic() < deadline and thread.is_alive(), "the planner got too few answers"
            time.sleep(0.05)
        stop.set()
        thread.join(timeout=TIMEOUT_S)
        assert not any(isinstance(r, Error) for r in replies), replies
        assert not thread.is_alive() and answers
        versions = [a.map_version for a in answers]
        assert versions == sorted(versions)  # one planner never gets an older answer after a newer one
        status = client.status()
        assert max(versions) <= status.map_version
        for a in answers:
            assert a.timing_ms["answer_reused"] in (0.0, 1.0) and a.timing_ms["answer_age_ms"] >= 0.0
            assert a.xyz.shape[0] == a.score.shape[0] <= 100
        stats = status.extra["answers"]
        reused = sum(stats[k] - before[k] for k in ("reused_same_version", "reused_stale"))
        assert reused == sum(a.timing_ms["answer_reused"] for a in answers) > 0
        assert stats["computed"] - before["computed"] < len(answers)

        # the stream stopped: once the integrator drained, the answer is of the current map
        deadline = time.monotonic() + TIMEOUT_S
        while client.status().extra["integration"]["backlog"]:
            assert time.monotonic() < deadline, "the integrator's backlog did not drain"
            time.sleep(0.05)
        time.sleep(0.6)  # > limits.ingest_active_s: frames no longer count as arriving
        final = client.query_points(QUESTION, max_points=100)
        current = client.status()
        assert final.map_version == current.map_version  # computed now, or reused of this very version
        assert final.map_version > versions[0]
