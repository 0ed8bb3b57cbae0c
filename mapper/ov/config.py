"""Configuration of the dense CLIP backend (``[ov_backend]``). Imports no torch."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

__all__ = ["ACTIVATIONS", "CLIP_MEAN", "CLIP_STD", "DTYPE_NAMES", "ClipBackendConfig"]

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
DTYPE_NAMES = ("float32", "float16", "bfloat16")
ACTIVATIONS = ("quick_gelu", "gelu")
_MODEL_NAME = re.compile(r"[A-Za-z0-9_.@/+-]{1,64}")
_DEVICE = re.compile(r"([a-z_]+)(?::(\d+))?")


@dataclass(frozen=True)
class ClipBackendConfig:
    """Where the CLIP weights live and how to run them."""

    weights_path: str
    """Local checkpoint: a plain state dict saved with ``torch.save`` (``.pt``/``.pth``/``.bin``)
    or a ``.safetensors`` file. OpenAI's TorchScript ``.pt`` archives are not supported (convert
    them once, see docs/how-to/clip-weights.md)."""

    bpe_path: str
    """Local ``bpe_simple_vocab_16e6.txt.gz`` (CLIP's BPE merges)."""

    model_name: str = "ViT-B-16"
    """Names the embedding space only: ``ov_space = f"openclip:{model_name}"``. 1..64 characters
    from ``A-Za-z0-9_.@/+-``."""

    device: str = "auto"
    """``"auto"`` (cuda if available, else cpu), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``."""

    dtype: str = "float32"
    """Compute dtype: ``"float32"``, ``"float16"`` (cuda only) or ``"bfloat16"``."""

    input_size: int | None = None
    """Short side (pixels) images are resized to for dense features; None = the model's native
    image size (224 for ViT-B/16). The long side keeps the aspect ratio. 16..4096."""

    activation: str = "quick_gelu"
    """MLP activation: ``"quick_gelu"`` (OpenAI weights, open_clip ``*-quickgelu`` models) or
    ``"gelu"`` (open_clip's LAION / DataComp weights). Not recoverable from the weights."""

    vision_heads: int | None = None
    """Attention heads of the image tower; None = width // 64 (right for ViT-B and ViT-L)."""

    text_heads: int | None = None
    """Attention heads of the text tower; None = width // 64."""

    image_mean: tuple[float, float, float] = CLIP_MEAN
    """Per-channel RGB mean in [0, 1] subtracted before the image tower."""

    image_std: tuple[float, float, float] = CLIP_STD
    """Per-channel RGB standard deviation in [0, 1] the image is divided by."""

    def __post_init__(self) -> None:
        if not isinstance(self.model_name, str) or not _MODEL_NAME.fullmatch(self.model_name):
            raise ValueError(
                f"model_name {self.model_name!r} invalid: need 1..64 characters from A-Za-z0-9_.@/+-"
            )
        if self.dtype not in DTYPE_NAMES:
            raise ValueError(f"dtype {self.dtype!r} not supported; choose one of {sorted(DTYPE_NAMES)}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation {self.activation!r} not supported; choose one of {ACTIVATIONS}")
        if self.device != "auto":
            match = _DEVICE.fullmatch(self.device) if isinstance(self.device, str) else None
            if match is None:
                raise ValueError(f"device {self.device!r} invalid: use 'auto', 'cpu', 'cuda' or 'cuda:N'")
            if match.group(1) not in ("cpu", "cuda") or (match.group(1) == "cpu" and match.group(2)):
                raise ValueError(
                    f"device {self.device!r} not supported: use 'auto', 'cpu', 'cuda' or 'cuda:N'"
                )
        if self.input_size is not None and (
            not isinstance(self.input_size, int) or not 16 <= self.input_size <= 4096
        ):
            raise ValueError(f"input_size {self.input_size!r} out of range: None or an int in 16..4096")
        for name in ("vision_heads", "text_heads"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, int) or v < 1):
                raise ValueError(f"{name} {v!r} out of range: None or an int >= 1")
        for name in ("image_mean", "image_std"):
            v = tuple(getattr(self, name))
            if len(v) != 3 or not all(isinstance(c, int | float) and math.isfinite(c) for c in v):
                raise ValueError(f"{name} {v!r} invalid: need three finite numbers (R, G, B)")
        if min(self.image_std) <= 0:
            raise ValueError(f"image_std {self.image_std!r} invalid: every value must be > 0")
