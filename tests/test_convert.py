"""Tests of gpomap.convert: occupancy grids to continuous GP maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from gpomap.convert import ConversionResult, convert_grid, grid_to_observations, output_grid
from gpomap.errors import EmptyDataError, InputFormatError
from gpomap.grid import FREE, OCCUPIED, UNKNOWN, GridSpec, OccupancyMap
from gpomap.io.npz import save_map
from gpomap.io.rosmap import read_rosmap, write_rosmap

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TURTLEBOT = DATA / "turtlebot3-world-map" / "map.yaml"


def _labels_to_map(labels: np.ndarray, origin=(0.0, 0.0), resolution=0.05) -> OccupancyMap:
    """An OccupancyMap whose ternary labels are `labels` (FREE / OCCUPIED / UNKNOWN), shape (ny, nx)."""
    p = np.where(labels == OCCUPIED, 1.0, np.where(labels == FREE, 0.0, np.nan))
    return OccupancyMap(GridSpec(origin, resolution, labels.shape), p)


def _wall_map(origin=(0.0, 0.0), resolution=0.05, n=40, thickness=3) -> OccupancyMap:
    """n x n pixels: a vertical wall (columns 19.. for n = 40) in the middle, free on both sides, an
    unknown strip along the bottom."""
    labels = np.full((n, n), FREE, dtype=np.int8)
    labels[:, n // 2 - 1 : n // 2 - 1 + thickness] = OCCUPIED
    labels[:3, :] = UNKNOWN  # a strip the map never saw
    return _labels_to_map(labels, origin, resolution)


@pytest.fixture(scope="module")
def wall_result() -> ConversionResult:
    return convert_grid(_wall_map())


def test_observations_are_known_pixel_centres():
    labels = np.array([[FREE, UNKNOWN, OCCUPIED], [UNKNOWN, FREE, FREE]], dtype=np.int8)
    obs = grid_to_observations(_labels_to_map(labels, origin=(-1.0, 2.0), resolution=0.5))
    np.testing.assert_allclose(obs.points, [[-0.75, 2.25], [0.25, 2.25], [-0.25, 2.75], [0.25, 2.75]])
    np.testing.assert_array_equal(obs.occupied, [False, True, False, False])


def test_round_trip_same_resolution(wall_result):
    src = _wall_map()
    out = wall_result.map
    assert out.grid == src.grid
    truth = src.ternary
    known = truth != UNKNOWN
    assert (out.ternary[known] == truth[known]).mean() > 0.95
    # The wall stays occupied along its whole length, and the far free space stays free.
    assert (out.ternary[3:, 19:22] == OCCUPIED).all()
    assert (out.ternary[3:, :15] == FREE).all() and (out.ternary[3:, 25:] == FREE).all()
    rep = wall_result.report
    assert rep["agreement"]["ternary"] > 0.95 and rep["agreement"]["auc"] > 0.99
    assert rep["pixels"] == {"free": 37 * 37, "occupied": 37 * 3, "partial": 0, "unknown": 3 * 40}
    # Wall-aware cells: the 9 columns within 3 pixels of the wall (16..24) are one cell per pixel,
    # one point per wall pixel; the 31 far columns are merged into blocks of at most 4 x 4 pixels.
    n_far = rep["cells"]["n"] - 9 * 37 - 3 * 37
    assert 31 * 37 / 16 <= n_far < 31 * 37 / 2
    assert rep["cells"]["occupied"] == 2 * 3 * 37
    assert set(rep["hyperparameters"]) >= {"length_scale", "noise", "alpha", "beta"}
    assert rep["timings"]["total"] > 0
    assert rep["grid"]["edges_coincide"]


def test_thin_wall_stays_occupied():
    # Unweighted, the few wall cells lost to the many free ones and came out 'unknown' (p ~ 0.5);
    # with class-balanced leave-one-out weights the 2-pixel wall stays occupied.
    res = convert_grid(_wall_map(thickness=2))
    assert (res.map.ternary[3:, 19:21] == OCCUPIED).all()


def test_report_agreement_matches_output_map(wall_result):
    src = _wall_map()
    known = src.ternary != UNKNOWN
    expected = (wall_result.map.ternary[known] == src.ternary[known]).mean()
    assert wall_result.report["agreement"]["ternary"] == pytest.approx(expected)


@pytest.mark.parametrize("resolution", [0.025, 0.1])
def test_origin_and_resolution(resolution):
    # Origin negative and not a multiple of anything round; 40 px of 0.05 m = 2 m each way.
    src = _wall_map(origin=(-3.7, -1.35))
    res = convert_grid(src, resolution=resolution)
    out = res.map.grid
    assert out.resolution == resolution
    assert out.origin == src.grid.origin
    np.testing.assert_allclose(out.extent, src.grid.extent, atol=1e-12)
    assert out.shape == (round(2.0 / resolution),) * 2
    assert res.report["grid"]["edges_coincide"]
    # The wall is where it was: occupied at its centre line x = -3.7 + 1.025, free 0.5 m away.
    p = res.model.predict_proba(np.array([[-2.675, -0.5], [-3.175, -0.5], [-2.175, -0.5]]))
    assert p[0] > 0.66 and p[1] < 0.33 and p[2] < 0.33
    cols = np.floor((np.array([-2.675, -3.175]) - out.origin[0]) / resolution).astype(int)
    row = int(np.floor((-0.5 - out.origin[1]) / resolution))
    assert res.map.ternary[row, cols[0]] == OCCUPIED and res.map.ternary[row, cols[1]] == FREE


def test_output_grid_when_resolution_does_not_divide():
    src = GridSpec((-1.0, 0.5), 0.05, (30, 40))  # 2.0 m x 1.5 m
    out = output_grid(src, 0.3)
    assert out.origin == src.origin
    assert out.shape == (5, 7)  # 1.5 / 0.3 = 5 exactly; 2.0 / 0.3 = 6.67 -> 7 cells
    assert out.extent[1] > src.extent[1] and out.extent[1] - src.extent[1] < 0.3
    assert out.extent[3] == pytest.approx(src.extent[3])
    # Float noise (19.2 / 0.01 = 1920.0000000000002) does not add a cell.
    assert output_grid(GridSpec((-10.0, -10.0), 0.05, (384, 384)), 0.01).shape == (1920, 1920)
    explicit = output_grid(src, 0.1, extent=(0.0, 1.0, 1.0, 1.5))
    assert explicit.origin == (0.0, 1.0) and explicit.shape == (5, 10)


def test_rosmap_and_npz_sources(tmp_path, wall_result):
    src = _wall_map(origin=(-0.5, 0.25))
    yaml_path, _ = write_rosmap(src, tmp_path / "wall.yaml")
    npz_path = save_map(src, tmp_path / "wall.npz")
    from_yaml = convert_grid(yaml_path)
    from_npz = convert_grid(npz_path)
    from_rosmap = grid_to_observations(read_rosmap(yaml_path))
    assert from_yaml.map.grid == src.grid == from_npz.map.grid
    assert from_rosmap.points.shape[0] == from_yaml.report["pixels"]["free"] + from_yaml.report["pixels"]["occupied"]
    # The same labels through either file give the same map.
    np.testing.assert_allclose(from_yaml.map.probability, from_npz.map.probability, atol=1e-9)
    # Shifting the origin only shifts the map (up to where the optimiser stops in float noise).
    known = src.ternary != UNKNOWN
    assert (from_yaml.map.ternary[known] == wall_result.map.ternary[known]).mean() > 0.99
    with pytest.raises(InputFormatError, match="expected a ROS map YAML"):
        convert_grid(tmp_path / "wall.pgm")


def test_unknown_only_map_is_an_error():
    labels = np.full((10, 12), UNKNOWN, dtype=np.int8)
    with pytest.raises(EmptyDataError, match=r"no known pixels .*all 120 unknown"):
        convert_grid(_labels_to_map(labels))


@pytest.mark.parametrize("value,name", [(FREE, "free"), (OCCUPIED, "occupied")])
def test_single_class_map_is_an_error(value, name):
    labels = np.full((10, 12), value, dtype=np.int8)
    labels[0] = UNKNOWN
    with pytest.raises(EmptyDataError, match=f"only {name} known pixels .*needs both free and occupied"):
        convert_grid(_labels_to_map(labels))


def test_rotated_origin_is_rejected(tmp_path):
    yaml_path, _ = write_rosmap(_wall_map(), tmp_path / "map.yaml")
    config = yaml.safe_load(yaml_path.read_text())
    config["origin"] = [0.0, 0.0, 0.3]
    yaml_path.write_text(yaml.safe_dump(config))
    with pytest.raises(InputFormatError, match="rotated maps are not supported"):
        convert_grid(yaml_path)


def test_model_options_override_defaults():
    res = convert_grid(_wall_map(), max_cell=0.1, optimise=False, length_scale=0.1)
    assert res.model.max_cell == 0.1
    assert res.report["hyperparameters"]["length_scale"] == pytest.approx(0.1)


@pytest.mark.slow
@pytest.mark.skipif(not TURTLEBOT.exists(), reason="shared TurtleBot3 map not available")
def test_turtlebot_map_converts():
    res = convert_grid(TURTLEBOT)
    rep = res.report
    assert res.map.grid == read_rosmap(TURTLEBOT).grid
    assert rep["pixels"]["free"] + rep["pixels"]["occupied"] == 8734
    # Every occupied pixel is a cell and a centre point.
    assert rep["cells"]["occupied"] == 2 * rep["pixels"]["occupied"]
    assert rep["agreement"]["ternary"] > 0.95 and rep["agreement"]["auc"] > 0.99
    # Far from every known pixel the map stays unknown.
    assert res.map.ternary[0, 0] == UNKNOWN and res.map.ternary[-1, -1] == UNKNOWN


def _thin_wall_plan(n=100):
    """A fine truth (n x n pixels of 0.01 m): 2-pixel walls at offsets that do not line up with a
    5-pixel coarse grid, a solid block, free elsewhere."""
    fine = np.zeros((n, n), dtype=bool)
    fine[:, 0:2] = fine[:, -2:] = fine[0:2, :] = fine[-2:, :] = True  # outer walls
    fine[20:80, 33:35] = True  # vertical wall inside coarse column 6 (fine 30..34)
    fine[61:63, 10:60] = True  # horizontal wall inside coarse row 12 (fine 60..64)
    fine[25:40, 70:85] = True  # a solid block
    return fine


def _pooled(fine: np.ndarray, k: int, pooling: str) -> np.ndarray:
    """`fine` (bool, shape (ny, nx)) pooled to pixels of k x k: occupied if any fine pixel is, if
    most are, or their occupied share."""
    ny, nx = fine.shape
    blocks = fine.reshape(ny // k, k, nx // k, k)
    return {
        "any": blocks.any(axis=(1, 3)).astype(float),
        "majority": (blocks.mean(axis=(1, 3)) > 0.5).astype(float),
        "mean": blocks.mean(axis=(1, 3)),
    }[pooling]


@pytest.mark.parametrize("pooling", ["any", "majority", "mean"])
def test_finer_resolution_beats_interpolation(pooling):
    # A coarse pixel of 5 x 5 fine pixels is occupied if any of them is, if most are, or holds
    # their occupied share. Sampled at the fine resolution, the continuous map ranks the true fine
    # occupancy better than nearest-neighbour and bilinear up-sampling of the coarse grid, and
    # (p > 0.5) overlaps it better, told how the grid was made and inferring it alike. Measured
    # (AUC GP / nearest / bilinear; IoU the same): any 0.983 / 0.919 / 0.956, 0.523 / 0.462 /
    # 0.453; majority 0.858 / 0.622 / 0.632, 0.242 / 0.240 / 0.228; mean 0.994 / 0.937 / 0.965,
    # 0.830 / 0.240 / 0.228. Majority pooling erases the 2-pixel walls: what is left are the block
    # and the walls' crossings, and the free pixels beside them, taken as partly occupied, bring
    # back a little of the walls they end.
    from scipy import ndimage

    from gpomap.convert import infer_pooling
    from gpomap.metrics import roc_auc

    fine = _thin_wall_plan()
    k = 5
    coarse = _pooled(fine, k, pooling)
    assert infer_pooling(coarse) == pooling
    grid = OccupancyMap(GridSpec((0.0, 0.0), 0.05, coarse.shape), coarse)
    res = convert_grid(grid, resolution=0.01, pooling=pooling)
    assert res.model.reading_.pooling == pooling
    assert res.map.grid.shape == fine.shape
    scores = {
        "gp": res.map.probability,
        "nearest": np.kron(coarse, np.ones((k, k))),
        "bilinear": ndimage.zoom(coarse, k, order=1, grid_mode=True, mode="nearest"),
    }
    auc = {name: roc_auc(fine.ravel(), s.ravel()) for name, s in scores.items()}
    iou = {name: ((s > 0.5) & fine).sum() / ((s > 0.5) | fine).sum() for name, s in scores.items()}
    assert auc["gp"] > max(auc["nearest"], auc["bilinear"]) + 0.02, auc
    margin = 0.0 if pooling == "majority" else 0.05
    assert iou["gp"] > max(iou["nearest"], iou["bilinear"]) + margin, iou
    # Inferring the pooling gives the same map.
    np.testing.assert_array_equal(convert_grid(grid, resolution=0.01).map.probability, res.map.probability)
    # The cells cover their pixels' footprints: every box edge lies on the coarse pixel lattice,
    # except the points where occupied pixels' obstacles most likely are.
    cells = res.model.cells_
    side = (cells.upper - cells.lower).min(axis=1)
    pixel_cells = side > 0.5 * 0.05
    for edge in (cells.lower[pixel_cells], cells.upper[pixel_cells]):
        np.testing.assert_allclose(edge / 0.05, np.round(edge / 0.05), atol=1e-9)
    assert (side[~pixel_cells] == 0.0).all() and cells.occupied[~pixel_cells].all()
    assert (~pixel_cells).sum() == (coarse > 0).sum()
    # Far inside free space the map is free, at the block's centre occupied.
    assert res.map.probability[50, 50] < 0.2 and res.map.probability[32, 77] > 0.8


@pytest.mark.parametrize("pooling", ["any", "majority", "mean"])
def test_the_map_keeps_what_each_pixel_says(pooling):
    # Against the same fine plan pooled each way, converted back to its fine pixels: a pixel the
    # grid holds wholly free (a 0 of an any- or mean-pooled grid; nothing of the plan is in it)
    # is free at every fine pixel, far below any pixel holding something; a mean-pooled pixel's
    # fine probabilities average to its value (to the points held beside 0.5); a 1 of a
    # majority-pooled grid averages at least a half and is occupied throughout, a 0 averages at most
    # a half; and the occupied region (p > 0.5) is the GP's own wherever the grid does not hold a
    # pixel wholly free or occupied and its bounds allow, and pooled again the same way it gives
    # back the grid (a mean-pooled value to one of the 8 x 8 samples per pixel the shares are
    # measured on).
    from gpomap.convert import SHARE_SAMPLES

    fine = _thin_wall_plan()
    k = 5
    coarse = _pooled(fine, k, pooling)
    res = convert_grid(OccupancyMap(GridSpec((0.0, 0.0), 0.05, coarse.shape), coarse), resolution=0.01, pooling=pooling)
    p = res.map.probability
    mean = p.reshape(20, k, 20, k).mean(axis=(1, 3))
    of_pixel = np.kron(np.arange(coarse.size).reshape(coarse.shape), np.ones((k, k), dtype=int))
    if pooling in ("any", "mean"):
        free = np.kron(coarse == 0.0, np.ones((k, k), dtype=bool))
        assert not fine[free].any()  # what the pooling says, checked on the truth
        assert p[free].max() < 1e-3
        # Below every fine pixel of a pixel holding something, but for the least likely parts of
        # pixels holding a sliver (a mean-pooled 0.04 has its probabilities scaled to average 0.04).
        assert (p[~free] > p[free].max()).mean() > (0.99 if pooling == "mean" else 1.0 - 1e-12)
    if pooling == "mean":
        part = (coarse > 0.0) & (coarse < 1.0)
        np.testing.assert_allclose(mean[part], coarse[part], atol=0.05)
        assert np.median(np.abs(mean[part] - coarse[part])) < 1e-3
    if pooling == "majority":
        assert (mean[coarse == 1.0] >= 0.5 - 1e-3).all() and (mean[coarse == 0.0] <= 0.5 + 1e-3).all()
        # A 1 is more than half occupied, and which of its parts are free the grid does not say:
        # the occupied region covers all of it.
        assert (p[np.kron(coarse == 1.0, np.ones((k, k), dtype=bool))] > 0.5).all()
    g = res.map.grid
    xx, yy = np.meshgrid(g.x_centres(), g.y_centres())
    own = res.model.predict_proba_gp(np.column_stack([xx.ravel(), yy.ravel()])).reshape(p.shape)
    reading = res.model.reading_
    held = ((reading.upper == 0.0) | (reading.lower == 1.0)).reshape(coarse.shape).ravel()[of_pixel]
    if pooling != "mean":
        # Without holding, the GP's own map, squashed at its own variance, ranks differently but
        # agrees on the occupied region up to the pixels its variance tips.
        assert ((own > 0.5) != (p > 0.5))[~held].mean() < 0.02
    assert ((p > 0.5) & held).sum() == ((p > 0.5) & held & (coarse.ravel()[of_pixel] == 1.0)).sum()
    if pooling == "mean":
        n = SHARE_SAMPLES
        on_samples = convert_grid(OccupancyMap(GridSpec((0.0, 0.0), 0.05, coarse.shape), coarse), resolution=0.05 / n)
        share = (on_samples.map.probability > 0.5).reshape(20, n, 20, n).mean(axis=(1, 3))
        np.testing.assert_allclose(share, coarse, atol=1.0 / n**2 + 1e-9)
    else:
        np.testing.assert_array_equal(_pooled(p > 0.5, k, pooling), coarse)


def test_pooling_inferred_from_the_grid():
    # Values between 0 and 1: mean pooling. A grid of 0s and 1s whose walls run edge to edge:
    # any-pixel pooling. One whose occupied pixels are mostly wall ends and corner-only contacts
    # (what majority pooling leaves of thin walls): majority. Unknown pixels are no evidence.
    from gpomap.convert import BROKEN_SHARE, infer_pooling

    room = np.zeros((20, 20))
    room[[1, 18], 1:19] = room[1:19, [1, 18]] = 1.0
    room[1:10, 9] = 1.0  # a wall from the top one, ending in the room: 1 end in 76 + 8 pixels
    assert infer_pooling(room) == "any"
    assert infer_pooling(np.where(room == 1.0, 0.4, 0.0)) == "mean"
    with_unknown = room.copy()
    with_unknown[:, 19] = np.nan
    assert infer_pooling(with_unknown) == "any"
    broken = np.zeros((20, 20))
    broken[1, [1, 2, 9, 10, 17, 18]] = broken[[5, 9], 9] = 1.0  # pieces of the room's walls
    broken[12, 12] = broken[13, 13] = 1.0  # touching at a corner
    assert infer_pooling(broken) == "majority"
    # A long wall's two ends are 2 / 40 of its pixels: any.
    long_wall = np.zeros((3, 40))
    long_wall[1, :] = 1.0
    assert BROKEN_SHARE >= 2 / 40 and infer_pooling(long_wall) == "any"
    with pytest.raises(ValueError, match="pooling must be one of"):
        convert_grid(_wall_map(), pooling="median")


def test_any_pooled_ones_beside_unknown_space_read_with_the_factor():
    # Three rows of 1 m pixels (row 0 lowest), an unknown column between free ones:
    #   [0, ?, 1, 0, 0]
    #   [0, ?, 1, 1, 0]
    #   [0, ?, 1, 0, 0]
    # Runs of 1s from an unknown pixel to a free one: the three rows' (1, 2 and 1 long); column
    # 2's runs from the grid's outside end at its outside again, column 3's lies between free
    # pixels. So 2 of 3 are one pixel long, and at a factor of 3 the walls are t = 1 + 3 / 3 = 2
    # fine pixels thick; a wall front with a free strip of j = 0 or 1 fine pixels before it is
    # 2 / 2 or 2 / 3 of its pixel's known part: share 5 / 6.
    from gpomap.convert import OCCUPIED_FRACTION, boundary_wall_thickness, occluded_share, read_pixels

    grid = np.array([[0, np.nan, 1, 0, 0], [0, np.nan, 1, 1, 0], [0, np.nan, 1, 0, 0]])
    assert boundary_wall_thickness(grid, 3) == pytest.approx(2.0)
    assert boundary_wall_thickness(grid, 6) == pytest.approx(3.0)
    assert boundary_wall_thickness(np.zeros((3, 3)), 4) == 1.0  # no such wall: the thinnest
    assert occluded_share(2.0, 3) == pytest.approx(5 / 6)
    assert occluded_share(1.0, 2) == pytest.approx(0.75)
    assert occluded_share(2.0, 2) == occluded_share(3.0, 2) == 1.0
    rows, cols = np.nonzero(np.isfinite(grid))
    points = np.column_stack([cols + 0.5, rows + 0.5])
    value = grid[rows, cols]
    reading = read_pixels(points, value, 1.0, "any", pooling_factor=3)
    share = {(int(r), int(c)): s for r, c, s in zip(rows, cols, reading.share)}
    # Column 2's 1s: beside the unknown column; rows 0 and 2 have a free side (wall fronts), row 1
    # none (its wall came in from the 1 beside it, so all of its known part is occupied). The 1 at
    # column 3 has no unknown side: the share of any 1.
    assert share[0, 2] == share[2, 2] == pytest.approx(5 / 6)
    assert share[1, 2] == 1.0
    assert share[1, 3] == OCCUPIED_FRACTION
    assert all(share[r, c] == 0.0 for r, c in share if grid[r, c] == 0.0)
    untold = read_pixels(points, value, 1.0, "any")
    np.testing.assert_array_equal(untold.share[value == 1.0], OCCUPIED_FRACTION)
    # Other poolings do not use the factor.
    majority = read_pixels(points, value, 1.0, "majority", pooling_factor=3)
    np.testing.assert_array_equal(majority.share, read_pixels(points, value, 1.0, "majority").share)
    with pytest.raises(ValueError, match="pooling_factor"):
        read_pixels(points, value, 1.0, "any", pooling_factor=0)


def test_model_defaults_are_area_gpom_arguments():
    # The CLI counts cells with AreaGPOM(**model_defaults(...)); the footprint padding is
    # convert_grid's own option, and pixel_pad=0 gives boxes round the pixel centres.
    from gpomap.convert import model_defaults
    from gpomap.mapping import AreaGPOM

    AreaGPOM(**model_defaults(0.05))
    res = convert_grid(_wall_map(), pixel_pad=0.0, optimise=False, length_scale=0.15)
    assert res.model.pixel_pad == 0.0
    single = res.model.cells_.upper - res.model.cells_.lower
    assert (single.min(axis=1) == 0.0).any()  # a one-pixel-wide cell is a segment without padding


def test_grid_cells_single_occupied_pixel():
    # 5 x 5 free pixels of 1 m round one occupied pixel at (2, 2), centre (2.5, 2.5): every pixel is
    # within 3 pixels of it, so 25 one-pixel cells, then one point at the occupied pixel's centre;
    # weights 3 except that point's. The grid is of 0s and 1s, pooled by any pixel, so the occupied
    # pixel is taken to be OCCUPIED_FRACTION occupied: its target is 2 * 0.7 - 1; every free one's
    # -1, the point's +1.
    from gpomap.convert import MAJORITY_NEIGHBOUR_SHARE, OCCUPIED_FRACTION, grid_cells

    xs, ys = np.meshgrid(np.arange(5) + 0.5, np.arange(5) + 0.5)
    points = np.column_stack([xs.ravel(), ys.ravel()])
    occupied = np.zeros(25, dtype=bool)
    occupied[12] = True
    cells = grid_cells(points, occupied, pixel=1.0, max_cell=4.0, pooling="any")
    assert cells.reading.pooling == "any"
    np.testing.assert_array_equal(cells.reading.lower, 0.0)
    np.testing.assert_array_equal(cells.reading.upper, occupied.astype(float))
    assert len(cells) == 25 + 1
    np.testing.assert_allclose(np.sort((cells.upper - cells.lower)[:25].ravel()), 1.0)
    np.testing.assert_allclose(cells.lower[25], [2.5, 2.5])
    np.testing.assert_allclose(cells.upper[25], [2.5, 2.5])
    assert cells.occupied[25] and cells.occupied[:25].sum() == 1
    pixel_of = cells.member_order[cells.member_offsets[:-1]]
    expected = np.where(pixel_of == 12, 2 * OCCUPIED_FRACTION - 1, -1.0)
    expected[25] = 1.0
    np.testing.assert_allclose(cells.labels, expected)
    np.testing.assert_allclose(cells.weight, [3.0] * 25 + [1.0])
    np.testing.assert_allclose(cells.to_supports().counts, [3.0] * 25 + [1.0])
    # A grid of fractions is read as it is: the same pixel at 0.4 has target -0.2.
    frac = np.where(occupied, 0.4, 0.0)
    soft = grid_cells(points, frac, pixel=1.0, max_cell=4.0)
    assert soft.reading.pooling == "mean"
    expected_soft = expected.copy()
    expected_soft[:25][pixel_of[:25] == 12] = -0.2
    np.testing.assert_allclose(soft.labels, expected_soft)
    # Pooled by majority, the occupied pixel holds more than half (bounds [0.5, 1]), and its eight
    # neighbours, which may hold up to half of a wall that vanished from the grid, are taken as
    # MAJORITY_NEIGHBOUR_SHARE occupied; the rest are free, bounded to at most half. The lone
    # pixel is a broken wall: "auto" reads the grid as majority-pooled.
    major = grid_cells(points, occupied, pixel=1.0, max_cell=4.0)
    assert major.reading.pooling == "majority"
    ring = (np.abs(points - 2.5).max(axis=1) == 1.0)[pixel_of[:25]]
    expected_major = expected.copy()
    expected_major[:25][ring] = 2 * MAJORITY_NEIGHBOUR_SHARE - 1
    np.testing.assert_allclose(major.labels, expected_major)
    np.testing.assert_array_equal(major.reading.lower, np.where(occupied, 0.5, 0.0))
    np.testing.assert_array_equal(major.reading.upper, np.where(occupied, 1.0, 0.5))


def test_core_centres_follow_the_free_sides():
    # One row of pixels of 1 m (no rows above or below): free, 0.4, free, free, 0.2, 0.2, free.
    # The 0.4 pixel has free pixels on both sides: its wall is at its centre. The two 0.2 pixels
    # each have one free side: the free 0.8 of each lies there, so each one's occupied fifth is
    # along the edge they share, its centre 0.1 m from that edge (x = 5 -+ 0.1).
    from gpomap.convert.inputs import _core_centres

    frac = np.array([0.0, 0.4, 0.0, 0.0, 0.2, 0.2, 0.0])
    ij = np.column_stack([np.arange(7), np.zeros(7, dtype=int)])
    pts = np.column_stack([np.arange(7) + 0.5, np.full(7, 0.5)])
    free = (frac == 0.0)[None, :]
    some = frac > 0
    got = _core_centres(pts[some], frac[some], free, ij[some], 1.0)
    np.testing.assert_allclose(got, [[1.5, 0.5], [4.9, 0.5], [5.1, 0.5]])
    # With free pixels above and below too, a 0.25 pixel's core is a centred square of side 0.5.
    free2 = np.ones((3, 3), dtype=bool)
    free2[1, 1] = False
    got = _core_centres(np.array([[1.5, 1.5]]), np.array([0.25]), free2, np.array([[1, 1]]), 1.0)
    np.testing.assert_allclose(got, [[1.5, 1.5]])
    # Free on the left and below only: the core (0.5 x 0.5 for f = 0.25) sits in the upper right.
    free3 = np.zeros((3, 3), dtype=bool)
    free3[1, 0] = free3[0, 1] = True
    got = _core_centres(np.array([[1.5, 1.5]]), np.array([0.25]), free3, np.array([[1, 1]]), 1.0)
    np.testing.assert_allclose(got, [[1.75, 1.75]])


def test_grid_cells_merge_far_free_pixels_but_never_unknown_ones():
    # 12 x 12 pixels, occupied (0, 0), one unknown pixel at row 8, column 9. With wall_reach 1 the
    # pixels beyond chessboard distance 1 merge into blocks of at most 4 pixels a side; no cell
    # covers the unknown pixel, and the pixel cells tile the known pixels exactly.
    from gpomap.convert import grid_cells

    labels = np.zeros((12, 12), dtype=int)
    labels[0, 0] = 1
    keep = np.ones((12, 12), dtype=bool)
    keep[8, 9] = False
    rows, cols = np.nonzero(keep)
    points = np.column_stack([cols + 0.5, rows + 0.5]) * 0.1
    cells = grid_cells(points, labels[rows, cols] == 1, pixel=0.1, max_cell=0.4, wall_reach=1, edge_strip=0.0, centre_noise=None)
    side = cells.upper - cells.lower
    assert side.max() <= 0.4 + 1e-12
    np.testing.assert_allclose(np.prod(side, axis=1).sum(), 143 * 0.01)
    np.testing.assert_array_equal(cells.counts, np.round(np.prod(side, axis=1) / 0.01).astype(int))
    inside = np.all((cells.lower < [0.95, 0.85]) & (cells.upper > [0.95, 0.85]), axis=1)
    assert not inside.any()
    assert (side.max(axis=1) > 0.1 + 1e-12).sum() > 0  # some far pixels were merged
    assert len(cells) < 143 / 2


@pytest.mark.parametrize("tol, atol", [(1e-9, 1e-6), (None, 1e-4)], ids=["tight", "default"])
def test_grid_prediction_equals_the_models(tol, atol, monkeypatch):
    # The written grid (every output cell, in the local prediction's blocks of the whole grid)
    # gives the model's own probabilities and variances at a few of its cells' centres predicted
    # alone (other blocks, other inputs left out): to 1e-6 when covariances below 1e-9 of the
    # variance are left out; at the default tolerances they differed by 1.4e-6 at most.
    import gpomap.gp.posterior

    if tol is not None:
        monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_TOL", tol)
        monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_VARIANCE_TOL", tol)
    res = convert_grid(_wall_map(n=24, thickness=2), resolution=0.02)
    g = res.map.grid
    rng = np.random.default_rng(1)
    iy, ix = rng.integers(0, g.shape[0], 400), rng.integers(0, g.shape[1], 400)
    pts = np.column_stack([g.x_centres()[ix], g.y_centres()[iy]])
    p, v = res.model.predict_proba(pts, return_var=True)
    np.testing.assert_allclose(res.map.probability[iy, ix], p, rtol=0, atol=atol)
    np.testing.assert_allclose(res.map.variance[iy, ix], v, rtol=0, atol=atol)


def test_upsampled_wall_is_where_the_coarse_pixels_fractions_put_it():
    # A fine plan of 0.01 m pixels (100 x 100): a wall 2 pixels thick at columns 21-22 (inside
    # coarse column 4, fine 20..24) and one at columns 54-55 (straddling coarse columns 10 and 11,
    # fine 50..54 and 55..59), free elsewhere. Averaged to 0.05 m pixels, as a grid of occupied
    # shares (0.4; 0.2 and 0.2), and converted back to 0.01 m: occupied (p > 0.5) lies on the
    # walls, no wider than they are, never across the whole coarse pixels as nearest-neighbour
    # up-sampling paints them, and free space stays free. The straddling wall is found exactly;
    # the 0.4 pixel between free ones says nothing of where in it its wall is, and the map puts
    # it at the middle (column 22, one of the wall's two), as wide as 0.4 of the pixel allows
    # on the 8 x 8 samples its share is measured on.
    fine = np.zeros((100, 100), dtype=bool)
    fine[:, 21:23] = True
    fine[:, 54:56] = True
    coarse = fine.reshape(20, 5, 20, 5).mean(axis=(1, 3))
    np.testing.assert_allclose(np.unique(coarse), [0.0, 0.2, 0.4])
    res = convert_grid(OccupancyMap(GridSpec((0.0, 0.0), 0.05, coarse.shape), coarse), resolution=0.01)
    assert res.report["pixels"]["partial"] == 3 * 20
    p = res.map.probability[20:80]  # away from the map's top and bottom edges
    occupied_cols = np.flatnonzero((p > 0.5).all(axis=0))
    assert set(occupied_cols) >= {22, 54, 55}
    assert set(occupied_cols) <= {21, 22, 23, 54, 55}
    assert set(np.flatnonzero((p > 0.5).any(axis=0))) <= {21, 22, 23, 54, 55}
    # Each coarse pixel's fine probabilities average to its share (but for the points held beside 0.5).
    np.testing.assert_allclose(p.reshape(60, 20, 5).mean(axis=(0, 2))[[4, 10, 11]], [0.4, 0.2, 0.2], atol=0.02)
    assert (p[:, :18] < 0.5).all() and (p[:, 26:51] < 0.5).all() and (p[:, 59:] < 0.5).all()
    # The straddling wall is at the shared edge (x = 0.55 m): its probability peaks there.
    peak = 50 + int(np.argmax(p[:, 50:60].mean(axis=0)))
    assert peak in (54, 55)


def test_cli_reads_values_as_fractions_or_by_thresholds(tmp_path, capsys):
    # A 20 x 20 grid of 0.05 m pixels averaged from a finer plan: a wall at 0.4 in column 10.
    # Read as fractions (the default for a map without a variance layer) the wall is evidence;
    # read by the thresholds (0.33, 0.66) its pixels are unknown and only free ones are left.
    from gpomap.cli import main

    values = np.zeros((20, 20))
    values[:, 10] = 0.4
    path = save_map(OccupancyMap(GridSpec((0.0, 0.0), 0.05, values.shape), values), tmp_path / "mean.npz")
    assert main(["convert", str(path), "-o", str(tmp_path / "a"), "--resolution", "0.01", "-q", "--json"]) == 0
    import json

    report = json.loads(capsys.readouterr().out.split("\nwrote")[0])
    assert report["pixels"] == {"free": 380, "occupied": 0, "partial": 20, "unknown": 0}
    assert main(["convert", str(path), "-o", str(tmp_path / "b"), "--values", "ternary", "-q"]) == 1
    assert "only free known pixels" in capsys.readouterr().err
    assert main(["convert", str(path), "-o", str(tmp_path / "c"), "--occupied-fraction", "1.5", "-q"]) == 1
    assert "--occupied-fraction must be in (0, 1]" in capsys.readouterr().err


def test_the_converted_grid_is_the_fitted_maps_and_its_points_answers(wall_result: ConversionResult) -> None:
    """The conversion's written map, the fitted map's grid and its answers at the cell centres are
    one: every one of them is held to the pixels (the fitted map is the only code that answers)."""
    model, written = wall_result.model, wall_result.map
    again = model.grid(written.grid.resolution, written.grid.extent)
    p = model.predict_proba(written.grid.centres()).reshape(written.grid.shape)
    np.testing.assert_allclose(again.probability, p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(written.probability, p, rtol=0, atol=1e-12)
    # Held: a wall pixel's centre is occupied, a free pixel's far from it free.
    occupied = _wall_map().ternary == OCCUPIED
    assert p[occupied].min() > 0.5 and p[:, :5][3:].max() < 0.5
