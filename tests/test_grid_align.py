"""Default written grids sit on the ray counts' lattice (origin on a multiple of the resolution)."""

import math

import numpy as np
import pytest

from gpomap.grid import GridSpec
from gpomap.mapping import AreaGPOM
from gpomap.simulate import paper_room, simulate_scans


def test_from_extent_align_by_hand() -> None:
    spec = GridSpec.from_extent((0.12, 1.0, -0.07, 0.5), 0.05, align=True)
    assert spec.origin == pytest.approx((0.10, -0.10))
    # 0.10 .. 1.0 is 18 cells; -0.10 .. 0.5 is 12 cells.
    assert spec.shape == (12, 18)
    assert GridSpec.from_extent((0.12, 1.0, -0.07, 0.5), 0.05).origin == (0.12, -0.07)
    # An extent already on the lattice does not move or grow.
    assert GridSpec.from_extent((0.1, 1.0, -0.1, 0.5), 0.05, align=True).shape == (12, 18)


def test_default_grid_cells_are_the_counted_cells() -> None:
    world, poses = paper_room()
    # Off the lattice, so the data's corner is not already on a multiple of the resolution.
    scans = simulate_scans(world, np.asarray(poses)[::8] + np.array([0.013, -0.021, 0.0]), 45)
    model = AreaGPOM(kernel="se", max_cell=1.0, optimise=False, calibration_scans=3).fit(scans)
    om = model.grid(model.evidence_resolution)
    x0, y0 = om.grid.origin
    r = om.grid.resolution
    assert math.isclose(x0 / r, round(x0 / r), abs_tol=1e-6) and math.isclose(y0 / r, round(y0 / r), abs_tol=1e-6)
    assert model.evidence_._on_lattice(om.grid)
    # The same cells as a grid given that extent explicitly.
    again = model.grid(r, om.grid.extent)
    np.testing.assert_allclose(again.probability, om.probability, atol=1e-12)
