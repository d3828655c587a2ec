"""PlaceGrid: fit over all sessions, row-major labels, edges, save/load."""

import json

import numpy as np
import pytest

import placejax.data.grid as grid_module
from placejax.data import PlaceGrid


def _sessions(seed=0):
    rng = np.random.default_rng(seed)
    # Shapes like NCLT poses (x, y, yaw) and extents inside the campus box of docs/nclt.md.
    a = np.column_stack([rng.uniform(-380, 140, 500), rng.uniform(-750, 150, 500), rng.uniform(-3, 3, 500)])
    b = np.column_stack([rng.uniform(-300, 100, 300), rng.uniform(-700, 0, 300), rng.uniform(-3, 3, 300)])
    return [a, b]


def test_fit_is_bounding_box_of_all_sessions():
    a, b = _sessions()
    g = PlaceGrid.fit([a, b], n=10)
    both = np.concatenate([a, b])
    assert (g.x_min, g.x_max) == (both[:, 0].min(), both[:, 0].max())
    assert (g.y_min, g.y_max) == (both[:, 1].min(), both[:, 1].max())
    assert g.num_classes == 100


def test_fit_points_always_inside_including_max_edge():
    a, b = _sessions(1)
    g = PlaceGrid.fit([a, b], n=7)
    for s in (a, b):
        lab = g.label(s)
        assert lab.dtype == np.int32
        assert lab.shape == (len(s),)
        assert (lab >= 0).all()
        assert (lab < 49).all()
    corner = np.array([[g.x_max, g.y_max], [g.x_min, g.y_min], [g.x_max, g.y_min], [g.x_min, g.y_max]])
    assert g.label(corner).tolist() == [48, 0, 6 * 7, 6]


def test_label_matches_independent_loop_row_major():
    g = PlaceGrid(-10.0, 30.0, 0.0, 100.0, n=4)  # cells 10 m along x (rows), 25 m along y (cols)
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(-10, 30, 200), rng.uniform(0, 100, 200)])
    expected = []
    for x, y in xy:
        row = min(int((x + 10) // 10), 3)
        col = min(int(y // 25), 3)
        expected.append(row * 4 + col)
    np.testing.assert_array_equal(g.label(xy), expected)
    # Hand-picked: x picks the row, y the column.
    assert g.label(np.array([[15.0, 5.0], [-5.0, 80.0], [29.9, 99.0]])).tolist() == [2 * 4 + 0, 0 * 4 + 3, 15]


def test_outside_points_minus_one_or_clipped():
    g = PlaceGrid(0.0, 10.0, 0.0, 10.0, n=10)
    pts = np.array([[-0.1, 5.0], [5.0, 10.5], [np.nan, 1.0], [3.2, 4.7]])
    assert g.label(pts).tolist() == [-1, -1, -1, 34]
    assert g.label(pts, clip=True).tolist() == [5, 59, 1, 34]


def test_label_keeps_batch_shape():
    g = PlaceGrid(0.0, 1.0, 0.0, 1.0, n=2)
    xy = np.full((3, 5, 2), 0.75)
    assert g.label(xy).shape == (3, 5)
    assert (g.label(xy) == 3).all()


def test_edges_bounds_centers_consistent():
    g = PlaceGrid(-380.0, 140.0, -750.0, 150.0, n=10)
    xe, ye = g.edges
    assert xe.shape == ye.shape == (11,)
    assert xe[0] == -380.0
    assert xe[-1] == 140.0
    assert ye[0] == -750.0
    assert ye[-1] == 150.0
    centers = g.cell_centers()
    assert centers.shape == (100, 2)
    np.testing.assert_array_equal(g.label(centers), np.arange(100))
    for k in (0, 9, 10, 57, 99):
        x0, x1, y0, y1 = g.cell_bounds(k)
        assert x0 < centers[k, 0] < x1
        assert y0 < centers[k, 1] < y1
    with pytest.raises(ValueError, match="out of range"):
        g.cell_bounds(100)


def test_counts_and_unseen_cells():
    g = PlaceGrid(0.0, 2.0, 0.0, 2.0, n=2)
    c = g.counts(np.array([[0.5, 0.5], [0.6, 0.2], [1.5, 0.5], [5.0, 5.0]]))
    assert c.tolist() == [2, 0, 1, 0]


def test_save_load_roundtrip_exact(tmp_path):
    a, b = _sessions(2)
    g = PlaceGrid.fit([a, b], n=10)
    p = tmp_path / "sub" / "grid.json"
    g.save(p)
    g2 = PlaceGrid.load(p)
    assert g2 == g
    np.testing.assert_array_equal(g2.label(a), g.label(a))
    assert not list(p.parent.glob(".*tmp"))  # no temp files left behind


def test_bad_inputs_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="degenerate"):
        PlaceGrid.fit([np.array([[1.0, 0.0], [1.0, 5.0]])])
    with pytest.raises(ValueError, match=r"session 1 .* \(N, 2\), got \(3,\)"):
        PlaceGrid.fit([np.zeros((2, 2)), np.zeros(3)])
    with pytest.raises(ValueError, match="NaN"):
        PlaceGrid.fit([np.array([[0.0, 0.0], [np.nan, 1.0]])])
    with pytest.raises(TypeError, match="list"):
        PlaceGrid.fit(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="no viewpoints"):
        PlaceGrid.fit([])
    bad = tmp_path / "g.json"
    bad.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match=r"g\.json.*not a PlaceGrid"):
        PlaceGrid.load(bad)
    bad.write_text("{")
    with pytest.raises(ValueError, match=r"g\.json.*invalid"):
        PlaceGrid.load(bad)


@pytest.mark.parametrize("n", [2.5, True, np.True_, 0, -3, 50000, grid_module.MAX_N + 1, "10", None])
def test_n_must_be_a_positive_int_whose_labels_fit_int32(n):
    with pytest.raises(ValueError, match=r"PlaceGrid\.n must be"):
        PlaceGrid(0.0, 1.0, 0.0, 1.0, n=n)
    with pytest.raises(ValueError, match=r"PlaceGrid\.n must be"):
        PlaceGrid.fit([np.array([[0.0, 0.0], [1.0, 1.0]])], n=n)  # not truncated to int(n)


def test_largest_grid_labels_fit_int32_and_numpy_n_round_trips(tmp_path):
    g = PlaceGrid(0.0, 1.0, 0.0, 1.0, n=grid_module.MAX_N)
    top = g.label(np.array([[1.0, 1.0]]))
    assert top.dtype == np.int32
    assert top[0] == g.num_classes - 1 == grid_module.MAX_N**2 - 1
    g = PlaceGrid.fit([np.array([[0.0, 0.0], [1.0, 1.0]])], n=np.int64(7))
    assert type(g.n) is int
    g.save(tmp_path / "g.json")
    assert PlaceGrid.load(tmp_path / "g.json") == g


def test_bad_saved_grid_named(tmp_path):
    path = tmp_path / "g.json"
    good = PlaceGrid(0.0, 1.0, 0.0, 1.0, n=4).to_dict()
    for field, value in [("n", 2.5), ("n", 50000), ("x_min", "a"), ("x_max", None)]:
        path.write_text(json.dumps({**good, field: value}))
        with pytest.raises(ValueError, match=r"g\.json: invalid PlaceGrid"):
            PlaceGrid.load(path)


def test_bounds_must_be_real_numbers_and_binnable():
    with pytest.raises(TypeError, match="real numbers"):
        PlaceGrid(0.0, True, 0.0, 1.0)
    with pytest.raises(ValueError, match="too large"):
        PlaceGrid(-1e308, 1e308, 0.0, 1.0)
