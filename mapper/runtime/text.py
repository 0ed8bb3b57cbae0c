"""Text prompts as the window's OV features read them: unit embeddings in the window's OV space."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapper.errors import RuntimeNotReady
from mapper.ov.encoders import UnknownSpaceError
from mapper.runtime.loading import LoadedModel
from mapper.runtime.prepared import Prepared


def text_embeddings(loaded: LoadedModel, prep: Prepared, texts: Sequence[str]) -> Tensor:
    """(T, D) unit embeddings of ``texts`` by the text encoder of the window's OV space.

    Raises :class:`RuntimeNotReady` when no keyframe carries OV features, the keyframes' features
    come from several spaces, the space has no text encoder, or its embeddings' size differs
    from the features'."""
    if prep.ov is None or not bool(prep.has_ov.any()):
        raise RuntimeNotReady(
            "semantic outputs need OV features, and no keyframe in the window carries 'ov'; "
            "send frames with ov (e.g. govnesf sim stream) or configure an in-process OV encoder"
        )
    if prep.ov_space is None:
        raise RuntimeNotReady("the window's keyframes carry OV features from several spaces")
    try:
        encoder = loaded.text_encoder(prep.ov_space)
    except UnknownSpaceError as exc:
        raise RuntimeNotReady(str(exc)) from None
    emb = torch.as_tensor(np.asarray(encoder.encode(list(texts)), dtype=np.float32), device=loaded.device)
    if emb.shape[-1] != prep.ov.shape[1]:
        raise RuntimeNotReady(
            f"text encoder for {prep.ov_space!r} gives {emb.shape[-1]}-d embeddings, the keyframes' "
            f"OV features are {prep.ov.shape[1]}-d"
        )
    return F.normalize(emb, dim=-1)
