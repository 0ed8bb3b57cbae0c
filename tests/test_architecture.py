"""The layout's rules, checked from the source (docs/concepts/architecture.md, "Layout and import rules").

* no import cycle anywhere in protocol/, mapper/, clients/ (imports inside functions count: a
  cycle closed lazily is still a cycle);
* imports point one way between the top-level packages: protocol imports nothing of the project,
  mapper never imports clients, clients never import mapper;
* the node core (config, window, store, global map, queries, service) imports without torch.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "mapper", "clients")
HEAVY = ("torch", "open3d", "sentence_transformers", "trimesh")
"""Packages the node core must not load (the model, the simulator, the text encoder load them lazily)."""

NODE_CORE = (
    "mapper.errors",
    "mapper.checks",
    "mapper.kernels.average",
    "mapper.kernels.average_kernel",
    "mapper.map.window",
    "mapper.map.global_map",
    "mapper.map.evicted_views",
    "mapper.map.query_kernels",
    "mapper.node.config",
    "mapper.node.store",
    "mapper.node.queries",
    "mapper.node.keyframe_queue",
    "mapper.node.state",
    "mapper.node.integration",
    "mapper.node.context",
    "mapper.node.ingest",
    "mapper.node.query_pool",
    "mapper.node.answers.status",
    "mapper.node.answers.persistence",
    "mapper.node.answers.query_points",
    "mapper.node.answers.segment",
    "mapper.node.answers.render",
    "mapper.node.backends",
    "mapper.node.backends.average",
    "mapper.node.service",
    "mapper.runtime.config",
    "mapper.ov.config",
    "protocol",
)
"""The node core: imports without torch, and answers ``average`` / ``average_depth`` /
``query_points`` in a process where importing torch fails."""

MAP_LEAVES = ("mapper.map", "mapper.kernels", "mapper.checks", "mapper.errors")
"""The map and its kernels sit below the node: they import nothing of ``mapper.node``,
``mapper.model``, ``mapper.runtime`` or ``mapper.training``."""


def module_files() -> dict[str, Path]:
    """Every module of the project: dotted name -> file."""
    mods: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = path
    return mods


def _resolve(name: str, mods: dict[str, Path]) -> str | None:
    """The project module an imported dotted name lives in (``a.b.C`` -> ``a.b``), or None."""
    while name:
        if name in mods:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(mods: dict[str, Path] | None = None) -> dict[str, set[str]]:
    """module -> the project modules it imports (anywhere in the file, also inside functions)."""
    mods = module_files() if mods is None else mods
    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        package = mod if is_pkg else mod.rpartition(".")[0]
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*up, base] if base else up)
                # `from a import b` imports a.b when it is a module, else a name of a
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            for target in targets:
                found = _resolve(target, mods)
                if found is not None and found != mod:
                    edges.add(found)
        graph[mod] = edges
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_cycle_finder_finds_a_cycle_and_accepts_a_dag() -> None:
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_graph_sees_lazy_and_relative_imports(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from pkg import b\n")
    (pkg / "b.py").write_text("from .a import f\n")
    mods = {"pkg": pkg / "__init__.py", "pkg.a": pkg / "a.py", "pkg.b": pkg / "b.py"}
    graph = import_graph(mods)
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}
    assert find_cycles(graph) == [["pkg.a", "pkg.b"]]


def test_no_import_cycles() -> None:
    cycles = find_cycles(import_graph())
    assert not cycles, "import cycles (break them; docs/concepts/architecture.md): " + "; ".join(
        " <-> ".join(c) for c in cycles
    )


@pytest.mark.parametrize(
    ("source", "forbidden"),
    [("protocol", ("mapper", "clients")), ("mapper", ("clients",)), ("clients", ("mapper",))],
)
def test_imports_point_one_way(source: str, forbidden: tuple[str, ...]) -> None:
    bad = sorted(
        f"{mod} -> {dep}"
        for mod, deps in import_graph().items()
        if mod.split(".")[0] == source
        for dep in deps
        if dep.split(".")[0] in forbidden
    )
    assert not bad, f"{source} must not import {forbidden}: {bad}"


def test_node_core_imports_without_torch() -> None:
    code = (
        "import sys\n"
        f"for m in {NODE_CORE!r}:\n"
        "    __import__(m)\n"
        f"heavy = sorted(m for m in {HEAVY!r} if m in sys.modules)\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"the node core imported {out.stdout.strip()}"


def test_the_map_imports_nothing_above_it() -> None:
    above = ("mapper.node", "mapper.model", "mapper.runtime", "mapper.training", "mapper.ov")
    bad = sorted(
        f"{mod} -> {dep}"
        for mod, deps in import_graph().items()
        if mod.startswith(MAP_LEAVES)
        for dep in deps
        if dep.startswith(above)
    )
    assert not bad, f"the map must not import the node, the model or training: {bad}"


TORCH_FREE_ANSWERS = """
import sys
sys.modules["torch"] = None  # `import torch` raises ImportError from here on
import numpy as np
from clients.harness import DEMO_OV_DIM, DEMO_OV_SPACE, synthetic_frame
from mapper.node.config import config_from_dict
from mapper.node.service import MapperNode
from mapper.ov.encoders import register_text_encoder
from protocol.messages import Points, QueryPoints, Segmentation, SegmentPoints, decode, encode

