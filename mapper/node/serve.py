"""What ``govnesf serve`` installs on a node, in its order, in one call (the server,
``govnesf evaluate``'s node rows and the node benchmarks build the same node this way): the learned
backend (:mod:`mapper.node.backends.learned`) and the background workers (:mod:`mapper.node.workers`)
the node's config asks for."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mapper.node.service import MapperNode
    from mapper.node.workers.depth_points import RenderedDepthPoints
    from mapper.node.workers.flow_points import DenseFlowPoints
    from mapper.node.workers.ov_features import OvFeatureWorker
    from mapper.node.workers.triangulation import SparseTriangulation
    from mapper.runtime.model_runtime import ModelRuntime

__all__ = ["ServeStages", "install_serve_stages"]


@dataclass
class ServeStages:
    """What :func:`install_serve_stages` installed (None: not configured)."""

    runtime: ModelRuntime | None
    """The learned model (``serve_model``); check ``runtime.ready`` before relying on it."""
    rendered_depth: RenderedDepthPoints | None
    """Rendered-depth map points of keyframes without depth (with a ready model)."""
    triangulation: SparseTriangulation | None
    """Sparse triangulation and stereo of RGB-only keyframes (``triangulation.enabled``)."""
    ov_backend: OvFeatureWorker | None
    """In-process OV features (``ov_backend.kind``)."""
    dense_flow: DenseFlowPoints | None = None
    """Dense optical-flow points of RGB-only keyframes (``dense_flow.enabled``)."""


def install_serve_stages(node: MapperNode) -> ServeStages:
    """Install on ``node``, from its config, what ``govnesf serve`` runs: the learned backend
    (``serve_model``; a model that fails to load is installed anyway and reported by ``status``),
    triangulation (``triangulation.enabled``; its bounds feed a ready model), dense-flow points
    (``dense_flow.enabled``), then the OV backend
    (``ov_backend.kind``; after the learned backend, it adds its notes to the ``not_ready`` answers)."""
    config = node.config
    runtime = rendered = tri = ov = flow = robots = None
    if config.serve_model:
        from mapper.node.backends.learned import install_learned_backend
        from mapper.node.backends.robot_runtimes import RobotRuntimes
        from mapper.runtime.model_runtime import ModelRuntime

        runtime = ModelRuntime(config.model)
        # one runtime per robot window, on this runtime's model
        robots = RobotRuntimes(runtime, config.global_map.max_depth_m)
        rendered = install_learned_backend(node, robots)
    if config.triangulation.enabled:
        from mapper.node.workers.triangulation import install_triangulation

        # the keyframes' extents and depth priors go to their robot's runtime
        tri = install_triangulation(node, robots if robots is not None and robots.ready else None)
    if config.dense_flow.enabled:
        from mapper.node.workers.flow_points import install_dense_flow

        flow = install_dense_flow(node)
    if config.ov_backend.kind:
        from mapper.node.workers.ov_features import install_ov_backend

        ov = install_ov_backend(node)
    return ServeStages(runtime, rendered, tri, ov, flow)
