"""In-process dense open-vocabulary features from CLIP ViT weights on local disk (MaskCLIP-style).

The CLIP ViT image and text towers are written here in plain torch (no open_clip, no
torchvision), loading the state-dict layout that OpenAI CLIP and open_clip ViT checkpoints share::

    visual.conv1.weight  visual.class_embedding  visual.positional_embedding  visual.ln_pre.*
    visual.transformer.resblocks.{i}.{ln_1, attn.in_proj_weight, attn.in_proj_bias,
                                      attn.out_proj, ln_2, mlp.c_fc, mlp.c_proj}.*
    visual.ln_post.*  visual.proj
    token_embedding.weight  positional_embedding  transformer.resblocks.{i}.*  ln_final.*
    text_projection  logit_scale

The architecture (widths, depths, MLP widths, patch size, image size, embedding size, context
length, vocabulary size) is read from the tensors' shapes; the number of attention heads is
``width // 64`` unless the config says otherwise (open_clip's ViT-H/g/bigG image towers use
wider heads and need ``vision_heads=16``). The activation is not visible in the weights:
``quick_gelu`` for OpenAI's weights, ``gelu`` for most open_clip (LAION / DataComp) weights.

Dense features follow MaskCLIP (Zhou et al., ECCV 2022, its ViT backbone): all blocks but the
last run as usual; the last block skips the query-key attention and uses the value path of every
token on its own::

    v = out_proj(W_v ln_1(x) + b_v)          # per token, no mixing between tokens
    x = x + v
    x = x + mlp(ln_2(x))
    features = ln_post(x[patch tokens]) @ proj   # (h_p, w_p, D), then L2-normalised per patch

Positional embeddings are interpolated bicubically to the patch grid of the input, whose aspect
ratio follows the image (``input_size`` sets the short side). Images are normalised with CLIP's
mean/std. See ``docs/how-to/clip-weights.md`` for where to get weights and the BPE file.

Nothing here downloads anything.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapper.checks import check_shape
from mapper.ov.clip_tokenizer import ClipTokenizer
from mapper.ov.config import ACTIVATIONS, ClipBackendConfig
from mapper.ov.encoders import PromptCache

#: CLIP's image normalisation (OpenAI; open_clip uses the same for its CLIP ViTs).

#: Keys some checkpoints carry that hold no weights (OpenAI's TorchScript metadata, old open_clip's
#: causal-mask buffer); they are dropped on load.
_IGNORED_KEYS = {"input_resolution", "context_length", "vocab_size", "attn_mask"}

_DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
_TEXT_BATCH = 256
#: Most patches one dense forward may hold (a 128 x 128 grid); bounds memory on odd aspect ratios.
MAX_DENSE_PATCHES = 16384


class ClipWeightsError(ValueError):
    """A CLIP checkpoint cannot be loaded: missing/unexpected keys, wrong shapes, unsupported format."""


# --------------------------------------------------------------------------------------------
# Configuration and architecture
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClipArchitecture:
    """The shape of a CLIP ViT model, inferred from its state dict."""

    embed_dim: int
    """Size of the joint image-text embedding (512 for ViT-B/16)."""
    image_size: int
    """Native input size in pixels (square), = patch_size * native grid."""
    patch_size: int
    vision_width: int
    vision_layers: int
    vision_heads: int
    vision_mlp_width: int
    context_length: int
    vocab_size: int
    text_width: int
    text_layers: int
    text_heads: int
    text_mlp_width: int

    @property
    def grid_size(self) -> int:
        """Patches per side at the native image size."""
        return self.image_size // self.patch_size


def _count_blocks(state: Mapping[str, Tensor], prefix: str) -> int:
    """Number of residual blocks ``{prefix}{i}.*`` (indices must run 0..n-1)."""
    idx = set()
    for k in state:
        if k.startswith(prefix):
            head = k[len(prefix) :].split(".", 1)[0]
            if head.isdigit():
                idx.add(int(head))
    n = len(idx)
    if idx != set(range(n)):
        missing = sorted(set(range(max(idx) + 1)) - idx)
        raise ClipWeightsError(f"residual blocks {prefix}{{i}} are not numbered 0..n-1: missing {missing}")
    return n


def _need(state: Mapping[str, Tensor], key: str, ndim: int) -> Tensor:
    """``state[key]`` with ``ndim`` dimensions, or a ClipWeightsError naming the key."""
    if key not in state:
        raise ClipWeightsError(f"state dict has no key {key!r}, which a CLIP ViT checkpoint needs")
    t = state[key]
    if t.ndim != ndim:
        raise ClipWeightsError(f"{key!r} has shape {tuple(t.shape)}, expected {ndim} dimensions")
    return t


def infer_architecture(
    state: Mapping[str, Tensor], vision_heads: int | None = None, text_heads: int | None = None
) -> ClipArchitecture:
    """Read a CLIP ViT architecture from tensor shapes.

    Raises:
        ClipWeightsError: a key the inference needs is missing, or shapes are inconsistent (e.g. a
            ResNet CLIP, or a non-square positional grid).
    """
    if "visual.attnpool.positional_embedding" in state or "visual.layer1.0.conv1.weight" in state:
        raise ClipWeightsError("this is a ResNet CLIP checkpoint; only ViT CLIP models are supported")
    conv1 = _need(state, "visual.conv1.weight", 4)  # (width, 3, p, p)
    vpos = _need(state, "visual.positional_embedding", 2)  # (1 + g*g, width)
    vproj = _need(state, "visual.proj", 2)  # (width, D)
    tok = _need(state, "token_embedding.weight", 2)  # (vocab, text_width)
    tpos = _need(state, "positional_embedding", 2)  # (L, text_width)
    tproj = _need(state, "text_projection", 2)  # (text_width, D)
    vfc = _need(state, "visual.transformer.resblocks.0.mlp.c_fc.weight", 2)  # (mlp, width)
    tfc = _need(state, "transformer.resblocks.0.mlp.c_fc.weight", 2)

    vision_width, in_ch, patch, patch_w = conv1.shape
    if in_ch != 3 or patch != patch_w:
        raise ClipWeightsError(
            f"'visual.conv1.weight' has shape {tuple(conv1.shape)}; expected (width, 3, p, p)"
        )
    grid = round(math.sqrt(vpos.shape[0] - 1))
    if grid * grid + 1 != vpos.shape[0]:
        raise ClipWeightsError(
            f"'visual.positional_embedding' has {vpos.shape[0]} rows; expected 1 + g*g for a square grid"
        )
    text_width = tok.shape[1]
    embed_dim = vproj.shape[1]
    if tproj.shape[1] != embed_dim:
        raise ClipWeightsError(
            f"'text_projection' maps to {tproj.shape[1]} dims but 'visual.proj' to {embed_dim}; "
            "the towers must share one embedding size"
        )
    v_heads = vision_heads if vision_heads is not None else vision_width // 64
    t_heads = text_heads if text_heads is not None else text_width // 64
    for name, width, heads in (("vision", vision_width, v_heads), ("text", text_width, t_heads)):
        if heads < 1 or width % heads:
            raise ClipWeightsError(
                f"{name} width {width} is not divisible into {heads} heads; set {name}_heads in the config"
            )
    return ClipArchitecture(
        embed_dim=int(embed_dim),
        image_size=int(patch * grid),
        patch_size=int(patch),
        vision_width=int(vision_width),
        vision_layers=_count_blocks(state, "visual.transformer.resblocks."),
        vision_heads=int(v_heads),
        vision_mlp_width=int(vfc.shape[0]),
        context_length=int(tpos.shape[0]),
        vocab_size=int(tok.shape[0]),
        text_width=int(text_width),
        text_layers=_count_blocks(state, "transformer.resblocks."),
        text_heads=int(t_heads),
        text_mlp_width=int(tfc.shape[0]),
    )


# --------------------------------------------------------------------------------------------
# The model (parameter names follow the checkpoint layout)
# --------------------------------------------------------------------------------------------


class _LayerNorm(nn.LayerNorm):
    """LayerNorm computed in float32 whatever the input dtype (as OpenAI CLIP does)."""

    def forward(self, x: Tensor) -> Tensor:
        return F.layer_norm(
            x.float(), self.normalized_shape, self.weight.float(), self.bias.float(), self.eps
        ).to(x.dtype)


class _QuickGELU(nn.Module):
    def forward(self, x: Tensor) -> Tensor:
        return x * torch.sigmoid(1.702 * x)


class _Attention(nn.Module):
    """Multi-head self-attention with ``nn.MultiheadAttention``'s packed parameter names."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.empty(3 * width))
        self.out_proj = nn.Linear(width, width)

    def forward(self, x: Tensor, causal: bool = False) -> Tensor:
        """(B, L, C) -> (B, L, C)."""
        b, n, c = x.shape
        qkv = F.linear(x, self.in_proj_weight, self.in_proj_bias)  # (B, L, 3C)
        qkv = qkv.view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)  # (3, B, H, L, c/H)
        y = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2], is_causal=causal)  # (B, H, L, c/H)
        return self.out_proj(y.transpose(1, 2).reshape(b, n, c))

    def value_path(self, x: Tensor) -> Tensor:
        """MaskCLIP: out_proj(value projection) of each token on its own. (B, L, C) -> (B, L, C)."""
        c = x.shape[-1]
        v = F.linear(x, self.in_proj_weight[2 * c :], self.in_proj_bias[2 * c :])
        return self.out_proj(v)


