"""The built wheel works installed, outside the checkout.

Builds the wheel from a copy of the source tree (``pip wheel --no-deps --no-build-isolation``),
installs it into a fresh virtual environment in a temporary folder, and from a temporary working
directory runs the installed ``govnesf``: ``--version``, ``serve`` on free loopback ports with its
default (packaged) config, ``status`` and a ``render`` by the learned model, whose checkpoint must
come from the wheel's package data.

The new environment reuses this environment's already-installed dependencies through a ``.pth``
file (they are large); the project's own packages come from the wheel only, which the test
checks by their ``__file__`` paths (a ``.pth`` line adds a folder to ``sys.path`` but does not run
that folder's own ``.pth`` files, so this checkout's editable install stays out).
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from clients.client import MapperClient
from clients.harness import free_endpoints, synthetic_frames
from govnesf import __version__

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "mapper", "clients", "govnesf")

pytestmark = pytest.mark.slow


def _source_files() -> list[str]:
    """The files of the source tree: what git tracks or would track (never data/, .venv, out/)."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-co", "--exclude-standard", "-z"],
            cwd=ROOT, capture_output=True, check=True, timeout=60,
        ).stdout.decode()  # fmt: skip
        files = [f for f in out.split("\0") if f and (ROOT / f).is_file()]
    except (OSError, subprocess.CalledProcessError):
        files = []
    if not files:  # not a git checkout: the packaging inputs only
        keep = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "CHANGELOG.md")
        files = [k for k in keep if (ROOT / k).is_file()]
        for top in (*PACKAGES, "checkpoints", "launch"):
            files += [str(p.relative_to(ROOT)) for p in (ROOT / top).rglob("*")
                      if p.is_file() and "__pycache__" not in p.parts]  # fmt: skip
    return files


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1", PYTHONNOUSERSITE="1", **extra)
    return env


def _run(cmd: list[str], cwd: Path, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=_env())


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path]]:
    """Build the wheel and install it into a fresh venv; yields the venv's paths."""
    base = tmp_path_factory.mktemp("wheel")
    src, dist, venv, cwd = base / "src", base / "dist", base / "venv", base / "cwd"
    for rel in _source_files():
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, src / rel)
    cwd.mkdir()
    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                  "-q", "-w", str(dist), str(src)], cwd=cwd, timeout=300)  # fmt: skip
    assert built.returncode == 0, built.stdout + built.stderr
    (wheel,) = dist.glob("govnesf-*.whl")

    made = _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=cwd)
    assert made.returncode == 0, made.stderr
    purelib = Path(
        subprocess.run(
            [str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True, text=True, check=True, timeout=60, env=_env(),
        ).stdout.strip()
    )  # fmt: skip
    # this environment's installed dependencies (and pip), after the new venv's own site-packages
    here = [p for p in dict.fromkeys([*site.getsitepackages(), sysconfig.get_paths()["purelib"]])
            if Path(p).is_dir()]  # fmt: skip
    (purelib / "_govnesf_test_deps.pth").write_text("\n".join(here) + "\n")
    inst = _run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                 "--ignore-installed", "--no-warn-script-location", str(wheel)], cwd=cwd)  # fmt: skip
    assert inst.returncode == 0, inst.stdout + inst.stderr
    yield {"wheel": wheel, "venv": venv, "purelib": purelib, "cwd": cwd, "base": base}


def test_wheel_contents(installed: dict[str, Path]) -> None:
    """Every project module, the checkpoints, the presets, py.typed, LICENSE and the metadata."""
    with zipfile.ZipFile(installed["wheel"]) as zf:
        names = set(zf.namelist())
        meta = zf.read(f"govnesf-{__version__}.dist-info/METADATA").decode()
    modules = {str(p.relative_to(ROOT)) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if "__pycache__" not in p.parts}  # fmt: skip
    assert modules - names == set(), "modules missing from the wheel"
    for folder in ("checkpoints", "launch"):
        shipped = {f"govnesf/{folder}/{p.name}" for p in (ROOT / folder).iterdir() if p.is_file()}
        assert shipped and shipped <= names, f"{folder}/ missing from the wheel"
    assert {f"{pkg}/py.typed" for pkg in PACKAGES} <= names
    assert f"govnesf-{__version__}.dist-info/licenses/LICENSE" in names
    assert f"Version: {__version__}\n" in meta and "License-Expression: Apache-2.0\n" in meta
    assert "Requires-Python: >=3.10\n" in meta
    assert 'Provides-Extra: sim\n' in meta
    # open3d only where it has a wheel (x86-64 Linux); elsewhere the simulator ray casts with torch
    (open3d,) = [line for line in meta.splitlines() if line.startswith("Requires-Dist: open3d-cpu==0.20.0")]
    assert 'extra == "sim"' in open3d and 'platform_machine == "x86_64"' in open3d


