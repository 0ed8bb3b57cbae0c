"""The learned model as the runtime serves it: the checkpoint (and point head) loaded once, and the
settings every part of :class:`~mapper.runtime.model_runtime.ModelRuntime` reads.

:class:`LoadedModel` holds the runtime's config, device, the :class:`~mapper.model.field.GovNeSF`
network (None when the checkpoint could not be loaded: :attr:`LoadedModel.load_error` says why), the
network weighing point answers' views (``model.point_head``) and the text encoders. The parts of the
runtime (the volume, view selection, point answers, renders) read these through one shared
:class:`LoadedModel`, so a changed ``config`` or ``point_head`` reaches all of them at once.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from govnesf.resources import data_root
from mapper.errors import RuntimeNotReady
from mapper.model.field import GovNeSF, default_device
from mapper.model.fusion import FusionNet
from mapper.ov.encoders import TextEncoder
from mapper.runtime.config import ModelRuntimeConfig

log = logging.getLogger("mapper.runtime.model_runtime")  # the runtime's one logger, whichever part logs


def resolve_checkpoint(path: str) -> Path:
    """``path`` as given when it exists (or is absolute), else inside the checkout or the installed
    wheel's packaged data when it is there, else as given."""
    p = Path(path).expanduser()
    if p.is_absolute() or p.exists() or p.with_suffix(".json").exists():
        return p
    in_repo = data_root() / p  # the checkout, or the installed wheel's packaged data
    if in_repo.exists() or in_repo.with_suffix(".json").exists():
        return in_repo
    return p


class LoadedModel:
    """The network, its settings and the text encoders, shared by the parts of the runtime.

    Args:
        config: runtime settings.
        model: an already built model (tests, benchmarks); when None the checkpoint is loaded.
            A missing or unreadable checkpoint does not raise: :attr:`load_error` says why and
            :meth:`require_model` raises :class:`RuntimeNotReady` with that message.
        text_encoder: ``space -> TextEncoder``.
    """

    def __init__(
        self,
        config: ModelRuntimeConfig,
        *,
        model: GovNeSF | None,
        text_encoder: Callable[[str], TextEncoder],
    ) -> None:
        self.config = config
        self.device = default_device() if self.config.device == "auto" else torch.device(self.config.device)
        self.load_error: str | None = None
        self.metadata: dict[str, Any] = {}
        self.model: GovNeSF | None = None
        self.point_head: FusionNet | None = None
        """The network weighing point answers' views in place of the model's FusionNet (None: the
        model's own); ``model.point_head`` (:mod:`mapper.model.point_head`)."""
        if model is not None:
            self.model = model.to(self.device).eval()
        else:
            self._load_checkpoint()
        self.text_encoder = text_encoder

    def _load_checkpoint(self) -> None:
        path = resolve_checkpoint(self.config.checkpoint)
        try:
            from mapper.model.checkpoint import load_model

            self.model, self.metadata = load_model(path, device=self.device)
        except FileNotFoundError as exc:
            self.load_error = (
                f"the GOV-NeSF checkpoint {str(path)!r} was not found ({exc}); train one "
                "(govnesf train) or set model.checkpoint to an existing file"
            )
        except Exception as exc:  # corrupt file, wrong format, ...: serve the rest, say why
            self.load_error = f"the GOV-NeSF checkpoint {str(path)!r} could not be loaded: {exc}"
        if not self.load_error and self.config.point_head:
            self._load_point_head(path)
        if self.load_error:
            log.error("%s", self.load_error)
        else:
            log.info("loaded GOV-NeSF checkpoint %s on %s", path, self.device)

    def _load_point_head(self, checkpoint: Path) -> None:
        """``model.point_head`` beside the loaded checkpoint. ``"auto"``: ``NAME-point-head`` next to
        the checkpoint ``NAME`` when it exists and was distilled from these weights, else the
        model's own FusionNet (logged, never an error). A named head that is missing, unreadable or
        distilled from other weights leaves the model unserved (``load_error`` says why)."""
        from mapper.model.checkpoint import checkpoint_paths
        from mapper.model.point_head import head_paths, load_point_head

        auto = self.config.point_head == "auto"
        if auto:
            meta_path = checkpoint_paths(checkpoint)[1]
            path = meta_path.with_name(meta_path.stem + "-point-head")
            if not head_paths(path)[1].exists():
                log.info("point answers use the checkpoint's FusionNet (no %s.json)", path)
                return
        else:
            path = resolve_checkpoint(self.config.point_head)
        try:
            self.point_head, meta = load_point_head(
                path, teacher_sha256=self.metadata.get("weights_sha256"), device=self.device
            )
        except (ValueError, OSError) as exc:
            if auto:
                log.warning("point answers use the checkpoint's FusionNet: %s", exc)
                return
            missing = isinstance(exc, FileNotFoundError)
            self.load_error = (f"the point head {str(path)!r} was not found ({exc}); set model.point_head"
                               if missing else f"the point head {str(path)!r} could not be loaded: {exc}")
            self.model = None
            return
        log.info("point answers use the point head %s (%s)", path, meta["fusion"])

    @property
    def ready(self) -> bool:
        """True when a model is loaded (queries may still need keyframes)."""
        return self.model is not None

    def require_model(self) -> GovNeSF:
        """The model; :class:`RuntimeNotReady` (saying why) when none is loaded."""
        if self.model is None:
            raise RuntimeNotReady(self.load_error or "no GOV-NeSF model is loaded")
        return self.model

    @property
    def image_wh(self) -> tuple[int, int]:
        """(W, H) working size of the keyframes."""
        model = self.require_model()
        w = self.config.image_width or model.cfg.image_wh[0]
        h = self.config.image_height or model.cfg.image_wh[1]
        return int(w), int(h)

    @property
    def ov_wh(self) -> tuple[int, int]:
        """(w, h) of the common OV grid: the working size / 4 (the 2D feature resolution)."""
        w, h = self.image_wh
        return max(1, math.ceil(w / 4)), max(1, math.ceil(h / 4))

    @property
    def source_views(self) -> int:
        """Source views per render sample (``source_views``, default the model's)."""
        return self.config.source_views or self.require_model().cfg.num_source_views

    @property
    def point_source_views(self) -> int:
        """Source views per point for point answers (``segment``, ``point_features``)."""
        return max(self.config.point_source_views, self.source_views)

    @property
    def samples_per_ray(self) -> int:
        """Samples per marched ray (``samples_per_ray``, default the model's)."""
        return self.config.samples_per_ray or self.require_model().cfg.render.n_samples