class _ResidualBlock(nn.Module):
    def __init__(self, width: int, heads: int, mlp_width: int, activation: str) -> None:
        super().__init__()
        self.ln_1 = _LayerNorm(width)
        self.attn = _Attention(width, heads)
        self.ln_2 = _LayerNorm(width)
        act: nn.Module = _QuickGELU() if activation == "quick_gelu" else nn.GELU()
        self.mlp = nn.Sequential()
        self.mlp.add_module("c_fc", nn.Linear(width, mlp_width))
        self.mlp.add_module("gelu", act)
        self.mlp.add_module("c_proj", nn.Linear(mlp_width, width))

    def forward(self, x: Tensor, causal: bool = False) -> Tensor:
        """(B, L, C) -> (B, L, C)."""
        x = x + self.attn(self.ln_1(x), causal=causal)
        return x + self.mlp(self.ln_2(x))

    def forward_maskclip(self, x: Tensor) -> Tensor:
        """The MaskCLIP last block: value path instead of attention. (B, L, C) -> (B, L, C)."""
        x = x + self.attn.value_path(self.ln_1(x))
        return x + self.mlp(self.ln_2(x))


class _Transformer(nn.Module):
    def __init__(self, width: int, layers: int, heads: int, mlp_width: int, activation: str) -> None:
        super().__init__()
        self.resblocks = nn.ModuleList(
            [_ResidualBlock(width, heads, mlp_width, activation) for _ in range(layers)]
        )