def test_installed_packages_come_from_the_wheel(installed: dict[str, Path]) -> None:
    code = (
        "import json, govnesf, mapper, clients, protocol, mapper.node.config as c, govnesf.resources as r\n"
        "print(json.dumps({'files': [m.__file__ for m in (govnesf, mapper, clients, protocol)],\n"
        "                  'config': str(c.DEFAULT_CONFIG_PATH), 'data': str(r.data_root())}))\n"
    )
    proc = _run([str(installed["venv"] / "bin" / "python"), "-c", code], cwd=installed["cwd"])
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    purelib = installed["purelib"].resolve()
    for file in info["files"]:
        assert Path(file).resolve().is_relative_to(purelib), f"{file} does not come from the wheel"
    assert Path(info["config"]).resolve() == purelib / "govnesf" / "launch" / "node.toml"
    assert Path(info["data"]).resolve() == purelib / "govnesf"
    version = _run([str(installed["venv"] / "bin" / "govnesf"), "--version"], cwd=installed["cwd"])
    assert version.returncode == 0 and version.stdout.strip() == f"govnesf {__version__}"


def test_installed_serve_finds_its_model(installed: dict[str, Path]) -> None:
    """`govnesf serve` from the wheel, default config, no checkout in sight: the packaged
    checkpoint loads, `govnesf status` reports the model without a load error, and a `render`
    (the learned model) of a few streamed frames succeeds."""
    govnesf = str(installed["venv"] / "bin" / "govnesf")
    cwd, base = installed["cwd"], installed["base"]
    ingest, query = free_endpoints(2)
    log_path = base / "serve.log"
    with open(log_path, "wb") as log:
        node = subprocess.Popen(
            [govnesf, "serve", "--ingest", ingest, "--query", query, "--events", "",
             "--map-dir", str(base / "maps"), "--log-level", "INFO"],
            cwd=cwd, env=_env(), stdout=log, stderr=log,
        )  # fmt: skip
    try:
        with MapperClient(ingest=ingest, query=query, timeout_s=0.5, retries=0) as client:
            deadline = time.monotonic() + 60
            while True:
                assert node.poll() is None, f"node exited: {log_path.read_text()}"
                try:
                    client.status()
                    break
                except TimeoutError:
                    assert time.monotonic() < deadline, f"node never answered: {log_path.read_text()}"
        status = _run([govnesf, "status", "--query", query, "--json"], cwd=cwd)
        assert status.returncode == 0, status.stdout + status.stderr
        model = json.loads(status.stdout)["model"]  # the status extras, flattened
        assert model["load_error"] is None, model
        served = log_path.read_text()
        packaged = installed["purelib"] / "govnesf" / "checkpoints" / "cpu-small.safetensors"
        assert f"loaded GOV-NeSF checkpoint {packaged}" in served, served

        with MapperClient(ingest=ingest, query=query, timeout_s=30) as client:
            for frame in synthetic_frames(12, 64, 48):
                client.send_frame(frame)
        out = base / "view.png"
        render = _run([govnesf, "render", "--query", query, "--pose", "3.0,0.0,1.5,180,-20",
                       "--width", "32", "--height", "24", "--out", str(out)],
                      cwd=cwd, timeout=180)  # fmt: skip
        assert render.returncode == 0, render.stdout + render.stderr + log_path.read_text()
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        node.terminate()
        try:
            node.wait(timeout=20)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait(timeout=10)


def test_installed_bench_runs_outside_the_checkout(installed: dict[str, Path]) -> None:
    """`govnesf bench --quick` from the wheel: the node and the map writer of its query_points phase
    (``python -m mapper.bench.synthetic_maps``) come from the installed packages, not a checkout."""
    govnesf = str(installed["venv"] / "bin" / "govnesf")
    out = installed["base"] / "bench" / "node"
    quick = ["--quick", "--out", str(out), "--node-arg=--set", "--node-arg=serve_model=false"]
    done = _run([govnesf, "bench", *quick], cwd=installed["cwd"], timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads(out.with_suffix(".json").read_text())
    assert result["query_points"]["1000"]["first"]["n"] == 1
    where = "import mapper.bench.synthetic_maps as m; print(m.__file__)"
    writer = _run([str(installed["venv"] / "bin" / "python"), "-c", where], cwd=installed["cwd"])
    assert writer.returncode == 0, writer.stderr
    assert Path(writer.stdout.strip()).resolve().is_relative_to(installed["purelib"].resolve())
