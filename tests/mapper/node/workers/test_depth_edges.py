"""``depth_points.depth_edges``: the rendered pixels at an occlusion edge (flying pixels)."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.node.config import ConfigError, config_from_dict
from mapper.node.workers.depth_points import depth_edges


def test_a_step_marks_both_sides_and_nothing_else() -> None:
    depth = np.full((6, 8), 2.0, np.float32)
    depth[:, 5:] = 4.0  # a wall behind an object edge between columns 4 and 5
    edge = depth_edges(depth, 0.1)
    assert edge[:, 4].all() and edge[:, 5].all()
    assert not edge[:, :4].any() and not edge[:, 6:].any()


def test_slopes_within_the_tolerance_holes_and_empty_images_are_not_edges() -> None:
    ramp = np.tile(np.linspace(2.0, 2.5, 10, dtype=np.float32), (5, 1))  # 2.7% steps: a slanted floor
    assert not depth_edges(ramp, 0.1).any()
    assert depth_edges(ramp, 0.01).all()  # a tolerance below the steps marks every pixel
    holes = np.full((4, 4), 3.0, np.float32)
    holes[1, 1] = 0.0  # no depth: neither an edge itself nor a reason for its neighbours
    assert not depth_edges(holes, 0.1).any()
    assert not depth_edges(np.zeros((3, 3), np.float32), 0.1).any()
    assert depth_edges(np.zeros((0, 5), np.float32), 0.1).shape == (0, 5)
    assert not depth_edges(np.full((1, 1), 2.0, np.float32), 0.1).any()
    with pytest.raises(ValueError, match=r"\(h, w\)"):
        depth_edges(np.ones((2, 3, 1), np.float32), 0.1)


def test_the_config_key_is_checked() -> None:
    assert config_from_dict({"global_map": {"rendered_edge_rel": 0.15}}).global_map.rendered_edge_rel == 0.15
    with pytest.raises(ConfigError, match="rendered_edge_rel"):
        config_from_dict({"global_map": {"rendered_edge_rel": -1.0}})
