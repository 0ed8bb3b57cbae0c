"""CLIP dense backend and tokenizer, tested with a tiny random CLIP the test writes to disk itself.

The weights are built key by key in the OpenAI / open_clip layout (not through the backend's own
module), and a slow, readable float64 reference of the CLIP forward passes (explicit per-head
attention, per-patch embedding) checks the backend's fast path.
"""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from mapper.ov.clip import (
    ClipBackendConfig,
    ClipDenseBackend,
    ClipWeightsError,
    dense_grid_shape,
    infer_architecture,
    read_state_dict,
)
from mapper.ov.clip_tokenizer import ClipTokenizer, clean_text

# Tiny architecture: image tower width 128 (2 heads of 64), text width 64 (2 heads of 32, set in the
# config), 2 layers each, patch 16 on a 64 px image (4 x 4 grid), joint embedding 32, context 16.
V_WIDTH, V_LAYERS, PATCH, IMAGE = 128, 2, 16, 64
T_WIDTH, T_LAYERS, T_HEADS, CONTEXT = 64, 2, 2, 16
EMBED = 32
V_HEADS = V_WIDTH // 64

MERGES = ["t h", "th e</w>", "c h", "a i", "ai r</w>", "ch air</w>", "t a", "b l", "l e</w>", "bl e</w>",
          "ta ble</w>"]  # fmt: skip


# ------------------------------------------------------------------------------------------------
# Fixtures: a merges file and a tiny CLIP state dict
# ------------------------------------------------------------------------------------------------


def write_bpe(path: Path, merges: list[str] = MERGES) -> Path:
    with gzip.open(path, "wt", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(merges) + "\n")
    return path


def _block(sd: dict, prefix: str, width: int, g: torch.Generator) -> None:
    def rn(*shape: int, scale: float = 1.0) -> torch.Tensor:
        return torch.randn(*shape, generator=g) * scale

    mlp = 4 * width
    sd[f"{prefix}.ln_1.weight"] = 1 + rn(width, scale=0.1)
    sd[f"{prefix}.ln_1.bias"] = rn(width, scale=0.1)
    sd[f"{prefix}.attn.in_proj_weight"] = rn(3 * width, width, scale=width**-0.5)
    sd[f"{prefix}.attn.in_proj_bias"] = rn(3 * width, scale=0.1)
    sd[f"{prefix}.attn.out_proj.weight"] = rn(width, width, scale=width**-0.5)
    sd[f"{prefix}.attn.out_proj.bias"] = rn(width, scale=0.1)
    sd[f"{prefix}.ln_2.weight"] = 1 + rn(width, scale=0.1)
    sd[f"{prefix}.ln_2.bias"] = rn(width, scale=0.1)
    sd[f"{prefix}.mlp.c_fc.weight"] = rn(mlp, width, scale=width**-0.5)
    sd[f"{prefix}.mlp.c_fc.bias"] = rn(mlp, scale=0.1)
    sd[f"{prefix}.mlp.c_proj.weight"] = rn(width, mlp, scale=mlp**-0.5)
    sd[f"{prefix}.mlp.c_proj.bias"] = rn(width, scale=0.1)


