"""Packaging rules that need no build (the wheel itself: tests/test_packaging_wheel.py).

* the core (protocol, client library, node core, CLI dispatcher) loads and a node starts without
  any optional extra being imported;
* a missing extra fails with a message naming it (``pip install 'govnesf[sim]'``), both from
  Python and from the ``govnesf`` command, while other import errors stay as they are;
* the version lives in one place (``govnesf/__init__.py``) and ``govnesf --version`` prints it;
* Python 3.10: no syntax and no standard-library names newer than 3.10 outside version guards,
  and the pyproject settings that make ruff and mypy check for 3.10.
"""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from govnesf import __version__
from govnesf._compat import tomllib
from govnesf._extras import EXTRAS, MissingExtraError, require

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

EXTRA_MODULES = ("open3d", "trimesh", "rerun", "cv2", "sentence_transformers", "transformers", "torch")
"""Modules the light entry points must not load (extras, and the heavy core parts loaded on use)."""


def _run(code: str, *, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter from the repository root."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=ROOT, capture_output=True, text=True, timeout=timeout,
        env={**_clean_env(), "PYTHONPATH": str(ROOT)},
    )  # fmt: skip


def _clean_env() -> dict[str, str]:
    import os

    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.setdefault("HF_HUB_OFFLINE", "1")
    return env


# ---------------------------------------------------------------------------------------------
# the core loads without the extras


def test_core_entry_points_load_no_extra(tmp_path: Path) -> None:
    """`import protocol`, the client library, a started node core (no model plugin) and the
    dispatcher's --version do not import an extra (nor torch or the text encoder)."""
    proc = _run(
        f"""
        import json, sys
        import protocol
        from protocol.messages import StatusRequest, Status, decode, encode
        import clients.client
        from clients.harness import free_endpoints
        from mapper.node.config import config_from_dict
        from mapper.node.service import MapperNode
        from clients.cli import main

        ingest, query = free_endpoints(2)
        cfg = config_from_dict({{"ingest_endpoint": ingest, "query_endpoint": query, "events_endpoint": "",
                                "serve_model": False, "map_dir": {str(tmp_path / "maps")!r}}})
        node = MapperNode(cfg)
        node.start()
        reply = decode(node.handle_query(encode(StatusRequest(id=1))))
        assert isinstance(reply, Status), reply
        node.stop()
        assert main(["--version"]) == 0
        print(json.dumps(sorted(m for m in {EXTRA_MODULES!r} if m in sys.modules)))
        """
    )
    assert proc.returncode == 0, proc.stderr
    *_, last = proc.stdout.strip().splitlines()
    assert json.loads(last) == [], f"the core imported {last}"
    assert f"govnesf {__version__}" in proc.stdout


def test_every_extra_is_declared() -> None:
    """The extras `require` knows are the ones pyproject declares, and [all] installs all of them."""
    optional = PYPROJECT["project"]["optional-dependencies"]
    assert set(EXTRAS) == set(optional) - {"all", "dev"}
    (everything,) = optional["all"]
    assert everything == f"govnesf[{','.join(EXTRAS)}]"
    core = " ".join(PYPROJECT["project"]["dependencies"])
    for heavy in ("open3d", "trimesh", "rerun-sdk"):
        assert heavy not in core, f"{heavy} belongs to an extra, not the core"


# ---------------------------------------------------------------------------------------------
# a missing extra names itself

# sys.modules[name] = None makes `import name` raise ModuleNotFoundError
BLOCK = "import sys\nfor _m in {mods!r}:\n    sys.modules[_m] = None\n"


@pytest.mark.parametrize(
    ("blocked", "code", "extra"),
    [
        # the simulator falls back to its torch ray casting without open3d; asking for open3d names it
        ("open3d", "from clients.sim.raycast import raycast_backend; raycast_backend('open3d')", "sim"),
        ("trimesh", "from clients.sim.export import write_ply; write_ply(None, None)", "sim"),
        ("regex", "import mapper.ov.clip_tokenizer", "clip"),
    ],
)
def test_missing_extra_is_named(blocked: str, code: str, extra: str) -> None:
    proc = _run(
        BLOCK.format(mods=[blocked])
        + "from govnesf._extras import MissingExtraError\n"
        + f"try:\n    {code}\nexcept MissingExtraError as exc:\n"
        + "    print('EXTRA', exc.extra, exc.module); print(exc)\nelse:\n    print('NO ERROR')\n"
    )
    assert proc.returncode == 0, proc.stderr
    assert f"EXTRA {extra} {blocked}" in proc.stdout
    assert f"pip install 'govnesf[{extra}]'" in proc.stdout


def test_missing_rerun_names_the_extra(tmp_path: Path) -> None:
    proc = _run(
        BLOCK.format(mods=["rerun"])
        + "from clients.rerun_log import RerunLogError, check_rrd_path\n"
        + f"try:\n    check_rrd_path({str(tmp_path / 'x.rrd')!r})\n"
        + "except RerunLogError as exc:\n    print(exc)\n"
    )
    assert proc.returncode == 0, proc.stderr
    assert "pip install 'govnesf[rerun]'" in proc.stdout


