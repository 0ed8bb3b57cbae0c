"""GOV-NeSF checkpoints: safetensors weights + a JSON sidecar, never pickle.

A checkpoint called ``NAME`` is two (optionally three) files next to each other:

* ``NAME.safetensors`` -- the model weights (float32, or float16 when saved with ``half=True``;
  ``load_model`` always returns a float32 model);
* ``NAME.json`` -- metadata: format, model config (every field of ``ModelConfig``), preset name,
  mode (``blend`` / ``distill``), weights dtype and SHA-256, and whatever the trainer adds (step,
  validation metrics, the command, the git commit, the training wall time, ...);
* ``NAME.train.safetensors`` (training checkpoints only) -- optimiser moments and the RNG state,
  so that ``govnesf train --resume NAME.json`` continues exactly where it stopped.

Every file is written to a temporary file in the same folder and moved into place
(``os.replace``); the JSON is written last and names the SHA-256 of the weights it belongs to, so a
reader never pairs a JSON with half-written or mismatched weights.

Examples:
    >>> from mapper.model.checkpoint import load_model
    >>> model, meta = load_model("checkpoints/cpu-small.json")  # run from the repository root
    >>> meta["preset"], meta["mode"]
    ('cpu-small', 'blend')
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from mapper.model.config import EncoderConfig, FusionConfig, ModelConfig, RenderConfig, VolumeConfig
from mapper.model.field import GovNeSF

__all__ = [
    "FORMAT",
    "checkpoint_paths",
    "config_from_dict",
    "config_to_dict",
    "load_metadata",
    "load_model",
    "load_training_state",
    "load_weights_except",
    "save_checkpoint",
]

FORMAT = "govnesf-checkpoint/1"
"""Value of the JSON's ``format`` field; readers refuse anything else."""

_SUBCONFIGS: dict[str, type] = {
    "encoder": EncoderConfig,
    "volume": VolumeConfig,
    "fusion": FusionConfig,
    "render": RenderConfig,
}


# ---- config <-> JSON ------------------------------------------------------------------------------
def config_to_dict(cfg: ModelConfig) -> dict[str, Any]:
    """Every field of a ``ModelConfig`` as plain JSON values (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _tuplify(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def config_from_dict(data: dict[str, Any]) -> ModelConfig:
    """Inverse of ``config_to_dict``; unknown keys are an error (a newer checkpoint format)."""
    known = {f.name for f in dataclasses.fields(ModelConfig)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"model config has unknown fields {sorted(unknown)}; known: {sorted(known)}")
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key in _SUBCONFIGS:
            sub = _SUBCONFIGS[key]
            sub_known = {f.name for f in dataclasses.fields(sub)}
            bad = set(value) - sub_known
            if bad:
                raise ValueError(f"model config section {key!r} has unknown fields {sorted(bad)}")
            kwargs[key] = sub(**{k: _tuplify(v) for k, v in value.items()})
        else:
            kwargs[key] = _tuplify(value)
    return ModelConfig(**kwargs)


# ---- paths and atomic writes ----------------------------------------------------------------------
def checkpoint_paths(path: str | Path) -> tuple[Path, Path, Path]:
    """(weights, json, training state) paths of a checkpoint given any of its files or its stem.

    ``ckpt/cpu-small``, ``ckpt/cpu-small.json``, ``ckpt/cpu-small.safetensors`` and
    ``ckpt/cpu-small.train.safetensors`` all name the same checkpoint.
    """
    p = Path(path)
    name = p.name
    for suffix in (".train.safetensors", ".safetensors", ".json"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    stem = p.with_name(name)
    return (
        stem.with_name(name + ".safetensors"),
        stem.with_name(name + ".json"),
        stem.with_name(name + ".train.safetensors"),
    )


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _plain(value: Any) -> Any:
    """JSON-able copy (tuples -> lists, numpy / torch scalars -> Python numbers)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        return value.item()
    if hasattr(value, "item") and callable(value.item) and not isinstance(value, (str, bytes)):
        try:
            return value.item()
        except (TypeError, ValueError):
            pass
    return value


