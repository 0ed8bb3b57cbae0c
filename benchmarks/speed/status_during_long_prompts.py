"""How long ``status`` waits while a ``query_points`` with many new, long prompts is answered (a real
node): the ``queries.light_text_chars`` routing sends such a question to the query workers, so the
query thread answers ``status`` at once. Run it with the shipped routing and with it off
(``--light-text-chars 1000000``: every question on the query thread) to compare. Prints one line
per trial.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/status_during_long_prompts.py --light-text-chars 256
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/speed/status_during_long_prompts.py \\
        --light-text-chars 1000000
"""

from __future__ import annotations

import argparse
import random
import string
import sys
import tempfile
import time
from pathlib import Path

import zmq

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clients.cli.bench import make_frames  # noqa: E402
from clients.harness import NodeProcess  # noqa: E402
from protocol.messages import QueryPoints, StatusRequest, decode, encode  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--light-text-chars", type=int, default=256, help="the node's setting")
    parser.add_argument("--prompts", type=int, default=64, help="prompts per question (protocol: at most 64)")
    parser.add_argument("--chars", type=int, default=1024, help="characters per prompt (at most 1024)")
    parser.add_argument("--trials", type=int, default=2)
    args = parser.parse_args()

    root = Path(tempfile.mkdtemp(prefix="govnesf-long-prompts-"))
    node = NodeProcess(root / "maps", log_path=root / "node.log",
                       extra_args=["--set", f"queries.light_text_chars={args.light_text_chars}"])  # fmt: skip
    with node:
        node.wait_ready(timeout_s=120.0)
        with node.client(timeout_s=120.0, retries=0) as client:
            for _ in client.send_frames(make_frames(30), window=8):
                pass
            client.query_points(["chair"])  # the encoder loaded and the default negatives embedded
        sock: zmq.Socket[bytes] = zmq.Context.instance().socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(node.query)
        rng = random.Random(0)
        try:
            for trial in range(args.trials):
                texts = ["".join(rng.choice(string.ascii_lowercase + " ") for _ in range(args.chars))
                         for _ in range(args.prompts)]  # fmt: skip
                t0 = time.perf_counter()
                sock.send(encode(QueryPoints(texts=texts, id="long")))
                time.sleep(0.05)
                t1 = time.perf_counter()
                sock.send(encode(StatusRequest(id="status")))
                got: dict[str, float] = {}
                while len(got) < 2:
                    if not sock.poll(120_000):
                        raise SystemExit("no reply within 120 s")
                    reply = decode(sock.recv(), direction="reply")
                    got[str(reply.id)] = time.perf_counter()
                print(f"light_text_chars={args.light_text_chars} trial {trial}: status answered "
                      f"{1e3 * (got['status'] - t1):.0f} ms after it was sent; the long query_points "
                      f"{got['long'] - t0:.2f} s", flush=True)  # fmt: skip
        finally:
            sock.close()


if __name__ == "__main__":
    main()
