#!/usr/bin/env bash
# Prove the platform claim of the core install (docs/getting-started/install.md): `pip download --only-binary=:all:`
# of the core's dependency set (pyproject.toml [project.dependencies], exact pins, and whatever
# they pull in) for a platform that is not this machine's, into a temporary folder that is deleted
# afterwards. A platform passes when every package of the set has a binary wheel for it.
#
#   bash scripts/check_platforms.sh              # download (several GB for aarch64 Linux: torch's CUDA libraries)
#   bash scripts/check_platforms.sh --dry-run    # resolve only, from the wheels' metadata (seconds)
#   PYTHONS="3.10 3.12" bash scripts/check_platforms.sh   # Python versions to check (default 3.10)
#
# pip evaluates environment markers for the machine it runs on, not for --platform (so on this
# Linux x86_64 machine it would ask for torch's Linux-only CUDA packages for macOS too). The script
# therefore runs pip with the target's marker environment (sys_platform, platform_system,
# platform_machine, python_version); everything else is plain `pip download`.
# Output: one line per target, PASS/FAIL, then the wheels that are not pure Python. Exit code 1
# when a claimed target fails.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
PYTHONS=${PYTHONS:-3.10}
MODE=download
if [ "${1:-}" = "--dry-run" ]; then MODE=dry-run; fi

WORK=$(mktemp -d /tmp/govnesf-platforms.XXXXXX)
trap 'rm -rf "$WORK"' EXIT

# The core's direct requirements, markers kept (the wrapper evaluates them for the target).
"$PY" - > "$WORK/core.txt" <<'EOF'
from govnesf._compat import tomllib
with open("pyproject.toml", "rb") as fh:
    print("\n".join(tomllib.load(fh)["project"]["dependencies"]))
EOF

# pip's own main, with the target's marker environment (argv: SYS_PLATFORM SYSTEM MACHINE PYVER pip-args...)
cat > "$WORK/pip_for.py" <<'EOF'
import sys
from pip._internal.cli.main import main
from pip._vendor.packaging import markers

sys_platform, system, machine, pyver = sys.argv[1:5]
_default = markers.default_environment

def target_environment():
    env = _default()
    env.update(sys_platform=sys_platform, platform_system=system, platform_machine=machine,
               python_version=pyver, python_full_version=pyver + ".0", implementation_name="cpython",
               platform_python_implementation="CPython", os_name="posix")
    return env

markers.default_environment = target_environment
sys.exit(main(sys.argv[5:]))
EOF

# target name | claimed? | sys_platform system machine | --platform tags. A target that is not
# claimed (macOS 11: torch 2.13.0, OpenCV and SciPy ship no wheel for it) is reported, not failed. pip does not widen a --platform tag to
# the older tags it is compatible with, so aarch64 Linux lists glibc 2.17 .. 2.35 (Ubuntu 22.04,
# ROS 2 Humble, JetPack 6); a macOS tag covers itself and older macOS versions.
TARGETS=(
  "linux-aarch64|claimed|linux Linux aarch64|$(for m in $(seq 35 -1 17); do printf 'manylinux_2_%s_aarch64 ' "$m"; done)manylinux2014_aarch64"
  "macos-11-arm64|not claimed|darwin Darwin arm64|macosx_11_0_arm64"
  "macos-14-arm64|claimed|darwin Darwin arm64|macosx_14_0_arm64"
)

status=0
for pyver in $PYTHONS; do
  for target in "${TARGETS[@]}"; do
    IFS='|' read -r name claim env tags <<<"$target"
    read -r sys_platform system machine <<<"$env"
    dest="$WORK/$name-py$pyver"
    mkdir -p "$dest"
    platform_args=()
    for tag in $tags; do platform_args+=(--platform "$tag"); done
    common=(--only-binary=:all: "${platform_args[@]}" --python-version "$pyver" --implementation cp
            --disable-pip-version-check -r "$WORK/core.txt")
    if [ "$MODE" = download ]; then
      cmd=(download -q -d "$dest" "${common[@]}")
    else
      cmd=(install -q --dry-run --ignore-installed --target "$dest/t" --report "$dest/report.json" "${common[@]}")
    fi
    start=$(date +%s)
    if "$PY" "$WORK/pip_for.py" "$sys_platform" "$system" "$machine" "$pyver" "${cmd[@]}" \
        > "$dest/pip.log" 2>&1; then
      "$PY" - "$dest" "$name" "$pyver" "$MODE" "$(( $(date +%s) - start ))" <<'EOF'
import json, sys
from pathlib import Path
dest, name, pyver, mode, secs = Path(sys.argv[1]), *sys.argv[2:]
if mode == "download":
    files = sorted(p.name for p in dest.glob("*.whl"))
    size = sum(p.stat().st_size for p in dest.glob("*.whl")) / 2**20
    what = f"{len(files)} wheels, {size:.0f} MiB downloaded"
else:
    report = json.loads((dest / "report.json").read_text())
    files = sorted(Path(i["download_info"]["url"]).name for i in report["install"])
    what = f"{len(files)} wheels resolved (metadata only)"
torch = next((f for f in files if f.startswith("torch-")), "no torch wheel")
print(f"PASS {name} python {pyver}: {what} in {secs} s; {torch}")
for f in files:
    if not f.endswith("-none-any.whl") and not f.startswith("torch-"):
        print(f"     {f}")
EOF
    else
      if [ "$claim" = claimed ]; then status=1; fi
      echo "FAIL $name python $pyver ($claim):"
      grep -E "^ERROR: (Could not|No matching|Cannot)|conflict is caused|depends on|requested" "$dest/pip.log" \
        | grep -v "Ignored the following" | sed 's/^ */     /' | head -6
      while read -r req; do  # which of the core's own requirements has no wheel for the target
        if ! "$PY" "$WORK/pip_for.py" "$sys_platform" "$system" "$machine" "$pyver" install -q --dry-run \
            --ignore-installed --no-deps --target "$dest/t" --only-binary=:all: "${platform_args[@]}" \
            --python-version "$pyver" --implementation cp --disable-pip-version-check "$req" > /dev/null 2>&1; then
          echo "     no wheel for the target: $req"
        fi
      done < "$WORK/core.txt"
    fi
    rm -rf "$dest"
  done
done
exit $status
