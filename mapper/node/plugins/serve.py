"""The plugins ``govnesf serve`` installs on a node, in its order, in one call (the server,
``govnesf evaluate``'s node rows and the node benchmarks build the same node this way)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mapper.node.plugins.depth_points import RenderedDepthPoints
    from mapper.node.plugins.ov_features import OvFeatureWorker
    from mapper.node.plugins.triangulation import SparseTriangulation
    from mapper.node.service import MapperNode
    from mapper.runtime.model_runtime import ModelRuntime

__all__ = ["ServedPlugins", "install_serve_plugins"]


@dataclass
class ServedPlugins:
    """What :func:`install_serve_plugins` installed (None: not configured)."""

    runtime: ModelRuntime | None
    """The learned model (``serve_model``); check ``runtime.ready`` before relying on it."""
    rendered_depth: RenderedDepthPoints | None
    """Rendered-depth map points of keyframes without depth (with a ready model)."""
    triangulation: SparseTriangulation | None
    """Sparse triangulation and stereo of RGB-only keyframes (``triangulation.enabled``)."""
    ov_backend: OvFeatureWorker | None
    """In-process OV features (``ov_backend.kind``)."""


def install_serve_plugins(node: MapperNode) -> ServedPlugins:
    """Install on ``node``, from its config, what ``govnesf serve`` runs: the learned model's
    handlers (``serve_model``; a model that fails to load is installed anyway and reported by
    ``status``), triangulation (``triangulation.enabled``; its bounds feed a ready model), then
    the OV backend (``ov_backend.kind``; after the learned handlers, it adds its notes to their
    ``not_ready``)."""
    config = node.config
    runtime = rendered = tri = ov = None
    if config.serve_model:
        from mapper.node.plugins.learned import install_learned_handlers
        from mapper.runtime.model_runtime import ModelRuntime

        runtime = ModelRuntime(config.model)
        rendered = install_learned_handlers(node, runtime)
    if config.triangulation.enabled:
        from mapper.node.plugins.triangulation import install_triangulation

        tri = install_triangulation(node, runtime if runtime is not None and runtime.ready else None)
    if config.ov_backend.kind:
        from mapper.node.plugins.ov_features import install_ov_backend

        ov = install_ov_backend(node)
    return ServedPlugins(runtime, rendered, tri, ov)
