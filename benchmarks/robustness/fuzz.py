"""Fuzzing at scale: hostile bytes into every decoder path and request handler of the node.

Inputs (deterministic for a seed; ``--inputs`` in all, default 100,000), in families:

- ``mutated``: valid encoded messages (``tests/protocol/protocol_samples.py``: one of every
  type, requests and replies, plus a frame with depth and ov) with 1..6 bit flips, byte
  insertions, deletions, duplications or cuts;
- ``truncated``: every kind of prefix of a valid message;
- ``random_msgpack``: random nested msgpack values (maps with and without known keys);
- ``known_keys``: valid wire maps with 1..3 known keys replaced by random values (wrong types,
  wrong shapes, out-of-range numbers, nd arrays with lying shape/dtype/data);
- ``huge_sizes``: short messages that *declare* huge bins, strings, arrays, maps, exts, or nest
  deeply (nothing may be allocated for the declared size), and some really above
  ``max_message_bytes`` (``too_large``);
- ``random_bytes``: uniformly random bytes;
- ``hypothesis``: property-based: messages drawn from the protocol test strategies
  (``protocol_samples.messages``), encoded, then mutated.

Every input goes to ``protocol.messages.decode`` in all three directions and to an in-process
:class:`mapper.node.service.MapperNode`'s ``handle_ingest`` and ``handle_query`` (the functions the
socket threads call). Checked for each: the decoder returns a message or raises ``ProtocolError``
with a known code and a message (anything else is a decoder bug); an accepted message
re-encodes to an equal message; every handler call returns exactly one decodable reply, an
``error`` with a known code and a non-empty message or a valid reply; the node's ``internal``
error count stays 0. Then a socket-level slice (``--socket-inputs``) goes through real ZeroMQ
sockets of a started node (ipc), one reply per message expected (inputs above the transport's
hard limit are dropped with the connection, by design, and are not in that slice), and finally
``status`` must answer on both a fresh and the fuzzing connection.

    .venv/bin/python benchmarks/robustness/fuzz.py                # 100,000 inputs + 3,000 over sockets
    .venv/bin/python benchmarks/robustness/fuzz.py --inputs 2000 --socket-inputs 200 --out /tmp/fuzz

Writes ``fuzz.json`` and ``fuzz.md`` to ``--out`` (default ``out/bench``).
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import struct
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "protocol"))

import protocol_samples  # noqa: E402

from mapper.node.config import config_from_dict  # noqa: E402
from mapper.node.service import HARD_LIMIT_FACTOR, MapperNode  # noqa: E402
from protocol.errors import ERROR_CODES, ProtocolError  # noqa: E402
from protocol.messages import Error, Message, StatusRequest, decode, encode, peek_id  # noqa: E402

MAX_BYTES = 1 << 20
"""``max_message_bytes`` of the fuzzed node (and of ``decode``): small, so size limits are hit too."""

FAMILIES = (
    "mutated",
    "truncated",
    "random_msgpack",
    "known_keys",
    "huge_sizes",
    "random_bytes",
    "hypothesis",
)
"""Input families, in the order their share of ``--inputs`` is drawn (hypothesis gets a fixed share)."""


# -- inputs -----------------------------------------------------------------------------------


def _corpus() -> list[tuple[bytes, dict[str, Any]]]:
    """Valid messages: ``(encoded, wire map)`` of every sample plus a frame with depth and ov."""
    out = [(encode(m), m.to_wire()) for m in protocol_samples.samples()]
    wire = protocol_samples.frame_wire()
    out.append((protocol_samples.pack(wire), wire))
    return out


def _random_value(rng: random.Random, depth: int = 0) -> Any:
    kind = rng.randrange(12 if depth < 3 else 8)
    if kind == 0:
        return None
    if kind == 1:
        return rng.random() < 0.5
    if kind == 2:
        return rng.choice([0, 1, -1, 2**63 - 1, -(2**63), 2**64 - 1, rng.randrange(-1000, 1000)])
    if kind == 3:
        return rng.choice(
            [0.0, -0.0, float("nan"), float("inf"), -float("inf"), 1e308, rng.uniform(-1e6, 1e6)]
        )
    if kind == 4:
        return "".join(chr(rng.randrange(32, 0x2FFF)) for _ in range(rng.randrange(0, 12)))
    if kind == 5:
        return rng.randbytes(rng.randrange(0, 40))
    if kind == 6:
        return rng.choice(["rgb8", "png", "jpeg", "<f4", "<f2", "|u1", "frame", "status", "chair", ""])
    if kind == 7:  # an nd array encoding that lies about itself
        return {
            "dtype": rng.choice(
                ["float32", "float16", "float64", "uint8", "uint16", "int32", "<f4", "object", "x"]
            ),
            "shape": [rng.choice([0, 1, 2, 3, 4, -1, 2**31, 2**62]) for _ in range(rng.randrange(0, 4))],
            "data": rng.randbytes(rng.randrange(0, 64)),
        }
    if kind in (8, 9):
        return [_random_value(rng, depth + 1) for _ in range(rng.randrange(0, 5))]
    return {
        rng.choice(["v", "type", "id", "seq", "shape", "dtype", "data", "x", ""]): _random_value(
            rng, depth + 1
        )
        for _ in range(rng.randrange(0, 5))
    }


def _mutate(rng: random.Random, data: bytes) -> bytes:
    buf = bytearray(data)
    for _ in range(rng.randint(1, 6)):
        op = rng.randrange(5)
        pos = rng.randrange(len(buf)) if buf else 0
        if op == 0 and buf:
            buf[pos] ^= 1 << rng.randrange(8)
        elif op == 1:
            buf[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif op == 2 and buf:
            del buf[pos : pos + rng.randint(1, 8)]
        elif op == 3 and buf:
            end = min(len(buf), pos + rng.randint(1, 32))
            buf[pos:pos] = buf[pos:end]
        elif op == 4 and buf:
            buf[pos] = rng.choice([0x00, 0x7F, 0x80, 0xC0, 0xC1, 0xC4, 0xC6, 0xD9, 0xDB, 0xDD, 0xDF, 0xFF])
    return bytes(buf)


def _huge(rng: random.Random) -> bytes:
    big = rng.choice([2**31 - 1, 2**32 - 1, 2**20 + 1, 2**16 + 1])
    header = msgpack.packb({"v": 1, "type": rng.choice(["frame", "status", "query_points", "save"])})
    assert isinstance(header, bytes)
    head = bytes([0x80 | (header[0] & 0x0F) + 1]) + header[1:]  # one more pair than written
    choice = rng.randrange(9)
    key = msgpack.packb(rng.choice(["rgb", "texts", "name", "K", "xyz", "depth_m", "x"]))
    assert isinstance(key, bytes)
    if choice == 0:
        tail = b"\xc6" + struct.pack(">I", big) + rng.randbytes(rng.randrange(0, 16))  # bin32
    elif choice == 1:
        tail = b"\xdb" + struct.pack(">I", big) + b"abc"  # str32
    elif choice == 2:
        tail = b"\xdd" + struct.pack(">I", big) + b"\x01\x02"  # array32
    elif choice == 3:
        tail = b"\xdf" + struct.pack(">I", big) + b"\xa1a\x01"  # map32
    elif choice == 4:
        tail = b"\xc9" + struct.pack(">I", big) + b"\x05xyz"  # ext32
    elif choice == 5:
        tail = b"\x91" * rng.randrange(100, 5000) + b"\xc0"  # nested arrays: recursion depth
    elif choice == 6:
        tail = b"\x81\xa1a" * rng.randrange(100, 5000) + b"\xc0"  # nested maps
    elif choice == 7:  # an nd array whose shape claims far more than its data
        arr = msgpack.packb({"dtype": "float32", "shape": [big, big], "data": b"\x00" * 8})
        assert isinstance(arr, bytes)
        tail = arr
    else:  # really above max_message_bytes (but below the transport's hard limit): too_large
        tail = b"\xc6" + struct.pack(">I", MAX_BYTES) + b"\x00" * (MAX_BYTES + rng.randrange(1, 1000))
    return head + key + tail


def _known_keys(rng: random.Random, wire: dict[str, Any]) -> bytes:
    wire = dict(wire)
    keys = [k for k in wire if k not in ("v", "type")] or ["id"]
    for key in rng.sample(keys, min(len(keys), rng.randint(1, 3))):
        wire[key] = _random_value(rng)
    if rng.random() < 0.1:
        wire["v"] = _random_value(rng)
    if rng.random() < 0.1:
        wire["type"] = rng.choice(["frame", "ack", "status", "render", "render_result", "nope", 5, None])
    try:
        out = msgpack.packb(wire, use_bin_type=True)
    except (ValueError, OverflowError, TypeError):
        out = protocol_samples.pack({"v": 1, "type": wire.get("type"), "id": "unpackable"})
    assert isinstance(out, bytes)
    return out


def generate(total: int, seed: int) -> Iterator[tuple[str, bytes]]:
    """``(family, data)`` for ``total`` inputs: a fixed share per family (hypothesis: 5 %)."""
    rng = random.Random(seed)
    corpus = _corpus()
    n_hyp = max(1, total // 20)
    rest = total - n_hyp
    per = [rest // 6] * 6
    per[0] += rest - sum(per)
    for family, count in zip(FAMILIES[:6], per, strict=True):
        for _ in range(count):
            data, wire = rng.choice(corpus)
            if family == "mutated":
                yield family, _mutate(rng, data)
            elif family == "truncated":
                yield family, data[: rng.randrange(len(data))]
            elif family == "random_msgpack":
                value: Any = _random_value(rng)
                if rng.random() < 0.5:
                    value = {
                        "v": 1,
                        "type": rng.choice(
                            ["frame", "status", "save", "load", "query_points", "segment_points", "render"]
                        ),
                        **(value if isinstance(value, dict) else {"x": value}),
                    }
                try:
                    packed = msgpack.packb(value, use_bin_type=True)
                except (ValueError, OverflowError, TypeError):
                    packed = b"\xc1"
                assert isinstance(packed, bytes)
                yield family, packed
            elif family == "known_keys":
                yield family, _known_keys(rng, wire)
            elif family == "huge_sizes":
                yield family, _huge(rng)
            else:
                yield family, rng.randbytes(rng.randrange(0, 300))
    yield from (("hypothesis", data) for data in _hypothesis_inputs(n_hyp, seed))


def _hypothesis_inputs(count: int, seed: int) -> list[bytes]:
    """``count`` messages drawn by Hypothesis from the protocol's strategies, encoded and (mostly)
    mutated: property-based inputs that reach deep into valid structure."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hyp_seed
    from hypothesis import strategies as st

    out: list[bytes] = []
    rng = random.Random(seed + 1)

    @hyp_seed(seed)
    @settings(
        max_examples=count,
        deadline=None,
        database=None,
        derandomize=False,
        suppress_health_check=list(HealthCheck),
    )
    @given(protocol_samples.messages, st.integers(0, 3))
    def draw(msg: Message, mode: int) -> None:
        try:
            data = encode(msg)
        except ProtocolError:
            return
        out.append(data if mode == 0 else _mutate(rng, data))

    while len(out) < count:  # hypothesis may stop early (small search space); draw again
        before = len(out)
        draw()
        if len(out) == before:
            break
    return out[:count]


