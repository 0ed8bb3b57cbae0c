"""The grid index behind the whole-map answers' nearest map point
(``mapper.map.query_kernels.NearestGrid``) against a k-d tree query with ``distance_upper_bound``."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapper.map import query_kernels
from mapper.map.query_kernels import NearestGrid


def _tree_nearest(pts: np.ndarray, queries: np.ndarray, radius: float) -> np.ndarray:
    dist, idx = cKDTree(pts).query(queries, distance_upper_bound=radius)
    return np.where(np.isfinite(dist), idx, -1)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("radius_cells", [0.4, 1.0, 2.5, 7.0])
def test_grid_nearest_equals_the_kd_tree(seed: int, radius_cells: float) -> None:
    # surface-like points (a noisy plane and a box edge), queries on them, off them, in empty space
    # beyond the radius and far outside the grid, for radii below, at and beyond a cell
    rng = np.random.default_rng(seed)
    cell = 0.05
    plane = np.column_stack([rng.uniform(0, 2, 3000), rng.uniform(0, 1.5, 3000), rng.normal(0, 0.004, 3000)])
    edge = np.column_stack([rng.uniform(0, 2, 500), np.full(500, 1.5), rng.uniform(0, 0.8, 500)])
    pts = np.concatenate([plane, edge])
    queries = np.concatenate([
        pts[rng.choice(pts.shape[0], 500)] + rng.normal(0, 0.01, (500, 3)),
        rng.uniform([-0.5, -0.5, -0.5], [2.5, 2.0, 1.0], (2000, 3)),
        rng.normal(0, 50.0, (50, 3)),
    ])
    grid = NearestGrid.build(pts, cell)
    assert grid is not None
    radius = radius_cells * cell
    got = grid.nearest(queries, radius, threads=2)
    want = _tree_nearest(pts, queries, radius)
    np.testing.assert_array_equal(got, want)
    assert 100 < int((got >= 0).sum()) < queries.shape[0]  # both hits and misses
    np.testing.assert_array_equal(grid.nearest(queries, radius, threads=1), got)


def test_grid_edge_cases() -> None:
    grid = NearestGrid.build(np.zeros((0, 3)), 0.1)
    assert grid is not None
    assert grid.nearest(np.zeros((3, 3)), 1.0).tolist() == [-1, -1, -1]
    one = NearestGrid.build(np.array([[1.0, 2.0, 3.0]]), 0.1)
    assert one is not None
    q = np.array([[1.0, 2.0, 3.0], [1.05, 2.0, 3.0], [1.2, 2.0, 3.0], [-1e12, 0.0, 0.0]])
    assert one.nearest(q, 0.1).tolist() == [0, 0, -1, -1]
    assert one.nearest(q, 0.0).tolist() == [-1, -1, -1, -1]  # nothing is strictly within 0
    assert one.nearest(q[:0], 0.1).shape == (0,)
    # equidistant points in different cells (either order of the cells): the lowest index
    for pair in ([[0.03, 0.0, 0.0], [-0.03, 0.0, 0.0]], [[-0.03, 0.0, 0.0], [0.03, 0.0, 0.0]]):
        tied = NearestGrid.build(np.array(pair), 0.05)
        assert tied is not None and tied.nearest(np.zeros((1, 3)), 0.1).tolist() == [0]
    with pytest.raises(ValueError, match="cell_m"):
        NearestGrid.build(np.zeros((2, 3)), 0.0)


def test_a_grid_too_large_is_not_built(monkeypatch: pytest.MonkeyPatch) -> None:
    # two points 1 km apart at 5 cm cells: 20 001 cells along x, over the budget -> None (the
    # global map then queries a k-d tree)
    monkeypatch.setattr(query_kernels, "_GRID_MAX_CELLS", 10_000)
    assert NearestGrid.build(np.array([[0.0, 0.0, 0.0], [1000.0, 0.0, 0.0]]), 0.05) is None
    assert NearestGrid.build(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]), 0.05) is not None