class ClipVisionTower(nn.Module):
    """CLIP's ViT image tower (``visual.*``)."""

    def __init__(self, arch: ClipArchitecture, activation: str) -> None:
        super().__init__()
        w = arch.vision_width
        self.patch_size = arch.patch_size
        self.grid_size = arch.grid_size
        self.conv1 = nn.Conv2d(3, w, kernel_size=arch.patch_size, stride=arch.patch_size, bias=False)
        self.class_embedding = nn.Parameter(torch.empty(w))
        self.positional_embedding = nn.Parameter(torch.empty(arch.grid_size**2 + 1, w))
        self.ln_pre = _LayerNorm(w)
        self.transformer = _Transformer(
            w, arch.vision_layers, arch.vision_heads, arch.vision_mlp_width, activation
        )
        self.ln_post = _LayerNorm(w)
        self.proj = nn.Parameter(torch.empty(w, arch.embed_dim))
        self._pos_cache: dict[tuple[int, int], Tensor] = {}

    def positional_embedding_for(self, h_p: int, w_p: int) -> Tensor:
        """Positional embedding for an h_p x w_p patch grid: (1 + h_p*w_p, C).

        The native grid returns the stored table itself; other grids interpolate the patch part
        bicubically (align_corners=False, in float32) and keep the class-token row.
        """
        g = self.grid_size
        if (h_p, w_p) == (g, g):
            return self.positional_embedding
        key = (h_p, w_p)
        cached = self._pos_cache.get(key)
        pos = self.positional_embedding.detach()
        if cached is None or cached.device != pos.device or cached.dtype != pos.dtype:
            grid = pos[1:].float().reshape(1, g, g, -1).permute(0, 3, 1, 2)  # (1, C, g, g)
            grid = F.interpolate(grid, size=(h_p, w_p), mode="bicubic", align_corners=False)
            patch = grid.permute(0, 2, 3, 1).reshape(h_p * w_p, -1).to(pos.dtype)  # (h_p*w_p, C)
            cached = torch.cat([pos[:1], patch], dim=0)
            self._pos_cache[key] = cached
        return cached

    def tokens(self, pixels: Tensor) -> tuple[Tensor, int, int]:
        """Normalised pixels (B, 3, H, W), H and W multiples of the patch -> (B, 1 + h_p*w_p, C), h_p, w_p."""
        x = self.conv1(pixels.to(self.conv1.weight.dtype))  # (B, C, h_p, w_p)
        b, c, h_p, w_p = x.shape
        x = x.flatten(2).transpose(1, 2)  # (B, h_p*w_p, C)
        cls = self.class_embedding.to(x.dtype).expand(b, 1, c)
        x = torch.cat([cls, x], dim=1) + self.positional_embedding_for(h_p, w_p).to(x.dtype)
        return self.ln_pre(x), h_p, w_p

    def forward(self, pixels: Tensor) -> Tensor:
        """The standard CLIP image embedding (class token path, not normalised): (B, 3, H, W) -> (B, D)."""
        x, _, _ = self.tokens(pixels)
        for block in self.transformer.resblocks:
            x = block(x)
        return self.ln_post(x[:, 0]) @ self.proj

    def dense(self, pixels: Tensor) -> Tensor:
        """MaskCLIP dense features (not normalised): (B, 3, H, W) -> (B, h_p, w_p, D)."""
        x, h_p, w_p = self.tokens(pixels)
        *blocks, last = self.transformer.resblocks
        for block in blocks:
            x = block(x)
        assert isinstance(last, _ResidualBlock)
        x = last.forward_maskclip(x)
        feats = self.ln_post(x[:, 1:]) @ self.proj  # (B, h_p*w_p, D)
        return feats.reshape(x.shape[0], h_p, w_p, -1)