# -- checks -----------------------------------------------------------------------------------


@dataclass
class Report:
    inputs: int = 0
    by_family: Counter[str] = field(default_factory=Counter)
    decode_outcomes: Counter[str] = field(default_factory=Counter)
    """``"<direction>:ok"`` or ``"<direction>:<error code>"``."""
    handler_replies: Counter[str] = field(default_factory=Counter)
    """``"<endpoint>:<reply type>"`` or ``"<endpoint>:error:<code>"``."""
    decoder_bugs: list[str] = field(default_factory=list)
    """Inputs on which a decoder raised something other than ProtocolError (must stay empty)."""
    reply_bugs: list[str] = field(default_factory=list)
    """Handler replies that were not exactly one valid message (must stay empty)."""
    seconds: dict[str, float] = field(default_factory=dict)
    socket: dict[str, Any] = field(default_factory=dict)
    internal_errors: int = 0


def _note(bugs: list[str], family: str, data: bytes, what: str) -> None:
    if len(bugs) < 20:
        bugs.append(f"{family}: {what}: input {data[:64].hex()}{'...' if len(data) > 64 else ''}")


def check_decoders(report: Report, family: str, data: bytes) -> None:
    for direction in ("request", "reply", "any"):
        try:
            msg = decode(data, max_bytes=MAX_BYTES, direction=direction)  # type: ignore[arg-type]
        except ProtocolError as exc:
            if exc.code not in ERROR_CODES or not exc.message:
                _note(report.decoder_bugs, family, data, f"bad ProtocolError {exc.code!r}")
            report.decode_outcomes[f"{direction}:{exc.code}"] += 1
            continue
        except Exception as exc:  # a decoder bug
            _note(report.decoder_bugs, family, data, f"{direction}: {type(exc).__name__}: {exc}")
            report.decode_outcomes[f"{direction}:BUG"] += 1
            continue
        report.decode_outcomes[f"{direction}:ok"] += 1
        try:
            if decode(encode(msg), max_bytes=1 << 31, direction=direction) != msg:  # type: ignore[arg-type]
                _note(report.decoder_bugs, family, data, "accepted message does not re-encode to itself")
        except Exception as exc:
            _note(report.decoder_bugs, family, data, f"re-encode failed: {type(exc).__name__}: {exc}")
    try:
        peek_id(data)
    except Exception as exc:
        _note(report.decoder_bugs, family, data, f"peek_id raised {type(exc).__name__}")


