"""The matrix's outputs: per-scenario JSON lines, a Markdown summary, a heat map.

Figures per scenario (:func:`figures`), each a number or None where it does not apply:

* ``{method} window settled`` / ``{method} all settled`` / ``{method} window after ack``: 3D mIoU;
* ``govnesf - average`` and ``dgm - average_depth`` (learned minus averaging, points; at the
  default window, settled and right after the last ack);
* ``window - all ({method})``: what the default window loses against every keyframe (settled);
* ``after ack - settled ({method})``: what background work changes (window; negative: the
  settled answer is better);
* ``settle s`` (window / all), ``find chair m``, ``objects found``, ``render depth err``,
  ``render PSNR dB``.

The summary gives, per figure, the median over scenarios and the WORST scenario (lowest for
scores and gaps, highest for errors, distances and times), with its name.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

METHODS = ("govnesf", "average", "dgm", "average_depth")
HIGHER_IS_WORSE = ("settle s", "find chair m", "render depth err")


def _get(d: dict[str, Any], *keys: str) -> float | None:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return float(d) if isinstance(d, int | float) and not isinstance(d, bool) else None


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def figures(row: dict[str, Any]) -> dict[str, float | None]:
    """The summary figures of one scenario row (see the module docstring)."""
    out: dict[str, float | None] = {}
    for m in METHODS:
        out[f"{m} window settled"] = _get(row, "window", "settled", m)
        out[f"{m} all settled"] = _get(row, "all", "settled", m)
        out[f"{m} window after ack"] = _get(row, "window", "after_ack", m)
    for when, key in (("settled", "settled"), ("after ack", "after_ack")):
        out[f"govnesf - average ({when})"] = _diff(_get(row, "window", key, "govnesf"),
                                                   _get(row, "window", key, "average"))
        out[f"dgm - average_depth ({when})"] = _diff(_get(row, "window", key, "dgm"),
                                                     _get(row, "window", key, "average_depth"))
    for m in METHODS:
        out[f"window - all ({m})"] = _diff(out[f"{m} window settled"], out[f"{m} all settled"])
    for m in METHODS:
        out[f"after ack - settled ({m})"] = _diff(out[f"{m} window after ack"], out[f"{m} window settled"])
    out["settle s (window)"] = _get(row, "window", "settle_s")
    out["settle s (all)"] = _get(row, "all", "settle_s")
    out["find chair m"] = _get(row, "window", "find_chair_m")
    found = _get(row, "window", "objects_found_share")
    out["objects found %"] = None if found is None else 100.0 * found
    out["render depth err"] = _get(row, "window", "render_depth_rel_err")
    out["render PSNR dB"] = _get(row, "window", "render_psnr_db")
    return out


def _worse_is_higher(name: str) -> bool:
    return any(name.startswith(p) for p in HIGHER_IS_WORSE)


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per figure: n, median, worst value and the worst scenario's name."""
    per = [(r["name"], figures(r)) for r in rows]
    names = list(per[0][1]) if per else []
    out = []
    for f in names:
        vals = [(n, v[f]) for n, v in per if v[f] is not None and math.isfinite(v[f])]  # type: ignore[arg-type]
        if not vals:
            out.append({"figure": f, "n": 0, "median": None, "worst": None, "worst_scenario": None})
            continue
        pick = max if _worse_is_higher(f) else min
        worst_name, worst = pick(vals, key=lambda t: t[1])  # type: ignore[arg-type,return-value]
        out.append({"figure": f, "n": len(vals), "median": float(np.median([v for _, v in vals])),
                    "worst": worst, "worst_scenario": worst_name})
    return out


def _fmt(v: Any, figure: str = "") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if figure.startswith("render depth err"):
            return f"{100 * v:.1f}%"
        return f"{v:.2f}" if abs(v) < 10 else f"{v:.1f}"
    return str(v)


def markdown(rows: list[dict[str, Any]], header: str = "") -> str:
    """The summary table (median and worst per figure) and a per-scenario table of the main figures."""
    lines = [header] if header else []
    lines += ["| figure | scenarios | median | worst | worst scenario |", "|---|---|---|---|---|"]
    for s in summarise(rows):
        lines.append(f"| {s['figure']} | {s['n']} | {_fmt(s['median'], s['figure'])} | "
                     f"{_fmt(s['worst'], s['figure'])} | {s['worst_scenario'] or '-'} |")
    main = ["govnesf window settled", "average window settled", "dgm window settled",
            "average_depth window settled", "govnesf - average (settled)", "govnesf - average (after ack)",
            "window - all (govnesf)", "window - all (average)", "after ack - settled (govnesf)",
            "settle s (window)", "find chair m", "render depth err", "render PSNR dB"]
    lines += ["", "| scenario | " + " | ".join(main) + " |", "|---|" + "---|" * len(main)]
    for r in rows:
        f = figures(r)
        lines.append(f"| {r['name']} | " + " | ".join(_fmt(f[k], k) for k in main) + " |")
    return "\n".join(lines) + "\n"


def heatmap(rows: list[dict[str, Any]], path: Path) -> None:
    """Scenarios x figures; each column coloured by its own range (green good, red bad), values written in."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["name"] for r in rows]
    figs = [figures(r) for r in rows]
    cols = [c for c in (figs[0] if figs else {}) if any(f[c] is not None for f in figs)]
    values = np.array([[np.nan if f[c] is None else f[c] for c in cols] for f in figs], np.float64)
    colour = np.full_like(values, np.nan)
    for j, c in enumerate(cols):
        v = values[:, j]
        ok = np.isfinite(v)
        if not ok.any():
            continue
        lo, hi = np.min(v[ok]), np.max(v[ok])
        t = (v - lo) / (hi - lo) if hi > lo else np.full_like(v, 0.5)
        colour[:, j] = 1.0 - t if _worse_is_higher(c) else t
    fig, ax = plt.subplots(figsize=(max(8.0, 0.55 * len(cols) + 4), max(3.0, 0.4 * len(names) + 2.5)))
    ax.imshow(np.ma.masked_invalid(colour), cmap="RdYlGn", vmin=0, vmax=1, aspect="auto")
    ax.set_xticks(range(len(cols)), cols, rotation=70, ha="right", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    for i in range(len(names)):
        for j, c in enumerate(cols):
            if np.isfinite(values[i, j]):
                ax.text(j, i, _fmt(float(values[i, j]), c), ha="center", va="center", fontsize=5.5)
    ax.set_title("scenario matrix: each column coloured by its own range (green = better)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def write_outputs(rows: list[dict[str, Any]], out_dir: Path, header: str = "") -> dict[str, Path]:
    """``summary.md``, ``summary.json`` (the figures per scenario and the summary) and
    ``heatmap.png`` in ``out_dir`` (the JSON lines are written as scenarios finish)."""
    paths = {"markdown": out_dir / "summary.md", "json": out_dir / "summary.json",
             "png": out_dir / "heatmap.png"}
    paths["markdown"].write_text(markdown(rows, header))
    paths["json"].write_text(json.dumps({
        "summary": summarise(rows), "scenarios": {r["name"]: figures(r) for r in rows}}, indent=1) + "\n")
    heatmap(rows, paths["png"])
    return paths
