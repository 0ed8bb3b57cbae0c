"""Point heads: a smaller FusionNet distilled from a checkpoint's own, for point answers.

``segment_points`` (and the model's features written into the global map) only need the
FusionNet's OV weights over each point's source views; on two CPU cores that network is most of
the query's time (docs/results.md). A point head is a FusionNet of the same architecture and
inputs, narrower, trained to give the teacher's OV weights (``mapper.training.point_head``,
``govnesf distill-point-head``); the runtime uses it in place of the teacher's for point answers
when ``model.point_head`` names one. Renders keep the teacher (colour weights, query directions).

A point head called ``NAME`` is two files next to each other, written as checkpoints are
(temporary file, ``os.replace``, the JSON last, naming the weights' SHA-256):

* ``NAME.safetensors`` -- the head's weights (float32);
* ``NAME.json`` -- ``format``, the head's ``fusion`` config, the 2D feature and volume feature
  dimensions it takes, the teacher checkpoint's ``weights_sha256`` (a head is only loaded next to
  the teacher it was distilled from), and what the distiller adds (command, data, metrics).

Example:
    >>> from mapper.model.point_head import load_point_head
    >>> head, meta = load_point_head("checkpoints/cpu-small-point-head.json")  # from the repo root
    >>> meta["fusion"]["attention_dim"] < 16
    True
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save as st_save

from mapper.model.checkpoint import _atomic_write, _plain, _read_verified, _sha256, checkpoint_paths
from mapper.model.config import FusionConfig
from mapper.model.fusion import FusionNet

__all__ = ["FORMAT", "head_paths", "load_point_head", "save_point_head"]

FORMAT = "govnesf-point-head/1"
"""Value of the JSON's ``format`` field; readers refuse anything else."""


def head_paths(path: str | Path) -> tuple[Path, Path]:
    """``NAME``, ``NAME.json`` or ``NAME.safetensors`` -> (weights path, JSON path): a checkpoint's
    naming (:func:`mapper.model.checkpoint.checkpoint_paths`)."""
    weights, meta, _ = checkpoint_paths(path)
    return weights, meta


def save_point_head(
    path: str | Path,
    head: FusionNet,
    cfg: FusionConfig,
    *,
    feature_dim: int,
    volume_feature_dim: int,
    teacher_sha256: str,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``head`` (weights float32) and its JSON; returns the JSON's path."""
    weights_path, json_path = head_paths(path)
    weights_path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in head.state_dict().items()}
    data = st_save(state)
    meta = {
        "format": FORMAT,
        "fusion": dataclasses.asdict(cfg),
        "feature_dim": int(feature_dim),
        "volume_feature_dim": int(volume_feature_dim),
        "teacher_weights_sha256": teacher_sha256,
        "weights_file": weights_path.name,
        "weights_sha256": _sha256(data),
        **_plain(extra or {}),
    }
    _atomic_write(weights_path, data)
    _atomic_write(json_path, (json.dumps(meta, indent=2) + "\n").encode())
    return json_path


def load_point_head(
    path: str | Path, *, teacher_sha256: str | None = None, device: str | torch.device = "cpu"
) -> tuple[FusionNet, dict[str, Any]]:
    """A point head in eval mode and its metadata.

    Args:
        path: ``NAME``, ``NAME.json`` or ``NAME.safetensors``.
        teacher_sha256: the loaded checkpoint's ``weights_sha256``; when given, a head distilled
            from other weights is refused.

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: wrong format, weights not matching their SHA-256, another teacher, or weights
            that do not fit the config.
    """
    weights_path, json_path = head_paths(path)
    meta = json.loads(json_path.read_text())
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{json_path} is not a point head (format {FORMAT!r})")
    if teacher_sha256 is not None and meta.get("teacher_weights_sha256") != teacher_sha256:
        raise ValueError(
            f"the point head {json_path} was distilled from weights {meta.get('teacher_weights_sha256')!r}, "
            f"not from the loaded checkpoint's {teacher_sha256!r}; distill one for this checkpoint "
            "(govnesf distill-point-head) or set model.point_head = \"\""
        )
    state = _read_verified(json_path.parent / meta.get("weights_file", weights_path.name),
                           str(meta.get("weights_sha256")))  # a JSON without one never matches
    try:
        cfg = FusionConfig(**meta["fusion"])
        head = FusionNet(int(meta["feature_dim"]), int(meta["volume_feature_dim"]), cfg)
        head.load_state_dict(state, strict=True)
    except (KeyError, TypeError, RuntimeError) as exc:
        raise ValueError(f"the point head {json_path} does not fit its config: {exc}") from None
    return head.to(device).eval(), meta
