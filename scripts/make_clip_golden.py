"""Write the golden files of ``tests/mapper/ov/test_clip_golden.py``: a tiny random CLIP and what the
upstream implementation (Hugging Face ``transformers``' ``CLIPModel`` / ``CLIPTokenizer`` /
``CLIPImageProcessorPil``) computes with it. Run once; the outputs are committed::

    .venv/bin/python scripts/make_clip_golden.py          # writes tests/data/clip_golden*

Outputs (about 0.8 MB together):

- ``tests/data/clip_golden_bpe.txt.gz``: a small BPE merges file (CLIP's format);
- ``tests/data/clip_golden.safetensors``: the random weights in the OpenAI / open_clip layout our
  backend loads (converted here from the ``transformers`` module: q/k/v stacked into
  ``in_proj_weight``, projections transposed);
- ``tests/data/clip_golden_ref.safetensors``: the reference outputs: ``tokens`` (CLIPTokenizer,
  given the vocabulary and merges of the same BPE file), ``text_embeds``
  (``get_text_features``), ``image`` and ``image_embeds`` (a 32x32 image through
  ``CLIPImageProcessorPil`` without resize/crop, then ``get_image_features``), and MaskCLIP dense
  features ``dense_square`` / ``dense_wide`` of a 32x32 and a 32x48 image, built from the
  upstream vision modules: every layer but the last as ``transformers`` runs it (positional
  embeddings interpolated by its ``interpolate_pos_encoding``), then the last layer's value path
  (``out_proj(v_proj(layer_norm1(x)))``) and MLP, ``post_layernorm``, ``visual_projection``.
  Embeddings are L2-normalised, as the backend returns them. The metadata records the versions.

The random weights are drawn here from one seeded generator, parameter by parameter in name order
(Gaussian; fan-in scaled matrices, LayerNorm gains 1 + noise, non-zero biases), so every run with the
same versions writes the same tensors (safetensors may order its JSON header differently).
"""

from __future__ import annotations

import gzip
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mapper.ov.clip_tokenizer import ClipTokenizer  # noqa: E402

OUT = REPO / "tests" / "data"
SEED = 20261202
MERGES = ["t h", "th e</w>", "c h", "a i", "ai r</w>", "ch air</w>", "t a", "b l", "l e</w>", "bl e</w>",
          "ta ble</w>", "s o", "f a</w>", "so fa</w>", "l a", "m p</w>", "la mp</w>", "d o", "o r</w>",
          "do or</w>", "b e", "d s</w>", "be ds</w>"]  # fmt: skip
TEXTS = ["the chair", "a table", "sofa lamp door", "", "café au lait!", "3 beds", "the chair " * 12]
CONTEXT = 16
WIDTH, HEADS, LAYERS, MLP = 64, 2, 2, 128
PATCH, IMAGE, EMBED = 8, 32, 32


def write_bpe(path: Path) -> Path:
    text = "#version: 0.2\n" + "\n".join(MERGES) + "\n"
    path.write_bytes(gzip.compress(text.encode("utf-8"), mtime=0))  # mtime 0: the same bytes every run
    return path


def hf_tokens(ours: ClipTokenizer) -> torch.Tensor:
    """(N, CONTEXT) token ids by transformers' CLIPTokenizer (the tokenizers-library CLIP: NFC,
    whitespace, lower case, CLIP's split regex, byte-level BPE), given the vocabulary and merges of
    the same BPE file; padded with 0 and truncated keeping EOT last, as open_clip does."""
    from transformers import CLIPTokenizer

    merges = [tuple(m.split(" ")) for m in MERGES]
    tok = CLIPTokenizer(vocab=dict(ours.encoder), merges=merges)
    assert (tok.bos_token_id, tok.eos_token_id) == (ours.sot_token, ours.eot_token)
    rows = []
    for text in TEXTS:
        ids = tok(text)["input_ids"]  # [SOT, ..., EOT]
        if len(ids) > CONTEXT:
            ids = ids[: CONTEXT - 1] + [ids[-1]]
        rows.append(ids + [0] * (CONTEXT - len(ids)))
    return torch.tensor(rows, dtype=torch.int64)


