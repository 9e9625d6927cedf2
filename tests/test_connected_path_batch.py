"""PathBatch / batch_path_reference: the same path references as SplinePath /
path_reference robot by robot, in one numpy pass."""

from __future__ import annotations

import numpy as np

from connected_helpers import preset_params
from controllers.connectivity.path_batch import PathBatch
from controllers.connectivity.paths import GridPlanner
from controllers.connectivity.targets import random_free_points
from controllers.connectivity.travel import PathReference, batch_path_reference, path_reference
from sim.geometry import Boxes


def test_batched_references_equal_the_single_path_ones():
    params = preset_params("office")
    walls = Boxes.axis_aligned([[5.0, 2.5, 2.5], [5.0, 8.75, 2.5]], [[0.1, 2.5, 2.5], [0.1, 1.25, 2.5]])
    planner = GridPlanner.from_params(walls, [0, 0, 0], [10, 10, 5], params)
    rng = np.random.default_rng(0)
    starts, goals = random_free_points(rng, planner, 8), random_free_points(rng, planner, 8)
    paths = [planner.plan(a, b) for a, b in zip(starts, goals)]
    batch = PathBatch(paths)
    for _ in range(5):
        # Points near, on and beyond the paths, including past both ends.
        along = rng.uniform(-0.2, 1.2, size=(8, 1))
        points = starts + along * (goals - starts) + rng.normal(0.0, 0.6, size=starts.shape)
        single = PathReference.stack([path_reference(p, x[None], 1.0, 2.0) for p, x in zip(paths, points)])
        batched = batch_path_reference(batch, points, 1.0, 2.0)
        for name in PathReference.__dataclass_fields__:
            np.testing.assert_allclose(getattr(batched, name), getattr(single, name), rtol=1e-12, atol=1e-12)
