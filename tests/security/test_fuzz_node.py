"""The fast subset of ``benchmarks/robustness/fuzz.py``: ~1,500 hostile inputs through every decoder and both
request handlers, 150 of them over real sockets; no internal errors, one clear reply each, and the
node answers afterwards. (``benchmarks/robustness/fuzz.py`` runs 100,000.)"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from protocol.errors import ERROR_CODES

REPO = Path(__file__).resolve().parents[2]


def _fuzz() -> ModuleType:
    script = REPO / "benchmarks" / "robustness" / "fuzz.py"
    spec = importlib.util.spec_from_file_location("benchmarks_fuzz", script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_fast_fuzz_subset_finds_no_internal_error_and_the_node_keeps_answering() -> None:
    fuzz = _fuzz()
    report = fuzz.run(inputs=1500, socket_inputs=150, seed=12)
    assert report.inputs == 1500
    assert set(report.by_family) == set(fuzz.FAMILIES)
    assert report.internal_errors == 0, report.reply_bugs
    assert report.decoder_bugs == [] and report.reply_bugs == []
    # two handler replies per input (ingest and query), every one classified
    assert sum(v for k, v in report.handler_replies.items() if not k.startswith("socket")) == 3000
    codes = {k.rsplit(":", 1)[1] for k in report.handler_replies if ":error:" in k}
    assert codes <= set(ERROR_CODES) and {"bad_request", "too_large"} <= codes
    assert report.socket["inputs"] == 150 and report.socket["no_reply"] == 0
    assert report.socket["extra_replies"] == 0
    assert all(report.socket["answers_after"].values())


def test_generation_is_deterministic_per_seed() -> None:
    fuzz = _fuzz()
    first = [data for family, data in fuzz.generate(300, seed=5) if family != "hypothesis"]
    again = [data for family, data in fuzz.generate(300, seed=5) if family != "hypothesis"]
    assert first == again and len(first) == 285