def build_model(vocab_size: int, eot: int):  # -> transformers.CLIPModel
    from transformers import CLIPConfig, CLIPModel

    config = CLIPConfig(
        text_config=dict(vocab_size=vocab_size, hidden_size=WIDTH, intermediate_size=MLP,
                         num_hidden_layers=LAYERS, num_attention_heads=HEADS,
                         max_position_embeddings=CONTEXT, hidden_act="quick_gelu", eos_token_id=eot,
                         bos_token_id=eot - 1, pad_token_id=0),
        vision_config=dict(hidden_size=WIDTH, intermediate_size=MLP, num_hidden_layers=LAYERS,
                           num_attention_heads=HEADS, image_size=IMAGE, patch_size=PATCH,
                           hidden_act="quick_gelu"),
        projection_dim=EMBED,
    )  # fmt: skip
    model = CLIPModel(config).eval()
    g = torch.Generator().manual_seed(SEED)
    with torch.no_grad():  # every parameter drawn here, in name order (reproducible bytes)
        for name, p in sorted(model.named_parameters()):
            noise = torch.randn(p.shape, generator=g, dtype=torch.float64)
            if name == "logit_scale":
                p.fill_(math.log(1 / 0.07))
            elif ("norm" in name or "layrnorm" in name) and name.endswith(".weight"):
                p.copy_(1 + 0.1 * noise)
            elif "embedding" in name:
                p.copy_(0.5 * noise)
            elif p.ndim >= 2:
                p.copy_(noise * p[0].numel() ** -0.5)  # fan-in scaling
            else:
                p.copy_(0.1 * noise)
    return model


def openai_state_dict(model) -> dict[str, torch.Tensor]:  # noqa: ANN001 - transformers.CLIPModel
    """The transformers CLIPModel's weights under OpenAI / open_clip key names."""
    sd = {k: v.detach().clone().float() for k, v in model.state_dict().items()}
    out: dict[str, torch.Tensor] = {}

    def block(src: str, dst: str) -> None:
        pairs = (("ln_1", "layer_norm1"), ("ln_2", "layer_norm2"), ("attn.out_proj", "self_attn.out_proj"),
                 ("mlp.c_fc", "mlp.fc1"), ("mlp.c_proj", "mlp.fc2"))  # fmt: skip
        for ours, theirs in pairs:
            for leaf in ("weight", "bias"):
                out[f"{dst}.{ours}.{leaf}"] = sd[f"{src}.{theirs}.{leaf}"]
        for leaf in ("weight", "bias"):
            out[f"{dst}.attn.in_proj_{leaf}"] = torch.cat(
                [sd[f"{src}.self_attn.{p}_proj.{leaf}"] for p in ("q", "k", "v")], dim=0
            )

    v, t = "vision_model", "text_model"
    out["visual.conv1.weight"] = sd[f"{v}.embeddings.patch_embedding.weight"]
    out["visual.class_embedding"] = sd[f"{v}.embeddings.class_embedding"]
    out["visual.positional_embedding"] = sd[f"{v}.embeddings.position_embedding.weight"]
    for leaf in ("weight", "bias"):
        out[f"visual.ln_pre.{leaf}"] = sd[f"{v}.pre_layrnorm.{leaf}"]
        out[f"visual.ln_post.{leaf}"] = sd[f"{v}.post_layernorm.{leaf}"]
        out[f"ln_final.{leaf}"] = sd[f"{t}.final_layer_norm.{leaf}"]
    for i in range(LAYERS):
        block(f"{v}.encoder.layers.{i}", f"visual.transformer.resblocks.{i}")
        block(f"{t}.encoder.layers.{i}", f"transformer.resblocks.{i}")
    out["visual.proj"] = sd["visual_projection.weight"].T.contiguous()
    out["token_embedding.weight"] = sd[f"{t}.embeddings.token_embedding.weight"]
    out["positional_embedding"] = sd[f"{t}.embeddings.position_embedding.weight"]
    out["text_projection"] = sd["text_projection.weight"].T.contiguous()
    out["logit_scale"] = sd["logit_scale"].reshape(())
    return {k: v.contiguous() for k, v in out.items()}