class ClipModel(nn.Module):
    """CLIP ViT image and text towers; ``state_dict()`` keys match OpenAI / open_clip checkpoints."""

    def __init__(self, arch: ClipArchitecture, activation: str = "quick_gelu") -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation {activation!r} not supported; choose one of {ACTIVATIONS}")
        self.arch = arch
        self.visual = ClipVisionTower(arch, activation)
        self.token_embedding = nn.Embedding(arch.vocab_size, arch.text_width)
        self.positional_embedding = nn.Parameter(torch.empty(arch.context_length, arch.text_width))
        self.transformer = _Transformer(
            arch.text_width, arch.text_layers, arch.text_heads, arch.text_mlp_width, activation
        )
        self.ln_final = _LayerNorm(arch.text_width)
        self.text_projection = nn.Parameter(torch.empty(arch.text_width, arch.embed_dim))
        self.logit_scale = nn.Parameter(torch.empty(()))

    def encode_image(self, pixels: Tensor) -> Tensor:
        """Normalised pixels (B, 3, S, S) -> (B, D) image embeddings (not L2-normalised)."""
        return self.visual(pixels)

    def encode_text(self, tokens: Tensor) -> Tensor:
        """Token ids (N, L) with EOT the largest id of a row -> (N, D) embeddings (not L2-normalised)."""
        x = self.token_embedding(tokens) + self.positional_embedding.to(self.token_embedding.weight.dtype)
        for block in self.transformer.resblocks:
            x = block(x, causal=True)
        x = self.ln_final(x)  # (N, L, C)
        eot = x[torch.arange(x.shape[0], device=x.device), tokens.argmax(dim=-1)]  # (N, C)
        return eot @ self.text_projection


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------