def test_cli_reports_a_missing_extra(tmp_path: Path) -> None:
    """`govnesf sim record` with Open3D ray casting asked for (GOVNESF_SIM_RAYCAST=open3d) and not
    installed: exit code 2 and one line naming the extra, no traceback, nothing written."""
    out = tmp_path / "rec"
    proc = _run(
        BLOCK.format(mods=["open3d"])
        + "import os\nos.environ['GOVNESF_SIM_RAYCAST'] = 'open3d'\n"
        + "from clients.cli import main\n"
        + "raise SystemExit(main(['sim', 'record', '--seed', '0', '--frames', '2', '--no-ov', "
        + f"'--out', {str(out)!r}]))\n"
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "govnesf sim: 'open3d' is not installed" in proc.stderr
    assert "pip install 'govnesf[sim]'" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists()


def test_require(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert require("json", "sim") is json
    with pytest.raises(ValueError, match="unknown extra 'gpu'"):
        require("json", "gpu")
    monkeypatch.setitem(sys.modules, "open3d", None)
    with pytest.raises(MissingExtraError, match=r"govnesf\[sim\]") as exc:
        require("open3d", "sim")
    assert isinstance(exc.value, ImportError) and exc.value.name == "open3d"
    # a module that is there but fails on a dependency of its own is not a missing extra
    (tmp_path / "h1_broken_mod.py").write_text("import h1_no_such_dependency\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError) as broken:
        require("h1_broken_mod", "sim")
    assert not isinstance(broken.value, MissingExtraError)
    assert broken.value.name == "h1_no_such_dependency"


# ---------------------------------------------------------------------------------------------
# version


def test_version_in_one_place() -> None:
    assert PYPROJECT["project"]["dynamic"] == ["version"]
    assert "version" not in PYPROJECT["project"]
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "govnesf.__version__"}
    assert __version__.count(".") == 2 and all(p.isdigit() for p in __version__.split("."))
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert f"## [{__version__}]" in changelog, "CHANGELOG.md has no section for the current version"
    assert changelog.index("## [Unreleased]") < changelog.index(f"## [{__version__}]")  # Keep a Changelog
    proc = subprocess.run(
        [sys.executable, "-m", "clients.cli", "--version"],
        cwd=ROOT, capture_output=True, text=True, timeout=30, env={**_clean_env(), "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert proc.returncode == 0 and proc.stdout.strip() == f"govnesf {__version__}"


def test_license_metadata() -> None:
    assert PYPROJECT["project"]["license"] == "Apache-2.0"
    assert PYPROJECT["project"]["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    for pkg in ("protocol", "mapper", "clients", "govnesf"):
        assert (ROOT / pkg / "py.typed").is_file(), f"{pkg}/py.typed missing"


# ---------------------------------------------------------------------------------------------
# Python 3.10

CORE_DIRS = ("protocol", "mapper", "clients", "govnesf")

NEWER_THAN_310: dict[str, set[str]] = {
    # module -> names added after Python 3.10
    "typing": {"Self", "LiteralString", "Never", "assert_never", "assert_type", "reveal_type",
               "dataclass_transform", "NotRequired", "Required", "TypeVarTuple", "Unpack",
               "get_overloads", "clear_overloads", "override", "TypeAliasType", "get_protocol_members",
               "is_protocol", "ReadOnly", "TypeIs", "NoDefault"},
    "enum": {"StrEnum", "ReprEnum", "EnumCheck", "FlagBoundary", "verify", "member", "nonmember",
             "global_enum", "property", "show_flag_values", "EnumType"},
    "datetime": {"UTC"},
    "asyncio": {"TaskGroup", "timeout", "timeout_at", "Runner", "Timeout"},
    "contextlib": {"chdir"},
    "hashlib": {"file_digest"},
    "itertools": {"batched"},
    "operator": {"call"},
    "logging": {"getLevelNamesMapping"},
    "math": {"cbrt", "exp2"},
}  # fmt: skip
NEW_MODULES = {"tomllib", "wsgiref.types"}
NEW_BUILTINS = {"ExceptionGroup", "BaseExceptionGroup"}


def _python_files() -> list[Path]:
    return [p for d in CORE_DIRS for p in sorted((ROOT / d).rglob("*.py"))]


def _is_version_guard(test: ast.expr) -> bool:
    return "version_info" in ast.unparse(test)


def _unguarded(tree: ast.Module) -> list[ast.AST]:
    """Every node outside the body of an ``if sys.version_info ...`` guard (its else branch counts)."""
    out: list[ast.AST] = []

    def visit(node: ast.AST) -> None:
        out.append(node)
        if isinstance(node, ast.If) and _is_version_guard(node.test):
            for child in node.orelse:
                visit(child)
            return
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return out


def newer_than_310(path: Path) -> list[str]:
    """``file:line what`` for each 3.11+ syntax or standard-library name used outside a guard."""
    src = path.read_text()
    try:
        tree = ast.parse(src, str(path), feature_version=(3, 10))
    except SyntaxError as exc:
        return [f"{path}:{exc.lineno} syntax newer than Python 3.10: {exc.msg}"]
    found: list[str] = []
    imported: dict[str, str] = {}  # local name -> module, for `import enum` / `import typing as t`
    for node in _unguarded(tree):
        where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in NEW_MODULES:
                    found.append(f"{where} import {alias.name}")
                imported[alias.asname or alias.name] = alias.name
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            if node.module in NEW_MODULES:
                found.append(f"{where} from {node.module} import")
            for alias in node.names:
                if alias.name in NEWER_THAN_310.get(node.module, set()):
                    found.append(f"{where} from {node.module} import {alias.name}")
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            module = imported.get(node.value.id)
            if module and node.attr in NEWER_THAN_310.get(module, set()):
                found.append(f"{where} {node.value.id}.{node.attr}")
        elif isinstance(node, ast.Name) and node.id in NEW_BUILTINS:
            found.append(f"{where} {node.id}")
    return found


def test_no_python_311_features_in_the_package() -> None:
    files = _python_files()
    assert len(files) > 50
    problems = [p for f in files for p in newer_than_310(f)]
    assert problems == [], "Python >= 3.11 only (guard with sys.version_info):\n" + "\n".join(problems)


def test_the_checker_finds_311_features(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The check above is not vacuous: each kind of 3.11 feature in a file is reported."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    bad = tmp_path / "bad.py"
    bad.write_text(
        "import sys\nimport tomllib\nimport enum\nfrom typing import Self, Any\n"
        "class C(enum.StrEnum):\n    A = 'a'\n"
        "def f() -> None:\n    raise ExceptionGroup('x', [ValueError()])\n"
        "if sys.version_info >= (3, 11):\n    from typing import Never\n"
        "else:\n    from typing import Required\n"
    )
    assert [p.split(" ", 1)[1] for p in newer_than_310(bad)] == [
        "import tomllib", "from typing import Self", "enum.StrEnum", "ExceptionGroup",
        "from typing import Required",
    ]  # fmt: skip
    star = tmp_path / "star.py"
    star.write_text("try:\n    pass\nexcept* ValueError:\n    pass\n")
    assert "syntax newer than Python 3.10" in newer_than_310(star)[0]


def test_tools_check_python_310() -> None:
    assert PYPROJECT["project"]["requires-python"] == ">=3.10"
    assert PYPROJECT["tool"]["mypy"]["python_version"] == "3.10"
    assert PYPROJECT["tool"]["ruff"]["target-version"] == "py310"
    deps = PYPROJECT["project"]["dependencies"]
    assert any(d.startswith("tomli==") and "python_version < '3.11'" in d for d in deps)


def _python310() -> str | None:
    """A working CPython 3.10: python3.10 on PATH, else a pyenv install (a pyenv shim on PATH may
    point at another version and fail)."""
    pyenv = sorted(Path.home().glob(".pyenv/versions/3.10.*/bin/python3.10"))
    for found in [shutil.which("python3.10"), *map(str, reversed(pyenv))]:
        if found is None:
            continue
        probe = subprocess.run([found, "-c", "import sys; print(sys.version_info[:2])"],
                               capture_output=True, text=True, timeout=30)  # fmt: skip
        if probe.returncode == 0 and probe.stdout.strip() == "(3, 10)":
            return found
    return None


def test_compiles_with_a_real_python_310() -> None:
    """Every project file compiles with an actual CPython 3.10 (skipped where none is installed)."""
    py310 = _python310()
    if py310 is None:
        pytest.skip("no Python 3.10 interpreter on this machine (python3.10 / pyenv)")
    files = [str(p) for p in _python_files()]
    code = (
        "import sys\nbad = []\nfor f in sys.argv[1:]:\n"
        "    try:\n        compile(open(f, encoding='utf-8').read(), f, 'exec')\n"
        "    except SyntaxError as exc:\n        bad.append(f'{f}:{exc.lineno}: {exc.msg}')\n"
        "print('\\n'.join(bad)); sys.exit(1 if bad else 0)\n"
    )
    proc = subprocess.run([py310, "-c", code, *files], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_govnesf_package_is_a_leaf() -> None:
    """govnesf/ (version, extras, resources) imports nothing of the project, so every package may use it."""
    for path in sorted((ROOT / "govnesf").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            for name in names:
                assert name.split(".")[0] not in ("protocol", "mapper", "clients"), f"{path}: imports {name}"


def test_demo_reports_a_missing_extra(tmp_path: Path) -> None:
    """`make demo` without [sim] (trimesh; open3d is optional since the simulator can ray cast with
    torch): exit code 2 naming the extra, before anything is written."""
    out = tmp_path / "demo"
    proc = _run(
        BLOCK.format(mods=["open3d", "trimesh"])
        + "from clients.demo import main\n"
        + f"raise SystemExit(main(['--out', {str(out)!r}]))\n"
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "pip install 'govnesf[sim]'" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()