def pixel_values(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (1, 3, H, W) by CLIPImageProcessorPil: rescale 1/255, OpenAI mean/std."""
    from transformers import CLIPImageProcessorPil  # the PIL/numpy processor (no torchvision here)

    proc = CLIPImageProcessorPil(do_resize=False, do_center_crop=False, do_convert_rgb=False)
    return proc(images=rgb, return_tensors="pt")["pixel_values"].float()


def maskclip_dense(model, pixels: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
    """(1, 3, H, W) -> (h_p, w_p, D) L2-normalised MaskCLIP features from the upstream modules."""
    vm = model.vision_model
    h_p, w_p = pixels.shape[2] // PATCH, pixels.shape[3] // PATCH
    x = vm.embeddings(pixels, interpolate_pos_encoding=True)
    x = vm.pre_layrnorm(x)
    *blocks, last = vm.encoder.layers
    for layer in blocks:
        x = layer(x, attention_mask=None)
        x = x[0] if isinstance(x, tuple) else x
    x = x + last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(x)))
    x = x + last.mlp(last.layer_norm2(x))
    feats = model.visual_projection(vm.post_layernorm(x[:, 1:]))  # (1, h_p*w_p, D)
    return F.normalize(feats.reshape(h_p, w_p, -1), dim=-1)


def main() -> None:
    import safetensors
    import transformers
    from safetensors.torch import save_file

    OUT.mkdir(parents=True, exist_ok=True)
    bpe = write_bpe(OUT / "clip_golden_bpe.txt.gz")
    ours = ClipTokenizer(bpe, context_length=CONTEXT)
    model = build_model(ours.vocab_size, ours.eot_token)
    tokens = hf_tokens(ours)
    rng = np.random.default_rng(SEED)
    image = rng.integers(0, 256, (IMAGE, IMAGE, 3), dtype=np.uint8)
    wide = rng.integers(0, 256, (IMAGE, IMAGE + IMAGE // 2, 3), dtype=np.uint8)
    with torch.no_grad():
        text_embeds = F.normalize(model.get_text_features(input_ids=tokens).pooler_output, dim=-1)
        image_embeds = F.normalize(
            model.get_image_features(pixel_values=pixel_values(image)).pooler_output, dim=-1
        )
        dense_square = maskclip_dense(model, pixel_values(image))
        dense_wide = maskclip_dense(model, pixel_values(wide))
    meta = {
        "generator": "scripts/make_clip_golden.py",
        "transformers": transformers.__version__,
        "torch": torch.__version__,
        "safetensors": safetensors.__version__,
        "seed": str(SEED),
        "texts": json.dumps(TEXTS, ensure_ascii=False),
        "text_heads": str(HEADS),
        "vision_heads": str(HEADS),
        "activation": "quick_gelu",
    }
    save_file(openai_state_dict(model), str(OUT / "clip_golden.safetensors"), metadata=meta)
    ref = {
        "tokens": tokens,
        "text_embeds": text_embeds.float().contiguous(),
        "image": torch.from_numpy(image),
        "image_embeds": image_embeds.float().contiguous(),
        "wide": torch.from_numpy(wide),
        "dense_square": dense_square.float().contiguous(),
        "dense_wide": dense_wide.float().contiguous(),
    }
    save_file(ref, str(OUT / "clip_golden_ref.safetensors"), metadata=meta)
    for name in ("clip_golden_bpe.txt.gz", "clip_golden.safetensors", "clip_golden_ref.safetensors"):
        print(f"wrote {OUT / name} ({(OUT / name).stat().st_size} bytes)")


if __name__ == "__main__":
    main()
