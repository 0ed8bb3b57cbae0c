"""all-MiniLM-L6-v2 sentence embeddings in plain torch (no ``sentence_transformers`` import).

The mapper embeds text queries with all-MiniLM-L6-v2 (mean pooling over the tokens, L2
normalised, 384-d). Importing ``sentence_transformers`` (and with it ``transformers``) costs
4-6 s of CPU on the 2-core machine, which a node paid inside the first seconds of a robot's
stream and a planner's first query waited for. The model is a 6-layer BERT; this module runs
the same forward pass from the same files (``tokenizer.json`` through the ``tokenizers``
package, ``model.safetensors``), so loading takes a fraction of a second. The embeddings equal
``SentenceTransformer(...).encode(..., normalize_embeddings=True)`` up to float round-off
(tests/mapper/ov/test_minilm.py compares them).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["MiniLM"]


class MiniLM:
    """A BERT sentence encoder (the all-MiniLM-L6-v2 files): ``encode(texts) -> (N, D)``."""

    def __init__(self, model_dir: str | Path, device: str = "cpu") -> None:
        from safetensors.torch import load_file
        from tokenizers import Tokenizer

        root = Path(model_dir)
        cfg = json.loads((root / "config.json").read_text())
        st_cfg_path = root / "sentence_bert_config.json"
        st_cfg = json.loads(st_cfg_path.read_text()) if st_cfg_path.exists() else {}
        if cfg.get("model_type") != "bert" or cfg.get("hidden_act") != "gelu":
            raise ValueError(f"{root}: expected a BERT model with gelu, got {cfg.get('model_type')!r}")
        self.device = torch.device(device)
        self.layers = int(cfg["num_hidden_layers"])
        self.heads = int(cfg["num_attention_heads"])
        self.dim = int(cfg["hidden_size"])
        self.eps = float(cfg.get("layer_norm_eps", 1e-12))
        max_len = min(int(st_cfg.get("max_seq_length", 512)), int(cfg["max_position_embeddings"]))
        self.tokenizer = Tokenizer.from_file(str(root / "tokenizer.json"))
        self.tokenizer.enable_truncation(max_length=max_len)
        self.tokenizer.enable_padding(pad_id=int(cfg.get("pad_token_id", 0)), pad_token="[PAD]")
        weights = load_file(str(root / "model.safetensors"))
        self.w = {k: v.to(self.device, torch.float32) for k, v in weights.items()
                  if not k.startswith("pooler.")}  # fmt: skip

    def _linear(self, x: Tensor, name: str) -> Tensor:
        return F.linear(x, self.w[f"{name}.weight"], self.w[f"{name}.bias"])

    def _norm(self, x: Tensor, name: str) -> Tensor:
        return F.layer_norm(x, (self.dim,), self.w[f"{name}.weight"], self.w[f"{name}.bias"], self.eps)

    @torch.inference_mode()
    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """(N,) strings -> (N, D) float32 L2-normalised mean-pooled token embeddings."""
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        batch = self.tokenizer.encode_batch(list(texts))
        ids = torch.tensor([e.ids for e in batch], dtype=torch.long, device=self.device)  # (B, L)
        types = torch.tensor([e.type_ids for e in batch], dtype=torch.long, device=self.device)
        mask = torch.tensor([e.attention_mask for e in batch], dtype=torch.float32, device=self.device)
        b, length = ids.shape
        w = self.w
        x = (w["embeddings.word_embeddings.weight"][ids]
             + w["embeddings.position_embeddings.weight"][:length].unsqueeze(0)
             + w["embeddings.token_type_embeddings.weight"][types])  # fmt: skip
        x = self._norm(x, "embeddings.LayerNorm")  # (B, L, D)
        head_dim = self.dim // self.heads
        bias = (1.0 - mask)[:, None, None, :] * torch.finfo(torch.float32).min  # (B, 1, 1, L): padding

        def heads(t: Tensor) -> Tensor:  # (B, L, D) -> (B, H, L, d)
            return t.view(b, length, self.heads, head_dim).transpose(1, 2)

        for i in range(self.layers):
            p = f"encoder.layer.{i}"
            q = heads(self._linear(x, f"{p}.attention.self.query"))
            k = heads(self._linear(x, f"{p}.attention.self.key"))
            v = heads(self._linear(x, f"{p}.attention.self.value"))
            scores = q @ k.transpose(-1, -2) / math.sqrt(head_dim) + bias  # (B, H, L, L)
            ctx = (scores.softmax(dim=-1) @ v).transpose(1, 2).reshape(b, length, self.dim)
            attn = self._linear(ctx, f"{p}.attention.output.dense")
            x = self._norm(attn + x, f"{p}.attention.output.LayerNorm")
            inner = F.gelu(self._linear(x, f"{p}.intermediate.dense"))  # exact (erf) gelu
            x = self._norm(self._linear(inner, f"{p}.output.dense") + x, f"{p}.output.LayerNorm")
        pooled = (x * mask.unsqueeze(-1)).sum(dim=1) / mask.sum(dim=1, keepdim=True).clamp_min(1e-9)
        return F.normalize(pooled, dim=-1).cpu().numpy().astype(np.float32)