def tiny_clip_state_dict(vocab_size: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A random CLIP ViT state dict in the OpenAI / open_clip key layout."""
    g = torch.Generator().manual_seed(seed)
    grid = IMAGE // PATCH
    sd: dict[str, torch.Tensor] = {}
    sd["visual.conv1.weight"] = torch.randn(V_WIDTH, 3, PATCH, PATCH, generator=g) * (3 * PATCH**2) ** -0.5
    sd["visual.class_embedding"] = torch.randn(V_WIDTH, generator=g) * 0.5
    sd["visual.positional_embedding"] = torch.randn(grid * grid + 1, V_WIDTH, generator=g) * 0.5
    sd["visual.ln_pre.weight"] = 1 + 0.1 * torch.randn(V_WIDTH, generator=g)
    sd["visual.ln_pre.bias"] = 0.1 * torch.randn(V_WIDTH, generator=g)
    for i in range(V_LAYERS):
        _block(sd, f"visual.transformer.resblocks.{i}", V_WIDTH, g)
    sd["visual.ln_post.weight"] = 1 + 0.1 * torch.randn(V_WIDTH, generator=g)
    sd["visual.ln_post.bias"] = 0.1 * torch.randn(V_WIDTH, generator=g)
    sd["visual.proj"] = torch.randn(V_WIDTH, EMBED, generator=g) * V_WIDTH**-0.5
    sd["token_embedding.weight"] = torch.randn(vocab_size, T_WIDTH, generator=g) * 0.5
    sd["positional_embedding"] = torch.randn(CONTEXT, T_WIDTH, generator=g) * 0.1
    for i in range(T_LAYERS):
        _block(sd, f"transformer.resblocks.{i}", T_WIDTH, g)
    sd["ln_final.weight"] = 1 + 0.1 * torch.randn(T_WIDTH, generator=g)
    sd["ln_final.bias"] = 0.1 * torch.randn(T_WIDTH, generator=g)
    sd["text_projection"] = torch.randn(T_WIDTH, EMBED, generator=g) * T_WIDTH**-0.5
    sd["logit_scale"] = torch.tensor(math.log(1 / 0.07))
    return sd


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("clip")
    bpe = write_bpe(root / "bpe_simple_vocab_16e6.txt.gz")
    vocab = ClipTokenizer(bpe).vocab_size
    sd = tiny_clip_state_dict(vocab)
    torch.save(sd, root / "tiny.pt")
    save_file(sd, str(root / "tiny.safetensors"))
    return {"bpe": bpe, "pt": root / "tiny.pt", "safetensors": root / "tiny.safetensors", "root": root}


def make_cfg(files: dict[str, Path], weights: Path | None = None, **kw) -> ClipBackendConfig:
    kw.setdefault("device", "cpu")
    kw.setdefault("text_heads", T_HEADS)
    return ClipBackendConfig(weights_path=str(weights or files["pt"]), bpe_path=str(files["bpe"]), **kw)


@pytest.fixture(scope="module")
def backend(files: dict[str, Path]) -> ClipDenseBackend:
    return ClipDenseBackend(make_cfg(files, model_name="tiny-test"))


@pytest.fixture(scope="module")
def ref_sd(files: dict[str, Path]) -> dict[str, torch.Tensor]:
    """The saved weights in float64, for the reference passes."""
    return {k: v.double() for k, v in torch.load(files["pt"], weights_only=True).items()}


# ------------------------------------------------------------------------------------------------
# Slow, readable reference of the CLIP forward passes (float64, one sample at a time)
# ------------------------------------------------------------------------------------------------


def ref_layer_norm(x: torch.Tensor, sd: dict, prefix: str, eps: float = 1e-5) -> torch.Tensor:
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + eps) * sd[f"{prefix}.weight"] + sd[f"{prefix}.bias"]


def ref_block(
    x: torch.Tensor, sd: dict, prefix: str, heads: int, causal: bool = False, value_only: bool = False
) -> torch.Tensor:
    """One residual block on (L, C) tokens; ``value_only`` is the MaskCLIP last block."""
    n, c = x.shape
    h = ref_layer_norm(x, sd, f"{prefix}.ln_1")
    w, b = sd[f"{prefix}.attn.in_proj_weight"], sd[f"{prefix}.attn.in_proj_bias"]
    q = h @ w[:c].T + b[:c]
    k = h @ w[c : 2 * c].T + b[c : 2 * c]
    v = h @ w[2 * c :].T + b[2 * c :]
    if value_only:
        mixed = v
    else:
        d = c // heads
        mixed = torch.zeros_like(v)
        for head in range(heads):
            cols = slice(head * d, (head + 1) * d)
            scores = q[:, cols] @ k[:, cols].T / math.sqrt(d)  # (L, L)
            if causal:
                future = torch.triu(torch.ones(n, n, dtype=torch.bool), diagonal=1)
                scores = scores.masked_fill(future, float("-inf"))
            mixed[:, cols] = torch.softmax(scores, dim=-1) @ v[:, cols]
    x = x + mixed @ sd[f"{prefix}.attn.out_proj.weight"].T + sd[f"{prefix}.attn.out_proj.bias"]
    h = ref_layer_norm(x, sd, f"{prefix}.ln_2")
    h = h @ sd[f"{prefix}.mlp.c_fc.weight"].T + sd[f"{prefix}.mlp.c_fc.bias"]
    h = h * torch.sigmoid(1.702 * h)  # QuickGELU
    return x + h @ sd[f"{prefix}.mlp.c_proj.weight"].T + sd[f"{prefix}.mlp.c_proj.bias"]


def ref_image_tokens(pixels: torch.Tensor, sd: dict) -> torch.Tensor:
    """(3, S, S) normalised pixels -> (1 + g*g, C) tokens after ln_pre (one patch at a time)."""
    grid = pixels.shape[-1] // PATCH
    tokens = [sd["visual.class_embedding"]]
    for row in range(grid):
        for col in range(grid):
            patch = pixels[:, row * PATCH : (row + 1) * PATCH, col * PATCH : (col + 1) * PATCH]
            tokens.append((sd["visual.conv1.weight"] * patch).sum(dim=(1, 2, 3)))
    x = torch.stack(tokens) + sd["visual.positional_embedding"]
    return ref_layer_norm(x, sd, "visual.ln_pre")


def ref_encode_image(pixels: torch.Tensor, sd: dict) -> torch.Tensor:
    """Standard CLIP image embedding (class token): (3, S, S) -> (D,)."""
    x = ref_image_tokens(pixels, sd)
    for i in range(V_LAYERS):
        x = ref_block(x, sd, f"visual.transformer.resblocks.{i}", V_HEADS)
    return ref_layer_norm(x[0], sd, "visual.ln_post") @ sd["visual.proj"]


def ref_dense(pixels: torch.Tensor, sd: dict, maskclip: bool = True) -> torch.Tensor:
    """MaskCLIP dense features at the native grid: (3, S, S) -> (g, g, D), not normalised.

    ``maskclip=False`` keeps the attention in the last block (plain CLIP patch tokens).
    """
    x = ref_image_tokens(pixels, sd)
    for i in range(V_LAYERS):
        last = i == V_LAYERS - 1
        x = ref_block(x, sd, f"visual.transformer.resblocks.{i}", V_HEADS, value_only=maskclip and last)
    feats = ref_layer_norm(x[1:], sd, "visual.ln_post") @ sd["visual.proj"]
    grid = pixels.shape[-1] // PATCH
    return feats.reshape(grid, grid, -1)


def ref_encode_text(tokens: torch.Tensor, sd: dict) -> torch.Tensor:
    """(L,) token ids -> (D,) text embedding at the EOT position (the largest id)."""
    x = sd["token_embedding.weight"][tokens] + sd["positional_embedding"]
    for i in range(T_LAYERS):
        x = ref_block(x, sd, f"transformer.resblocks.{i}", T_HEADS, causal=True)
    x = ref_layer_norm(x, sd, "ln_final")
    return x[int(tokens.argmax())] @ sd["text_projection"]


def normalised_pixels(rgb: np.ndarray, backend: ClipDenseBackend) -> torch.Tensor:
    """(S, S, 3) uint8 -> (3, S, S) float64 CLIP-normalised (no resize)."""
    x = torch.from_numpy(rgb).permute(2, 0, 1).double() / 255.0
    mean = torch.tensor(backend.cfg.image_mean, dtype=torch.float64).view(3, 1, 1)
    std = torch.tensor(backend.cfg.image_std, dtype=torch.float64).view(3, 1, 1)
    return (x - mean) / std


def random_rgb(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 3), dtype=np.uint8)


# ------------------------------------------------------------------------------------------------
# Tokenizer
# ------------------------------------------------------------------------------------------------


def test_tokenizer_applies_merges_in_rank_order(files: dict[str, Path]) -> None:
    tok = ClipTokenizer(files["bpe"], context_length=CONTEXT)
    assert tok.vocab_size == 512 + len(MERGES) + 2
    assert (tok.sot_token, tok.eot_token) == (tok.vocab_size - 2, tok.vocab_size - 1)
    ids = tok.encode("The CHAIR  table")
    assert ids == [tok.encoder["the</w>"], tok.encoder["chair</w>"], tok.encoder["table</w>"]]
    # A word no merge applies to stays as byte symbols, the last one marked as the end of the word.
    assert tok.encode("dog") == [tok.encoder["d"], tok.encoder["o"], tok.encoder["g</w>"]]


@pytest.mark.parametrize(
    "text", ["the chair", "A  Table\n", "café au lait", "3 beds", "ω chairs", "fish &amp; chips"]
)
def test_tokenizer_round_trips(files: dict[str, Path], text: str) -> None:
    tok = ClipTokenizer(files["bpe"])
    words = clean_text(text).split(" ")
    ids = tok.encode(text)
    # CLIP's decode ends every word with one space; digits are single tokens ("3 " + ...).
    assert tok.decode(ids) == "".join(w + " " for w in words)


def test_tokenizer_splits_punctuation_like_clip(files: dict[str, Path]) -> None:
    tok = ClipTokenizer(files["bpe"])
    assert tok.decode(tok.encode("chair, table!")) == "chair , table ! "
    assert tok.decode(tok.encode("it's")) == "it 's "


def test_tokenize_pads_and_truncates(files: dict[str, Path]) -> None:
    tok = ClipTokenizer(files["bpe"], context_length=CONTEXT)
    rows = tok.tokenize(["the chair", "", "the chair " * 20])
    assert rows.shape == (3, CONTEXT) and rows.dtype == np.int64
    body = tok.encode("the chair")
    assert rows[0].tolist() == [tok.sot_token, *body, tok.eot_token] + [0] * (CONTEXT - 2 - len(body))
    assert rows[1].tolist() == [tok.sot_token, tok.eot_token] + [0] * (CONTEXT - 2)
    long_ids = tok.encode("the chair " * 20)
    assert rows[2].tolist() == [tok.sot_token, *long_ids[: CONTEXT - 2], tok.eot_token]
    # EOT is the largest id of every row: the text tower finds it with argmax.
    assert (rows.argmax(axis=1) == [len(body) + 1, 1, CONTEXT - 1]).all()


def test_tokenizer_rejects_bad_input(tmp_path: Path, files: dict[str, Path]) -> None:
    with pytest.raises(FileNotFoundError, match="nope.txt.gz"):
        ClipTokenizer(tmp_path / "nope.txt.gz")
    bad = write_bpe(tmp_path / "bad.txt.gz", ["t h", "one two three"])
    with pytest.raises(ValueError, match="line 3"):
        ClipTokenizer(bad)
    tok = ClipTokenizer(files["bpe"])
    with pytest.raises(TypeError):
        tok.tokenize("a str, not a list")
    with pytest.raises(ValueError, match="out of range"):
        tok.decode([tok.vocab_size])


# ------------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------------


def test_architecture_is_read_from_shapes(files: dict[str, Path]) -> None:
    arch = infer_architecture(read_state_dict(files["pt"]), text_heads=T_HEADS)
    assert (arch.image_size, arch.patch_size, arch.grid_size) == (IMAGE, PATCH, IMAGE // PATCH)
    assert (arch.vision_width, arch.vision_layers, arch.vision_heads) == (V_WIDTH, V_LAYERS, V_HEADS)
    assert (arch.text_width, arch.text_layers, arch.text_heads) == (T_WIDTH, T_LAYERS, T_HEADS)
    assert (arch.embed_dim, arch.context_length) == (EMBED, CONTEXT)
    assert (arch.vision_mlp_width, arch.text_mlp_width) == (4 * V_WIDTH, 4 * T_WIDTH)
    assert arch.vocab_size == ClipTokenizer(files["bpe"]).vocab_size


def test_pt_and_safetensors_load_the_same_model(files: dict[str, Path], backend: ClipDenseBackend) -> None:
    other = ClipDenseBackend(make_cfg(files, files["safetensors"]))
    rgb = random_rgb(IMAGE, IMAGE, seed=3)
    assert np.array_equal(other.dense_features(rgb), backend.dense_features(rgb))
    assert np.array_equal(other.encode_text(["the chair"]), backend.encode_text(["the chair"]))


def test_nested_state_dict_with_module_prefix(files: dict[str, Path], backend: ClipDenseBackend) -> None:
    sd = torch.load(files["pt"], weights_only=True)
    nested = {"epoch": 7, "state_dict": {f"module.{k}": v for k, v in sd.items()}}
    nested["state_dict"]["module.attn_mask"] = torch.zeros(CONTEXT, CONTEXT)  # old open_clip buffer
    path = files["root"] / "nested.pt"
    torch.save(nested, path)
    other = ClipDenseBackend(make_cfg(files, path))
    assert np.array_equal(other.encode_text(["a table"]), backend.encode_text(["a table"]))


@pytest.mark.parametrize(
    "key", ["visual.ln_post.weight", "visual.conv1.weight", "transformer.resblocks.1.attn.out_proj.bias"]
)
def test_missing_key_is_named(tmp_path: Path, files: dict[str, Path], key: str) -> None:
    sd = torch.load(files["pt"], weights_only=True)
    del sd[key]
    torch.save(sd, tmp_path / "broken.pt")
    with pytest.raises(ClipWeightsError, match=key.replace(".", r"\.")):
        ClipDenseBackend(make_cfg(files, tmp_path / "broken.pt"))


def test_unexpected_key_and_wrong_shape_are_named(tmp_path: Path, files: dict[str, Path]) -> None:
    sd = torch.load(files["pt"], weights_only=True)
    extra = dict(sd, **{"visual.transformer.resblocks.0.ls_1.gamma": torch.ones(V_WIDTH)})
    torch.save(extra, tmp_path / "extra.pt")
    with pytest.raises(ClipWeightsError, match=r"ls_1\.gamma"):
        ClipDenseBackend(make_cfg(files, tmp_path / "extra.pt"))
    wrong = dict(sd, **{"visual.ln_pre.bias": torch.zeros(5)})
    torch.save(wrong, tmp_path / "wrong.pt")
    with pytest.raises(ClipWeightsError, match=r"visual\.ln_pre\.bias.*\(5,\).*\(128,\)"):
        ClipDenseBackend(make_cfg(files, tmp_path / "wrong.pt"))


def test_torchscript_archive_is_refused_clearly(tmp_path: Path, files: dict[str, Path]) -> None:
    path = tmp_path / "ViT-B-16.pt"
    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 2)), str(path))
    with pytest.raises(ClipWeightsError, match="TorchScript.*not supported.*torch.jit.load"):
        ClipDenseBackend(make_cfg(files, path))


def test_bad_config_is_refused(files: dict[str, Path]) -> None:
    with pytest.raises(ValueError, match="dtype 'float64'"):
        make_cfg(files, dtype="float64")
    with pytest.raises(ValueError, match="input_size 8 out of range"):
        make_cfg(files, input_size=8)
    with pytest.raises(ValueError, match="model_name"):
        make_cfg(files, model_name="has space")
    with pytest.raises(ValueError, match="activation"):
        make_cfg(files, activation="relu")
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        ClipDenseBackend(make_cfg(files, files["root"] / "missing.pt"))
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="float16.*cuda"):
            ClipDenseBackend(make_cfg(files, dtype="float16"))
        with pytest.raises(ValueError, match="CUDA is not available"):
            ClipDenseBackend(make_cfg(files, device="cuda"))


def test_tokenizer_larger_than_text_tower_is_refused(tmp_path: Path, files: dict[str, Path]) -> None:
    bpe = write_bpe(tmp_path / "big.txt.gz", [*MERGES, "d o", "do g</w>"])
    cfg = ClipBackendConfig(
        weights_path=str(files["pt"]), bpe_path=str(bpe), device="cpu", text_heads=T_HEADS
    )
    with pytest.raises(ClipWeightsError, match="do not belong together"):
        ClipDenseBackend(cfg)


# ------------------------------------------------------------------------------------------------
# Forward passes against the reference
# ------------------------------------------------------------------------------------------------


def test_encode_image_matches_reference(backend: ClipDenseBackend, ref_sd: dict) -> None:
    rgbs = [random_rgb(IMAGE, IMAGE, seed=s) for s in range(2)]
    pixels = torch.stack([normalised_pixels(rgb, backend) for rgb in rgbs])  # (2, 3, S, S)
    with torch.no_grad():
        fast = backend.model.encode_image(pixels.float()).double()  # (2, D)
    for i in range(len(rgbs)):
        ref = ref_encode_image(pixels[i], ref_sd)
        torch.testing.assert_close(fast[i], ref, atol=1e-5, rtol=0)
        # The public entry point (resize and crop are no-ops at the native size) agrees too.
        np.testing.assert_allclose(backend.encode_image(rgbs[i]), (ref / ref.norm()).numpy(), atol=1e-5)


def test_dense_features_match_maskclip_reference(backend: ClipDenseBackend, ref_sd: dict) -> None:
    rgb = random_rgb(IMAGE, IMAGE, seed=5)
    pixels = normalised_pixels(rgb, backend)
    ref = ref_dense(pixels, ref_sd)  # (g, g, D)
    with torch.no_grad():
        fast = backend.model.visual.dense(pixels[None].float())[0].double()
    torch.testing.assert_close(fast, ref, atol=1e-5, rtol=0)
    out = backend.dense_features(rgb)  # float16, normalised
    np.testing.assert_allclose(
        out.astype(np.float64), (ref / ref.norm(dim=-1, keepdim=True)).numpy(), atol=2e-3
    )
    # The value path matters: plain CLIP patch tokens (attention kept in the last block) differ.
    plain = ref_dense(pixels, ref_sd, maskclip=False)
    assert (plain - ref).abs().max() > 0.1


def test_encode_text_matches_reference(backend: ClipDenseBackend, ref_sd: dict) -> None:
    texts = ["the chair", "a table", "the chair " * 20]
    tokens = torch.from_numpy(backend.tokenizer.tokenize(texts))
    with torch.no_grad():
        fast = backend.model.encode_text(tokens).double()
    for i in range(len(texts)):
        torch.testing.assert_close(fast[i], ref_encode_text(tokens[i], ref_sd), atol=1e-5, rtol=0)


# ------------------------------------------------------------------------------------------------
# The backend's public API
# ------------------------------------------------------------------------------------------------


def test_encode_text_is_normalised_deterministic_and_cached(
    backend: ClipDenseBackend, files: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    assert backend.space == "openclip:tiny-test" and backend.dim == EMBED
    calls: list[int] = []
    real = backend.model.encode_text

    def counting(tokens: torch.Tensor) -> torch.Tensor:
        calls.append(tokens.shape[0])
        return real(tokens)

    monkeypatch.setattr(backend.model, "encode_text", counting)
    texts = ["a sofa", "a bed", "a sofa"]
    first = backend.encode_text(texts)
    assert first.shape == (3, EMBED) and first.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(first, axis=1), 1.0, atol=1e-6)
    assert calls == [2]  # two distinct strings, one batch
    again = backend.encode_text(["a bed", "a sofa"])
    assert calls == [2]  # served from the cache
    assert np.array_equal(again, first[[1, 0]]) and np.array_equal(first[0], first[2])
    assert not np.allclose(first[0], first[1])
    assert backend.encode(["a bed"]).tobytes() == first[1].tobytes()  # TextEncoder protocol
    assert backend.encode_text([]).shape == (0, EMBED)
    # A fresh backend from the same files gives the same embeddings.
    fresh = ClipDenseBackend(make_cfg(files))
    assert np.array_equal(fresh.encode_text(texts), first)
    with pytest.raises(TypeError):
        backend.encode_text("a sofa")


@pytest.mark.parametrize(
    ("hw", "input_size", "grid"), [((48, 80), None, (4, 7)), ((48, 80), 32, (2, 3)), ((90, 30), 48, (9, 3))]
)
def test_dense_features_keep_the_aspect_ratio(
    files: dict[str, Path], hw: tuple[int, int], input_size: int | None, grid: tuple[int, int]
) -> None:
    b = ClipDenseBackend(make_cfg(files, input_size=input_size))
    assert b.dense_grid(*hw) == grid == dense_grid_shape(*hw, input_size or IMAGE, PATCH)
    out = b.dense_features(random_rgb(*hw, seed=1))
    assert out.shape == (*grid, EMBED) and out.dtype == np.float16
    np.testing.assert_allclose(np.linalg.norm(out.astype(np.float32), axis=-1), 1.0, atol=2e-3)
    assert np.isfinite(out).all()


def test_positional_embedding_interpolation_keeps_axes(files: dict[str, Path]) -> None:
    """Patch positions that vary only along x stay constant along y after resizing to a 3 x 7 grid."""
    sd = torch.load(files["pt"], weights_only=True)
    grid = IMAGE // PATCH
    direction = torch.randn(V_WIDTH, generator=torch.Generator().manual_seed(1))
    cols = torch.arange(grid, dtype=torch.float32).repeat(grid)  # column index of patch r * grid + c
    sd["visual.positional_embedding"][1:] = cols[:, None] * direction
    path = files["root"] / "pos.pt"
    torch.save(sd, path)
    b = ClipDenseBackend(make_cfg(files, path))
    pos = b.model.visual.positional_embedding_for(3, 7)
    assert pos.shape == (1 + 3 * 7, V_WIDTH)
    torch.testing.assert_close(pos[0], sd["visual.positional_embedding"][0])  # class token untouched
    patch = pos[1:].reshape(3, 7, V_WIDTH)
    torch.testing.assert_close(patch, patch[:1].expand(3, 7, V_WIDTH), atol=1e-5, rtol=0)
    along_x = patch[0] @ direction / direction.dot(direction)  # (7,) column coordinate
    assert (along_x.diff() >= -1e-5).all() and along_x[-1] - along_x[0] > grid - 2
    assert b.model.visual.positional_embedding_for(grid, grid) is b.model.visual.positional_embedding


def test_bfloat16_is_close_to_float32(files: dict[str, Path], backend: ClipDenseBackend) -> None:
    b16 = ClipDenseBackend(make_cfg(files, dtype="bfloat16"))
    rgb = random_rgb(40, 72, seed=2)
    lo, hi = b16.dense_features(rgb).astype(np.float32), backend.dense_features(rgb).astype(np.float32)
    assert lo.shape == hi.shape
    cos = (lo * hi).sum(-1)
    assert cos.min() > 0.97, cos.min()
    assert b16.encode_text(["the chair"]).dtype == np.float32


def test_bad_images_are_refused(backend: ClipDenseBackend) -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8.*float32"):
        backend.dense_features(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(8, 8\)"):
        backend.dense_features(np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match="at least 1x1"):
        backend.dense_features(np.zeros((0, 8, 3), np.uint8))
    with pytest.raises(TypeError):
        backend.dense_features([[0, 0, 0]])
    # A 1 x 5000 strip at a 64 px short side would need a 4 x 20000 grid.
    with pytest.raises(ValueError, match="patch grid.*more than 16384"):
        backend.dense_features(np.zeros((1, 5000, 3), np.uint8))