def _classify(report: Report, family: str, data: bytes, endpoint: str, reply: bytes) -> None:
    try:
        msg = decode(reply, max_bytes=1 << 31, direction="reply")
    except Exception as exc:
        _note(report.reply_bugs, family, data, f"{endpoint} reply does not decode: {exc}")
        report.handler_replies[f"{endpoint}:UNDECODABLE"] += 1
        return
    if isinstance(msg, Error):
        if msg.code == "internal":  # a handler bug (the node logged its traceback)
            _note(report.reply_bugs, family, data, f"{endpoint}: internal error: {msg.message}")
        if msg.code not in ERROR_CODES or not msg.message:
            _note(report.reply_bugs, family, data, f"{endpoint}: unclear error {msg.code!r} {msg.message!r}")
        report.handler_replies[f"{endpoint}:error:{msg.code}"] += 1
    else:
        report.handler_replies[f"{endpoint}:{msg.TYPE}"] += 1


def check_handlers(report: Report, node: MapperNode, family: str, data: bytes) -> None:
    for endpoint, handle in (("ingest", node.handle_ingest), ("query", node.handle_query)):
        try:
            reply = handle(data)
        except Exception as exc:  # the handlers must never raise
            _note(report.reply_bugs, family, data, f"{endpoint} handler raised {type(exc).__name__}: {exc}")
            report.handler_replies[f"{endpoint}:RAISED"] += 1
            continue
        _classify(report, family, data, endpoint, reply)


