"""The faster query paths against the previous ones: cell-hash radius components against every
k-d tree point pair, and the object clusters of ``query_points`` against the previous
``cluster_points`` on random maps."""

import numpy as np
import pytest

from mapper.node.queries import _pair_components, cluster_points, radius_components


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two component labelings group the points identically."""
    if a.shape != b.shape:
        return False
    pairs = np.unique(np.stack([a, b], axis=1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def blobs(seed: int, n: int, spread: float, n_blobs: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 5, (n_blobs, 3))
    return centres[rng.integers(0, n_blobs, n)] + rng.normal(0, spread, (n, 3))


@pytest.mark.parametrize(
    "pts",
    [
        blobs(0, 3000, 0.15, 40),  # many components of mixed sizes
        blobs(1, 2000, 0.05, 5),  # dense: the k-d tree path
        np.random.default_rng(2).uniform(0, 3, (2500, 3)),  # near the percolation threshold
        np.random.default_rng(3).uniform(-1, 1, (800, 3)) * [10, 0.01, 0.01],  # almost on a line
        np.stack(np.meshgrid(*[np.arange(12) * 0.11] * 3, indexing="ij"), -1).reshape(-1, 3),  # grid < r
        np.stack(np.meshgrid(*[np.arange(10) * 0.125] * 3, indexing="ij"), -1).reshape(-1, 3),  # grid, > r
        np.zeros((30, 3)),  # one repeated point
        np.array([[1.0, 2.0, 3.0]]),
    ],
)
def test_radius_components_equal_every_pair(pts: np.ndarray) -> None:
    for radius in (0.12, 0.3):
        n_ref, ref = _pair_components(pts, radius)
        n, comp = radius_components(pts, radius)
        assert n == n_ref
        assert same_partition(comp, ref)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_clusters_equal_the_previous_implementation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    xyz = blobs(seed, 4000, rng.uniform(0.05, 0.3), 30).astype(np.float32)
    label = np.asarray(rng.integers(0, 3, size=int(xyz.shape[0])))
    score = np.asarray(rng.random(size=int(xyz.shape[0])), np.float32)
    for radius, min_points in ((0.12, 15), (0.25, 5), (0.05, 2)):
        new = cluster_points(xyz, score, label, radius, min_points)
        ref = cluster_points(xyz, score, label, radius, min_points, reference=True)
        assert len(new) == len(ref) and len(ref) > 0

        def key(c) -> tuple:  # noqa: ANN001
            return (c.label, tuple(c.indices.tolist()))

        ref_by_key = {key(c): c for c in ref}
        for c in new:
            r = ref_by_key[key(c)]
            assert c.score == r.score
            np.testing.assert_array_equal(c.centroid, r.centroid)
            np.testing.assert_array_equal(c.aabb_min, r.aabb_min)
            np.testing.assert_array_equal(c.aabb_max, r.aabb_max)
        assert [c.score for c in new] == [c.score for c in ref]  # the same order up to ties


@pytest.mark.parametrize("seed", range(4))
def test_radius_components_ids_in_cell_order(seed: int) -> None:
    """Component ids count up in the order of the cells (the points' cell keys), so clusters of
    equal score keep one order between runs; the partition is every point pair's."""
    rng = np.random.default_rng(seed)
    pts = blobs(seed, 20_000, rng.uniform(0.02, 0.2), int(rng.integers(5, 200)))
    radius = float(rng.uniform(0.05, 0.2))
    n, comp = radius_components(pts, radius)
    n_ref, ref = _pair_components(pts, radius)
    assert n == n_ref and same_partition(comp, ref)
    side = radius / np.sqrt(3.0) * (1.0 - 1e-9)
    cell = np.floor(pts / side).astype(np.int64)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    first_seen = comp[np.argsort(key, kind="stable")]
    _, first = np.unique(first_seen, return_index=True)
    np.testing.assert_array_equal(first_seen[np.sort(first)], np.arange(n))


def test_radius_components_far_apart_points_use_the_hash() -> None:
    """Points kilometres apart: the key grid is too large for a dense table (the hash path)."""
    rng = np.random.default_rng(5)
    pts = np.concatenate([blobs(5, 500, 0.05, 3), blobs(6, 500, 0.05, 3) + [3000.0, -2000.0, 40.0]])
    pts = pts[rng.permutation(len(pts))]
    for radius in (0.05, 0.2):
        n, comp = radius_components(pts, radius)
        n_ref, ref = _pair_components(pts, radius)
        assert n == n_ref and same_partition(comp, ref)


def test_radius_components_beyond_the_key_range() -> None:
    """Points so far apart (in cells) that packed cell keys would overflow: the same components."""
    rng = np.random.default_rng(7)
    pts = np.concatenate([blobs(7, 300, 0.002, 4), blobs(8, 300, 0.002, 4) + [9e4, -9e4, 9e4]])
    pts = pts[rng.permutation(len(pts))]
    n, comp = radius_components(pts, 0.001)
    n_ref, ref = _pair_components(pts, 0.001)
    assert n == n_ref and same_partition(comp, ref)
