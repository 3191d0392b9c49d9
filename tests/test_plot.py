import io
import itertools

import numpy as np
import pytest
from PIL import Image

from gpomap.grid import GridSpec, OccupancyMap
from gpomap.plot import ScoreCurve, figure_png, plot_3d, plot_evaluation, plot_inputs, plot_map, plot_slices, save_figure
from gpomap.voxels import VoxelMap, VoxelSpec

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _map(with_variance=True, with_path=True):
    grid = GridSpec((-1.0, -0.5), 0.1, (12, 20))
    xs, ys = np.meshgrid(grid.x_centres(), grid.y_centres())
    p = np.clip(0.5 + 0.5 * np.sin(3 * xs) * np.cos(2 * ys), 0, 1)
    t = np.linspace(0, np.pi, 10)
    return OccupancyMap(
        grid,
        p,
        variance=np.abs(xs) if with_variance else None,
        path=np.c_[0.5 * np.cos(t), 0.3 * np.sin(t)] if with_path else None,
    )


def _assert_png(path):
    assert path.exists()
    assert path.read_bytes()[:8] == PNG_MAGIC
    with Image.open(path) as img:
        img.verify()


def test_plot_map_three_panels_and_png(tmp_path):
    out = tmp_path / "map.png"
    fig = plot_map(_map(), path=out, title="test map")
    assert len(fig.axes) == 3
    assert [ax.get_title() for ax in fig.axes][:2] == ["probability", "latent variance"]
    for ax in fig.axes:
        # Axes in metres: the grid's extent, origin lower.
        assert ax.get_xlim() == pytest.approx((-1.0, 1.0))
        assert ax.get_ylim() == pytest.approx((-0.5, 0.7))
        assert ax.child_axes, "each panel has its colour bar"
        assert len(ax.get_lines()) == 2  # the robot path and its start marker
    assert fig.axes[0].images[0].get_array().shape == (12, 20)
    _assert_png(out)


@pytest.mark.parametrize(
    ("origin", "shape", "title"),
    [((-1.0, -0.5), (12, 20), "test map"), ((-1234.5, -5678.0), (900, 200), None), ((0.0, 0.0), (40, 400), "wide")],
    ids=["small", "tall-far-from-origin", "wide"],
)
def test_plot_maps_panels_labels_and_colour_bars_fit_the_figure_apart(origin, shape, title):
    # The fixed margins (no layout engine) against what was drawn: every panel with its tick
    # labels, axis labels and colour bar inside the figure, and no two panels' drawings overlapping.
    grid = GridSpec(origin, 0.1, shape)
    xs, ys = np.meshgrid(grid.x_centres(), grid.y_centres())
    m = OccupancyMap(grid, np.clip(0.5 + 0.5 * np.sin(xs) * np.cos(ys), 0, 1), variance=1e-5 * np.abs(np.sin(xs)))
    fig = plot_map(m, title=title)
    _assert_laid_out(fig, fig.axes)  # each panel with its colour bar (a child axes)


def _assert_laid_out(fig, parts):
    """Every part of `fig` (axes, left to right), its tick labels, axis labels and children
    included, lies inside the figure and apart from the next, and the title above them all."""
    figure_png(fig)  # drawn, so the texts have their extents
    renderer = fig.canvas.get_renderer()
    boxes = [ax.get_tightbbox(renderer) for ax in parts]
    frame = fig.bbox
    for b in boxes:
        assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1, (b, frame)
    for left, right in itertools.pairwise(boxes):
        assert left.x1 < right.x0
    if fig._suptitle is not None:
        assert fig._suptitle.get_window_extent(renderer).y0 > max(b.y1 for b in boxes) - 1