def _is_torchscript(path: Path) -> bool:
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as zf:
        return any(n.endswith("/constants.pkl") or "/code/" in n for n in zf.namelist())


def read_state_dict(path: str | Path) -> dict[str, Tensor]:
    """Tensors of a local CLIP checkpoint, with ``state_dict`` nesting and ``module.`` prefixes removed.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ClipWeightsError: a TorchScript archive (OpenAI's original ``.pt``), or not a dict of tensors.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(
            f"CLIP weights {str(p)!r} not found; point weights_path at a local state dict "
            "(.pt or .safetensors, see docs/how-to/clip-weights.md)"
        )
    if p.suffix == ".safetensors":
        from safetensors.torch import load_file

        obj: object = load_file(str(p), device="cpu")
    else:
        if _is_torchscript(p):
            raise ClipWeightsError(
                f"{str(p)!r} is a TorchScript archive (OpenAI's original CLIP .pt), which is not supported; "
                'convert it once to a plain state dict: python -c "import torch; '
                f"m = torch.jit.load('{p.name}', map_location='cpu'); "
                "torch.save(m.state_dict(), 'clip_state_dict.pt')\" (see docs/how-to/clip-weights.md)"
            )
        try:
            obj = torch.load(str(p), map_location="cpu", weights_only=True)
        except Exception as e:  # pickle errors come in many types
            raise ClipWeightsError(f"cannot read {str(p)!r} as a torch state dict: {e}") from e
    if isinstance(obj, Mapping) and "state_dict" in obj and isinstance(obj["state_dict"], Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping):
        raise ClipWeightsError(f"{str(p)!r} holds a {type(obj).__name__}, expected a dict of tensors")
    state: dict[str, Tensor] = {}
    for k, v in obj.items():
        key = str(k)
        if key.startswith("module."):
            key = key[len("module.") :]
        if key in _IGNORED_KEYS:
            continue
        if not isinstance(v, Tensor):
            raise ClipWeightsError(f"{str(p)!r}: entry {key!r} is a {type(v).__name__}, expected a tensor")
        state[key] = v
    return state


def build_model(
    state: Mapping[str, Tensor],
    activation: str = "quick_gelu",
    vision_heads: int | None = None,
    text_heads: int | None = None,
) -> ClipModel:
    """A float32 :class:`ClipModel` holding ``state``'s weights, architecture read from the shapes.

    Raises:
        ClipWeightsError: missing keys, unexpected keys or wrong shapes (each named).
    """
    arch = infer_architecture(state, vision_heads=vision_heads, text_heads=text_heads)
    model = ClipModel(arch, activation)
    expected = model.state_dict()
    missing = [k for k in expected if k not in state]
    if missing:
        more = f" (and {len(missing) - 5} more)" if len(missing) > 5 else ""
        raise ClipWeightsError(f"state dict is missing key(s) {missing[:5]}{more} of a CLIP ViT model")
    unexpected = [k for k in state if k not in expected]
    if unexpected:
        more = f" (and {len(unexpected) - 5} more)" if len(unexpected) > 5 else ""
        raise ClipWeightsError(
            f"state dict has key(s) {unexpected[:5]}{more} that this plain CLIP ViT does not use "
            "(layer scale, attention pooling or a custom text tower are not supported)"
        )
    for k, ref in expected.items():
        got = state[k]
        if tuple(got.shape) != tuple(ref.shape):
            raise ClipWeightsError(f"{k!r} has shape {tuple(got.shape)}, expected {tuple(ref.shape)}")
        if not got.is_floating_point():
            raise ClipWeightsError(f"{k!r} has dtype {got.dtype}, expected a floating-point tensor")
    model.load_state_dict({k: state[k].float() for k in expected}, strict=True)
    return model.eval().requires_grad_(False)


# --------------------------------------------------------------------------------------------
# Preprocessing
# --------------------------------------------------------------------------------------------


def dense_grid_shape(height: int, width: int, short_side: int, patch_size: int) -> tuple[int, int]:
    """Patch grid (h_p, w_p) for an image resized so its short side is ``short_side`` pixels.

    Each side is rounded to a whole number of patches (at least one), so the aspect ratio is kept
    to within half a patch.
    """
    scale = short_side / min(height, width)
    return max(1, round(height * scale / patch_size)), max(1, round(width * scale / patch_size))


def _check_rgb(rgb: np.ndarray) -> None:
    if not isinstance(rgb, np.ndarray):
        raise TypeError(f"rgb must be a numpy array, got {type(rgb).__name__}")
    check_shape(rgb, "H W 3", "rgb")
    if rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"rgb must be at least 1x1 pixels, got {rgb.shape[0]}x{rgb.shape[1]}")


def _resize(img: Tensor, size: tuple[int, int]) -> Tensor:
    """(1, 3, H, W) float in [0, 1] -> (1, 3, size) bicubic (antialiased when shrinking), clamped."""
    if tuple(img.shape[-2:]) == size:
        return img
    return F.interpolate(img, size=size, mode="bicubic", align_corners=False, antialias=True).clamp_(0.0, 1.0)


# --------------------------------------------------------------------------------------------
# The backend
# --------------------------------------------------------------------------------------------


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available here; use 'cpu' or 'auto'")
    return dev


class ClipDenseBackend:
    """Dense open-vocabulary image features and text embeddings from local CLIP ViT weights.

    Also satisfies ``mapper.ov.encoders.TextEncoder`` (``space``, ``dim``, ``encode``), so it can be
    registered for its space with ``register_text_encoder``.

    Attributes:
        space: ``f"openclip:{model_name}"``, the ``ov_space`` of everything it produces.
        dim: embedding size D.
        arch: the architecture read from the weights.
        device, dtype: where and in which precision it runs.
    """

    def __init__(self, cfg: ClipBackendConfig) -> None:
        self.cfg = cfg
        self.device = _resolve_device(cfg.device)
        self.dtype = _DTYPES[cfg.dtype]
        if self.dtype == torch.float16 and self.device.type != "cuda":
            raise ValueError(
                f"dtype 'float16' needs a cuda device, got device {str(self.device)!r}; "
                "use 'float32' or 'bfloat16' on cpu"
            )
        state = read_state_dict(cfg.weights_path)
        model = build_model(state, cfg.activation, cfg.vision_heads, cfg.text_heads)
        self.model = model.to(device=self.device, dtype=self.dtype)
        self.arch = model.arch
        self.tokenizer = ClipTokenizer(cfg.bpe_path, context_length=self.arch.context_length)
        if self.tokenizer.vocab_size > self.arch.vocab_size:
            raise ClipWeightsError(
                f"BPE file {cfg.bpe_path!r} gives {self.tokenizer.vocab_size} tokens but the text tower "
                f"of {cfg.weights_path!r} embeds only {self.arch.vocab_size}; they do not belong together"
            )
        self.space = f"openclip:{cfg.model_name}"
        self.dim = self.arch.embed_dim
        self.input_size = cfg.input_size if cfg.input_size is not None else self.arch.image_size
        self._mean = torch.tensor(cfg.image_mean, dtype=torch.float32).view(1, 3, 1, 1)
        self._std = torch.tensor(cfg.image_std, dtype=torch.float32).view(1, 3, 1, 1)
        self._text_cache = PromptCache(self._embed_texts, self.dim)

    # ---- text ----
    def _embed_texts(self, texts: list[str]) -> np.ndarray:  # (M,) distinct -> (M, D) unit rows
        out = []
        for start in range(0, len(texts), _TEXT_BATCH):
            chunk = texts[start : start + _TEXT_BATCH]
            tokens = torch.from_numpy(self.tokenizer.tokenize(chunk)).to(self.device)  # (M, L)
            with torch.inference_mode():
                emb = F.normalize(self.model.encode_text(tokens).float(), dim=-1)  # (M, D)
            out.append(emb.cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.dim), np.float32)

    def encode_text(self, texts: Sequence[str]) -> np.ndarray:
        """(N,) strings -> (N, D) float32, L2-normalised rows; each distinct string is embedded once
        (kept in a bounded :class:`mapper.ov.encoders.PromptCache`)."""
        return self._text_cache.get(texts)

    def uncached_chars(self, texts: Sequence[str]) -> int:
        """Characters of the distinct ``texts`` that :meth:`encode_text` would have to embed."""
        return self._text_cache.uncached_chars(texts)

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """``TextEncoder`` protocol: same as :meth:`encode_text`."""
        return self.encode_text(texts)

    # ---- images ----
    def _to_tensor(self, rgb: np.ndarray) -> Tensor:
        """(H, W, 3) uint8 -> (1, 3, H, W) float32 in [0, 1] on the backend's device."""
        return (
            torch.from_numpy(np.ascontiguousarray(rgb)).to(self.device).permute(2, 0, 1)[None].float() / 255.0
        )

    def _normalise(self, img: Tensor) -> Tensor:
        return ((img - self._mean.to(img.device)) / self._std.to(img.device)).to(self.dtype)

    def dense_grid(self, height: int, width: int) -> tuple[int, int]:
        """Patch grid (h_p, w_p) :meth:`dense_features` returns for an image of height x width pixels."""
        return dense_grid_shape(height, width, self.input_size, self.arch.patch_size)

    def dense_features(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (h_p, w_p, D) float16, L2-normalised per patch (MaskCLIP).

        The image is resized (bicubic) so its short side is ``input_size`` and each side a whole
        number of patches; ``dense_grid(H, W)`` gives (h_p, w_p).

        Raises:
            ValueError: not an (H, W, 3) uint8 image, or its grid exceeds ``MAX_DENSE_PATCHES``.
        """
        _check_rgb(rgb)
        h_p, w_p = self.dense_grid(rgb.shape[0], rgb.shape[1])
        if h_p * w_p > MAX_DENSE_PATCHES:
            raise ValueError(
                f"a {rgb.shape[0]}x{rgb.shape[1]} image at input_size {self.input_size} needs a "
                f"{h_p}x{w_p} patch grid ({h_p * w_p} patches), more than {MAX_DENSE_PATCHES}; "
                "lower input_size or crop the image"
            )
        p = self.arch.patch_size
        with torch.inference_mode():
            img = _resize(self._to_tensor(rgb), (h_p * p, w_p * p))
            feats = self.model.visual.dense(self._normalise(img))[0].float()  # (h_p, w_p, D)
            feats = F.normalize(feats, dim=-1)
            return feats.to(torch.float16).cpu().numpy()

    def encode_image(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (D,) float32 L2-normalised global CLIP embedding.

        CLIP's own preprocessing: bicubic resize of the short side to the native image size, then
        a centre crop to a square.
        """
        _check_rgb(rgb)
        s = self.arch.image_size
        h, w = rgb.shape[:2]
        scale = s / min(h, w)
        rh, rw = max(s, round(h * scale)), max(s, round(w * scale))
        with torch.inference_mode():
            img = _resize(self._to_tensor(rgb), (rh, rw))
            top, left = (rh - s) // 2, (rw - s) // 2
            img = img[..., top : top + s, left : left + s]
            emb = self.model.encode_image(self._normalise(img))[0].float()
            return F.normalize(emb, dim=-1).cpu().numpy()