# ---- save -----------------------------------------------------------------------------------------
def _optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Optimiser state split into tensors (for safetensors) and plain values (for JSON)."""
    state_dict = optimizer.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    plain_state: dict[str, dict[str, Any]] = {}
    for idx, per_param in state_dict["state"].items():
        for key, value in per_param.items():
            if isinstance(value, torch.Tensor):
                tensors[f"optim.{idx}.{key}"] = value.detach().cpu().contiguous().clone()
            else:
                plain_state.setdefault(str(idx), {})[key] = _plain(value)
    return tensors, {"param_groups": _plain(state_dict["param_groups"]), "plain_state": plain_state}


def save_checkpoint(
    path: str | Path,
    model: GovNeSF,
    *,
    metadata: dict[str, Any] | None = None,
    optimizer: torch.optim.Optimizer | None = None,
    extra_tensors: dict[str, torch.Tensor] | None = None,
    half: bool = False,
) -> Path:
    """Write a checkpoint atomically; returns the JSON path.

    Args:
        path: the checkpoint's stem or any of its file names (see ``checkpoint_paths``).
        model: the network; its config and mode are recorded.
        metadata: extra JSON-able fields (step, metrics, command, ...); must not use the keys this
            function writes (``format``, ``config``, ``mode``, ``weights_*``, ``train_state``).
        optimizer: with ``extra_tensors``, written to ``NAME.train.safetensors`` for resuming.
        extra_tensors: training tensors to keep (e.g. ``rng.torch``), names without dots first.
        half: store the weights as float16 (half the size; ``load_model`` returns float32).
    """
    weights_path, json_path, train_path = checkpoint_paths(path)
    meta = dict(metadata or {})
    reserved = {"format", "config", "mode", "weights_dtype", "weights_sha256", "weights_file", "train_state"}
    clash = reserved & set(meta)
    if clash:
        raise ValueError(f"metadata must not set reserved keys {sorted(clash)}")
    dtype = torch.float16 if half else torch.float32
    state = {
        k: (v.detach().to("cpu", dtype) if v.is_floating_point() else v.detach().cpu()).contiguous().clone()
        for k, v in model.state_dict().items()
    }
    weights = st_save(state, metadata={"format": FORMAT})
    _atomic_write(weights_path, weights)
    train_meta: dict[str, Any] | None = None
    if optimizer is not None or extra_tensors:
        tensors: dict[str, torch.Tensor] = {}
        train_meta = {"file": train_path.name}
        if optimizer is not None:
            opt_tensors, opt_plain = _optimizer_tensors(optimizer)
            tensors.update(opt_tensors)
            train_meta["optimizer"] = opt_plain
        for k, v in (extra_tensors or {}).items():
            tensors[f"extra.{k}"] = v.detach().cpu().contiguous().clone()
        blob = st_save(tensors, metadata={"format": FORMAT})
        _atomic_write(train_path, blob)
        train_meta["sha256"] = _sha256(blob)
    full = {
        "format": FORMAT,
        "mode": model.mode,
        "config": config_to_dict(model.cfg),
        "weights_file": weights_path.name,
        "weights_dtype": "float16" if half else "float32",
        "weights_sha256": _sha256(weights),
        **_plain(meta),
    }
    if train_meta is not None:
        full["train_state"] = train_meta
    _atomic_write(json_path, (json.dumps(full, indent=2, sort_keys=False) + "\n").encode())
    return json_path


# ---- load -----------------------------------------------------------------------------------------
def load_metadata(path: str | Path) -> dict[str, Any]:
    """The JSON sidecar of a checkpoint (checked format)."""
    _, json_path, _ = checkpoint_paths(path)
    if not json_path.is_file():
        raise FileNotFoundError(
            f"checkpoint metadata {json_path} not found (give NAME, NAME.json or NAME.safetensors)"
        )
    meta = json.loads(json_path.read_text())
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ValueError(f"{json_path}: format {got!r} is not {FORMAT!r}")
    return meta


def _read_verified(path: Path, sha256: str | None) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint file {path} not found")
    data = path.read_bytes()
    if sha256 is not None and _sha256(data) != sha256:
        raise ValueError(f"{path} does not match the SHA-256 in its JSON (partial or mismatched write?)")
    return st_load(data)


def load_model(path: str | Path, *, device: str | torch.device = "cpu") -> tuple[GovNeSF, dict[str, Any]]:
    """A trained model in eval mode (float32, on ``device``) and its metadata.

    Args:
        path: ``NAME``, ``NAME.json`` or ``NAME.safetensors``.
        device: where to put the model.

    Returns:
        (model, metadata): metadata is the JSON sidecar (``config``, ``mode``, ``preset``, ``step``,
        ``metrics``, ...).
    """
    meta = load_metadata(path)
    weights_path, _, _ = checkpoint_paths(path)
    cfg = config_from_dict(meta["config"])
    model = GovNeSF(cfg, mode=meta.get("mode", "blend"))
    state = _read_verified(weights_path, meta.get("weights_sha256"))
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    model.load_state_dict(state, strict=True)
    model.to(device)
    model.eval()
    return model, meta


def _load_into(model: GovNeSF, state: dict[str, torch.Tensor], *, strict: bool) -> None:
    """``model.load_state_dict`` of ``state`` moved to the model's device, floats as float32."""
    device = next(model.parameters()).device
    model.load_state_dict(
        {k: v.to(device, torch.float32) if v.is_floating_point() else v.to(device) for k, v in state.items()},
        strict=strict,
    )