class OneHot:
    space, dim = DEMO_OV_SPACE, DEMO_OV_DIM
    def encode(self, texts):  # sky, dark, light: the demo features' channels; other prompts elsewhere
        rows = {"sky": 0, "dark": 1, "light": 2}
        return np.stack([np.eye(DEMO_OV_DIM, dtype=np.float32)[rows.get(t, 3 + len(t) % 5)] for t in texts])

register_text_encoder(DEMO_OV_SPACE, OneHot)
node = MapperNode(config_from_dict({"map_dir": sys.argv[1], "autosave_name": "", "save_on_exit": False,
                                    "global_map": {"integrate_queue": 0}}))
for seq in range(0, 20, 2):
    node.handle_ingest(encode(synthetic_frame(seq, 20, 64, 48)))
xyz = np.asarray(node.state.global_map.snapshot().xyz[:200], np.float32)
for method in ("average", "average_depth"):
    reply = decode(node.handle_query(encode(SegmentPoints(xyz=xyz, texts=["sky", "dark", "light"],
                                                          method=method))), direction="reply")
    assert isinstance(reply, Segmentation), reply
    assert (reply.label >= 0).mean() > 0.5, (method, reply.label)
found = decode(node.handle_query(encode(QueryPoints(texts=["dark"]))), direction="reply")
assert isinstance(found, Points) and found.xyz.shape[0] > 0, found
print("torch" in sys.modules and sys.modules["torch"] is not None)
"""


def test_node_core_answers_averaging_and_queries_without_torch(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-c", TORCH_FREE_ANSWERS, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
        timeout=300, check=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == "False"


def _layout_tree() -> set[str]:
    """The paths the layout tree of docs/concepts/architecture.md names (``a/b.py``, ``a/``)."""
    text = (ROOT / "docs" / "concepts" / "architecture.md").read_text()
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    named: set[str] = set()
    stack: list[str] = []
    for line in block.splitlines():
        stripped = line.lstrip(" ")
        token = stripped.split(" ", 1)[0]
        if not token or not (token.endswith("/") or token.endswith(".py")):
            continue  # a description's continuation line
        depth = (len(line) - len(stripped)) // 2
        stack = stack[:depth]
        path = "/".join([*stack, token]).replace("//", "/")
        named.add(path)
        if token.endswith("/"):
            stack.append(token.rstrip("/"))
    return named


def test_the_layout_page_lists_every_module() -> None:
    named = _layout_tree()
    missing: list[str] = []
    for pkg in ("govnesf", "protocol", "mapper"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if path.name not in ("__init__.py", "__main__.py") and rel not in named:
                missing.append(rel)
    for path in sorted((ROOT / "clients").iterdir()):  # clients' subpackages may be summarised
        rel = path.relative_to(ROOT).as_posix() + ("/" if path.is_dir() else "")
        if path.name.startswith("__") or not (path.is_dir() or path.suffix == ".py"):
            continue
        if rel not in named:
            missing.append(rel)
    stale = sorted(p for p in named if not (ROOT / p.rstrip("/")).exists())
    assert not missing, f"docs/concepts/architecture.md's layout omits: {missing}"
    assert not stale, f"docs/concepts/architecture.md's layout names what does not exist: {stale}"
