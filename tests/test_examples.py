"""Rendered examples for the appearance model (Izo–Grimson §4)."""

import numpy as np

from estimator.examples import ExampleGrid, render_examples
from estimator.gait import GaitStyle
from estimator.skeleton import BodyShape


def test_default_grid_is_the_papers():
    grid = ExampleGrid()
    assert len(grid.azimuths_deg) == 72 and len(grid.elevations_deg) == 12  # 864 viewpoints
    assert len(grid) == 20 * 864 == 17_280
    assert grid.elevations_deg[0] == -20 and grid.elevations_deg[-1] == 35


def test_examples_cover_the_grid_with_joints_on_silhouettes():
    grid = ExampleGrid(n_phases=4, azimuth_step_deg=90.0, elevations_deg=(-20.0, 35.0))
    ex = render_examples(grid)
    assert len(ex) == 4 * 4 * 2
    assert {(p, a, e) for p, a, e in zip(ex.phase, ex.azimuth_deg, ex.elevation_deg)} == {
        (p, a, e) for p in (0, 0.25, 0.5, 0.75) for a in (0, 90, 180, 270) for e in (-20, 35)
    }
    w, h = grid.crop
    uv = np.round(ex.joints2d).astype(int)
    assert uv[..., 0].min() >= 0 and uv[..., 0].max() < w and uv[..., 1].min() >= 0 and uv[..., 1].max() < h
    on = ex.silhouettes[np.arange(len(ex))[:, None], uv[..., 1], uv[..., 0]] == 255
    assert on.mean() > 0.99
    # Nothing is cut off by the crop.
    assert not ex.silhouettes[:, [0, -1], :].any() and not ex.silhouettes[:, :, [0, -1]].any()


def test_bodies_render_all_points_or_take_turns():
    grid = ExampleGrid(n_phases=2, azimuth_step_deg=180.0, elevations_deg=(0.0,))
    bodies = [(BodyShape(height=1.6), GaitStyle()), (BodyShape(height=1.9, girth=1.2), GaitStyle(arm_swing=1.4))]
    every = render_examples(grid, bodies=bodies)
    assert len(every) == 8 and list(every.style) == [0, 0, 0, 0, 1, 1, 1, 1]
    turns = render_examples(grid, bodies=bodies, cycle=True)
    assert len(turns) == 4 and list(turns.style) == [0, 1, 0, 1]
    np.testing.assert_array_equal(turns.silhouettes[0], every.silhouettes[0])
    np.testing.assert_array_equal(turns.silhouettes[1], every.silhouettes[5])