def test_a_map_larger_than_a_panel_draws_every_kth_cell(monkeypatch):
    """A map wider than :data:`FIGURE_CELLS` is drawn from every k-th row and column (20 columns,
    at most 8 a side: every 3rd), over the map's whole extent, and its variance colour bar still
    reaches the largest variance of all cells, here one that is not drawn."""
    from gpomap import resources

    m = _map()
    m.variance[1, 1] = 9.0  # row and column 1: not among every 3rd
    monkeypatch.setattr(resources, "FIGURE_CELLS", 8)
    fig = plot_map(m)
    np.testing.assert_array_equal(fig.axes[0].images[0].get_array(), m.probability[::3, ::3])
    np.testing.assert_array_equal(fig.axes[2].images[0].get_array(), m.ternary[::3, ::3])
    assert fig.axes[0].images[0].get_extent() == pytest.approx([-1.0, 1.0, -0.5, 0.7])
    assert fig.axes[1].images[0].get_clim() == (0.0, 9.0)
    blank = plot_map(_map(with_variance=False))
    assert blank.axes[1].images[0].get_array().shape == (4, 7)


def test_plot_map_without_variance_or_path(tmp_path):
    fig = plot_map(_map(with_variance=False, with_path=False))
    assert len(fig.axes) == 3
    assert not fig.axes[0].get_lines()
    out = save_figure(fig, tmp_path / "nested.png")
    _assert_png(out)


def test_plot_inputs_with_boxes(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 4, (200, 2))
    occ = pts[:, 0] > 3
    boxes = np.array([[[0, 0], [2, 2]], [[3, 0], [4, 4]]])
    out = tmp_path / "inputs.png"
    fig = plot_inputs(pts, occ, boxes=boxes, box_labels=[-1, 1], path=out)
    assert len(fig.axes) == 1
    labels = fig.axes[0].get_legend_handles_labels()[1]
    n_hits = int(occ.sum())
    assert labels == ["occupied cells (1)", "free cells (1)", f"free ({200 - n_hits})", f"hits ({n_hits})"]
    _assert_png(out)


def test_plot_inputs_rejects_mismatch():
    with pytest.raises(ValueError, match="3 points but 2 occupied flags"):
        plot_inputs(np.zeros((3, 2)), [True, False])
    with pytest.raises(ValueError, match="1 boxes but 2 box labels"):
        plot_inputs(np.zeros((1, 2)), [True], boxes=np.zeros((1, 2, 2)), box_labels=[1, -1])


def test_save_figure_failure_keeps_old_png(tmp_path, monkeypatch):
    out = tmp_path / "fig.png"
    fig = plot_map(_map(), path=out)
    before = out.read_bytes()

    def broken_savefig(*args, **kwargs):
        raise RuntimeError("render failed")

    monkeypatch.setattr(fig, "savefig", broken_savefig)
    with pytest.raises(RuntimeError, match="render failed"):
        save_figure(fig, out)
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["fig.png"]


def test_a_figure_is_rendered_to_png_bytes_and_written_as_those_bytes(tmp_path):
    fig = plot_map(_map(), title="bytes")
    png = figure_png(fig)
    assert png[:8] == PNG_MAGIC
    with Image.open(io.BytesIO(png)) as img:
        # 150 dpi by default: the figure's size in inches times the dpi, in pixels.
        assert img.size == tuple(round(v * 150) for v in fig.get_size_inches())
    # Drawn again, the same map gives the same bytes.
    assert save_figure(plot_map(_map(), title="bytes"), tmp_path / "a.png").read_bytes() == png
    with Image.open(io.BytesIO(figure_png(fig, dpi=50))) as small:
        assert small.size == tuple(round(v * 50) for v in fig.get_size_inches())


def _voxels():
    """A 0.1 m slab: occupied at x > 0.5 m, free elsewhere."""
    spec = VoxelSpec((0.0, 0.0, 0.0), 0.1, (4, 6, 10))
    x = spec.centres()[:, 0].reshape(spec.shape)
    return VoxelMap(spec, np.where(x > 0.5, 0.9, 0.1))