def load_weights_except(path: str | Path, model: GovNeSF, *, prefix: str) -> dict[str, Any]:
    """Load a checkpoint's weights into ``model`` in place (float32), where the model has extra
    parameters under ``prefix`` that the checkpoint lacks (they keep their values); returns the
    metadata. Every other parameter must match by name and shape, and the checkpoint may not hold
    anything the model lacks."""
    if not prefix:
        raise ValueError("prefix must name the model's extra parameters")
    meta = load_metadata(path)
    weights_path, _, _ = checkpoint_paths(path)
    state = _read_verified(weights_path, meta.get("weights_sha256"))
    ours = model.state_dict()
    missing = sorted(k for k in ours if k not in state and not k.startswith(prefix))
    unexpected = sorted(k for k in state if k not in ours or k.startswith(prefix))
    if missing or unexpected:
        raise ValueError(
            f"checkpoint {path}: missing {missing}, unexpected {unexpected} (extra prefix {prefix!r})"
        )
    _load_into(model, state, strict=False)
    return meta


def load_training_state(
    path: str | Path, model: GovNeSF, optimizer: torch.optim.Optimizer | None = None
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Restore weights (and optimiser moments) in place for resuming; returns (metadata, extra tensors).

    The model must have the checkpoint's config and mode.
    """
    meta = load_metadata(path)
    weights_path, _, train_path = checkpoint_paths(path)
    cfg = config_from_dict(meta["config"])
    if cfg != model.cfg or meta.get("mode") != model.mode:
        raise ValueError(
            f"checkpoint {path} is a {meta.get('mode')} model with config {cfg.name!r}; cannot resume "
            f"into a {model.mode} model with config {model.cfg.name!r} (settings differ)"
        )
    state = _read_verified(weights_path, meta.get("weights_sha256"))
    _load_into(model, state, strict=True)
    extra: dict[str, torch.Tensor] = {}
    train_meta = meta.get("train_state")
    if train_meta is None:
        if optimizer is not None:
            raise ValueError(
                f"checkpoint {path} has no training state (weights only); cannot resume the optimiser"
            )
        return meta, extra
    tensors = _read_verified(train_path, train_meta.get("sha256"))
    if optimizer is not None:
        opt_meta = train_meta.get("optimizer")
        if opt_meta is None:
            raise ValueError(f"checkpoint {path} has no optimiser state")
        state_out: dict[int, dict[str, Any]] = {}
        for key, value in tensors.items():
            if key.startswith("optim."):
                _, idx, name = key.split(".", 2)
                state_out.setdefault(int(idx), {})[name] = value  # moved to the params by torch
        for idx, values in opt_meta["plain_state"].items():
            state_out.setdefault(int(idx), {}).update(values)
        groups = opt_meta["param_groups"]
        for g in groups:
            if "betas" in g and isinstance(g["betas"], list):
                g["betas"] = tuple(g["betas"])
        optimizer.load_state_dict({"state": state_out, "param_groups": groups})
    extra = {k[len("extra.") :]: v for k, v in tensors.items() if k.startswith("extra.")}
    return meta, extra