def socket_slice(report: Report, node: MapperNode, inputs: list[tuple[str, bytes]], timeout_s: float) -> None:
    """Send ``inputs`` over real sockets (alternating ingest / query), one at a time; each must
    get exactly one reply. Then ``status`` must answer on the same and on a fresh connection."""
    import zmq

    ctx = zmq.Context.instance()
    socks = {}
    for name, endpoint in (("ingest", node.config.ingest_endpoint), ("query", node.config.query_endpoint)):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(endpoint)
        socks[name] = sock
    replies: Counter[str] = Counter()
    missing = 0
    extra = 0
    started = time.perf_counter()
    try:
        for i, (family, data) in enumerate(inputs):
            name = "ingest" if i % 2 == 0 else "query"
            sock = socks[name]
            sock.send_multipart([b"", data])
            if not sock.poll(int(timeout_s * 1000)):
                missing += 1
                _note(report.reply_bugs, family, data, f"{name} socket: no reply within {timeout_s} s")
                continue
            parts = sock.recv_multipart()
            _classify(report, family, data, f"socket-{name}", parts[-1])
            replies[name] += 1
            while sock.poll(0):  # a second reply to one message would be a bug
                sock.recv_multipart()
                extra += 1
        after = {}
        for name, sock in socks.items():
            sock.send_multipart([b"", encode(StatusRequest(id="after"))])
            after[name] = bool(sock.poll(int(timeout_s * 1000))) and bool(sock.recv_multipart())
        fresh = ctx.socket(zmq.DEALER)
        fresh.setsockopt(zmq.LINGER, 0)
        fresh.connect(node.config.query_endpoint)
        fresh.send_multipart([b"", encode(StatusRequest(id="fresh"))])
        answered_fresh = bool(fresh.poll(int(timeout_s * 1000)))
        fresh.close()
    finally:
        for sock in socks.values():
            sock.close()
    report.socket = {
        "inputs": len(inputs),
        "replies": dict(replies),
        "no_reply": missing,
        "extra_replies": extra,
        "answers_after": {**after, "fresh_connection": answered_fresh},
        "seconds": time.perf_counter() - started,
    }