def test_a_voxel_maps_slices_one_panel_a_height():
    m = _voxels()
    fig = plot_slices(m, heights=[0.05, 0.35], title="slices")
    panels = [ax for ax in fig.axes if ax.get_title().startswith("z = ")]
    assert [ax.get_title() for ax in panels] == ["z = 0.05 m", "z = 0.35 m"]
    np.testing.assert_array_equal(panels[1].images[0].get_array(), m.probability[3])
    assert panels[0].images[0].get_extent() == pytest.approx([0.0, 1.0, 0.0, 0.6])
    assert figure_png(fig)[:8] == PNG_MAGIC
    # The panels, then the colour bar in the right margin.
    _assert_laid_out(fig, [*panels, *(ax for ax in fig.axes if ax not in panels)])
    plain = plot_slices(m)
    _assert_laid_out(plain, plain.axes)
    # Where the map knows which voxels rays went to, the others are tinted over the probability.
    observed = np.zeros(m.spec.shape, dtype=bool)
    observed[:, :, :4] = True
    seen = plot_slices(VoxelMap(m.spec, m.probability, observed=observed), heights=[0.05])
    [panel] = [ax for ax in seen.axes if ax.get_title().startswith("z = ")]
    tint = np.asarray(panel.images[1].get_array())
    np.testing.assert_array_equal(tint[..., 3] > 0, ~observed[0])
    assert [t.get_text() for t in panel.get_legend().get_texts()] == ["no ray went there"]
    assert len(panels[0].images) == 1 and panels[0].get_legend() is None  # no mask known: no tint


def test_a_voxel_maps_occupied_voxels_in_3d():
    m = _voxels()
    fig = plot_3d(m)
    [ax] = [a for a in fig.axes if a.name == "3d"]
    occupied = int((m.probability > m.thresholds[1]).sum())
    assert ax.get_title() == f"occupied voxels ({occupied:,} shown)"
    thinned = plot_3d(m, max_points=occupied // 4)
    [ax] = [a for a in thinned.axes if a.name == "3d"]
    assert ax.get_title() == f"occupied voxels ({len(range(0, occupied, 4)):,} shown)"
    _assert_laid_out(fig, fig.axes)  # the view, then its colour bar


def _scores(with_roc=True):
    # Three of ten bins used: the empty ones have no point on the reliability curve.
    counts = [0] * 10
    counts[1], counts[5], counts[9] = 4, 2, 4
    mean_p = [None] * 10
    mean_p[1], mean_p[5], mean_p[9] = 0.15, 0.55, 0.95
    frac = [None] * 10
    frac[1], frac[5], frac[9] = 0.0, 0.5, 1.0
    out = {"auc": 0.9, "ece": 0.04, "reliability": {"mean_prob": mean_p, "frac_pos": frac, "counts": counts}}
    if with_roc:
        out["roc"] = {"fpr": [0.0, 0.0, 0.5, 1.0], "tpr": [0.0, 0.6, 1.0, 1.0]}
    return out


def test_plot_evaluation_roc_above_reliability_a_column_per_split(tmp_path):
    out = tmp_path / "eval.png"
    curves = [ScoreCurve("map", _scores(), "tab:blue"), ScoreCurve("grid", _scores(), "tab:red", ":")]
    fig = plot_evaluation([("blocks", curves), ("every", curves[:1])], path=out, title="scores")
    assert len(fig.axes) == 4  # two rows, two columns, row by row
    roc_blocks, roc_every, rel_blocks, rel_every = fig.axes
    assert [roc_blocks.get_title(), roc_every.get_title()] == ["blocks", "every"]
    # Each panel: the diagonal, then one line per curve.
    assert len(roc_blocks.get_lines()) == 3 and len(roc_every.get_lines()) == 2
    np.testing.assert_array_equal(roc_blocks.get_lines()[1].get_xdata(), [0.0, 0.0, 0.5, 1.0])
    np.testing.assert_array_equal(rel_blocks.get_lines()[1].get_xdata(), [0.15, 0.55, 0.95])
    np.testing.assert_array_equal(rel_blocks.get_lines()[1].get_ydata(), [0.0, 0.5, 1.0])
    assert rel_blocks.get_lines()[2].get_linestyle() == ":"
    labels = [t.get_text() for t in roc_blocks.get_legend().get_texts()]
    assert labels == ["chance", "map (AUC 0.900)", "grid (AUC 0.900)"]
    assert [t.get_text() for t in rel_every.get_legend().get_texts()] == ["calibrated", "map (ECE 0.040)"]
    _assert_png(out)


def test_plot_evaluation_without_roc_draws_the_reliability_row():
    fig = plot_evaluation([("every", [ScoreCurve("map", _scores(with_roc=False))])])
    assert len(fig.axes) == 1 and fig.axes[0].get_title() == "every"
    assert fig.axes[0].get_xlabel() == "predicted occupancy probability"