def _node(map_dir: Path, endpoints: tuple[str, str] | None) -> MapperNode:
    data: dict[str, Any] = {
        "map_dir": str(map_dir), "events_endpoint": "", "max_message_bytes": MAX_BYTES,
        "poll_interval_s": 0.02, "window": {"max_keyframes": 8},
    }  # fmt: skip
    if endpoints:
        data["ingest_endpoint"], data["query_endpoint"] = endpoints
    return MapperNode(config_from_dict(data))


def run(
    inputs: int = 100_000,
    socket_inputs: int = 3000,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
) -> Report:
    """Fuzz ``inputs`` inputs in-process and ``socket_inputs`` of them over sockets; the report."""
    logging.getLogger("mapper").setLevel(logging.CRITICAL)  # every bad input logs; keep the run quiet
    report = Report()
    with tempfile.TemporaryDirectory(prefix="govnesf-fuzz-") as tmp:
        node = _node(Path(tmp) / "maps", None)
        t0 = time.perf_counter()
        all_inputs = list(generate(inputs, seed))
        report.seconds["generate"] = time.perf_counter() - t0
        t_dec = t_handle = 0.0
        for i, (family, data) in enumerate(all_inputs):
            report.inputs += 1
            report.by_family[family] += 1
            t = time.perf_counter()
            check_decoders(report, family, data)
            t_dec += time.perf_counter() - t
            t = time.perf_counter()
            check_handlers(report, node, family, data)
            t_handle += time.perf_counter() - t
            if progress is not None and i % 10_000 == 9_999:
                progress(i + 1)
        report.seconds["decoders"] = t_dec
        report.seconds["handlers"] = t_handle
        with node.state.lock:
            report.internal_errors = node.state.error_counts["internal"]
        if socket_inputs:
            live = _node(Path(tmp) / "maps-live", (f"ipc://{tmp}/ingest.sock", f"ipc://{tmp}/query.sock"))
            live.start()
            try:
                step = max(1, len(all_inputs) // socket_inputs)
                hard_limit = HARD_LIMIT_FACTOR * MAX_BYTES  # above it ZeroMQ drops the connection
                picked = [x for x in all_inputs[::step] if len(x[1]) <= hard_limit][:socket_inputs]
                socket_slice(report, live, picked, timeout_s=10.0)
                with live.state.lock:
                    report.internal_errors += live.state.error_counts["internal"]
            finally:
                live.stop()
    return report


def to_json(report: Report, args: dict[str, Any]) -> dict[str, Any]:
    return {
        "benchmark": "fuzz",
        "args": args,
        "inputs": report.inputs,
        "by_family": dict(report.by_family),
        "decode_outcomes": dict(sorted(report.decode_outcomes.items())),
        "handler_replies": dict(sorted(report.handler_replies.items())),
        "internal_errors": report.internal_errors,
        "decoder_bugs": report.decoder_bugs,
        "reply_bugs": report.reply_bugs,
        "socket": report.socket,
        "seconds": report.seconds,
    }


def to_markdown(data: dict[str, Any]) -> str:
    lines = [
        "# Fuzzing the node", "",
        f"`{data['args']['command']}`", "",
        f"- inputs: **{data['inputs']:,}** in-process (each through `decode` x3 directions, "
        f"`handle_ingest`, `handle_query`), {data['socket'].get('inputs', 0):,} also over ipc",
        f"- internal errors: **{data['internal_errors']}**; decoder bugs: **{len(data['decoder_bugs'])}**; "
        f"reply bugs: **{len(data['reply_bugs'])}**",
        f"- socket slice: no reply {data['socket'].get('no_reply')}, extra replies "
        f"{data['socket'].get('extra_replies')}, answers afterwards {data['socket'].get('answers_after')}",
        f"- time: generate {data['seconds'].get('generate', 0):.1f} s, decoders "
        f"{data['seconds'].get('decoders', 0):.1f} s, handlers {data['seconds'].get('handlers', 0):.1f} s",
        "", "| family | inputs |", "|---|---|",
    ]  # fmt: skip
    lines += [f"| {k} | {v:,} |" for k, v in data["by_family"].items()]
    lines += ["", "| handler reply | count |", "|---|---|"]
    lines += [f"| {k} | {v:,} |" for k, v in data["handler_replies"].items()]
    lines += ["", "| decode outcome | count |", "|---|---|"]
    lines += [f"| {k} | {v:,} |" for k, v in data["decode_outcomes"].items()]
    for title, key in (("Decoder bugs", "decoder_bugs"), ("Reply bugs", "reply_bugs")):
        if data[key]:
            lines += ["", f"## {title}", ""] + [f"- `{b}`" for b in data[key]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", type=int, default=100_000, help="inputs in-process (default 100,000)")
    parser.add_argument(
        "--socket-inputs", type=int, default=3000, help="of them over sockets (default 3,000)"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO / "out" / "bench", help="output directory")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    report = run(
        args.inputs,
        args.socket_inputs,
        args.seed,
        progress=lambda n: print(f"  {n:,} inputs", file=sys.stderr, flush=True),
    )
    command = "benchmarks/robustness/fuzz.py " + " ".join(sys.argv[1:] if argv is None else argv)
    data = to_json(
        report,
        {
            "inputs": args.inputs,
            "socket_inputs": args.socket_inputs,
            "seed": args.seed,
            "command": command.strip(),
        },
    )
    data["seconds"]["total"] = time.perf_counter() - started
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fuzz.json").write_text(json.dumps(data, indent=1) + "\n")
    (args.out / "fuzz.md").write_text(to_markdown(data))
    print(to_markdown(data))
    ok = not (data["internal_errors"] or data["decoder_bugs"] or data["reply_bugs"])
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
