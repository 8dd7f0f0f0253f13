"""The local surface: a defect stays out of it, on noisy and on noise-free maps."""
from __future__ import annotations

import numpy as np

from touchroller_perception.inspection.background import local_surface


def test_a_noise_free_map_keeps_its_defect_out_of_the_local_surface():
    """A noise-free rest has a residual sigma of 0: the rounds after the first kept nothing out (the
    surface sank 3.4 grey levels beside a dark line) before they kept what the first round left out."""
    values = np.full((300, 400), 128, np.float32)
    values[100:104, 50:300] = 60
    usable = np.ones(values.shape, bool)
    usable[:, :20] = False
    surface, sigma = local_surface(np.where(usable, values, 0).astype(np.float32), usable, 25.0, 2, 2.5, 1_000_000)
    assert sigma == 0.0
    off_the_line = usable & (np.abs(np.arange(300) - 101.5)[:, None] > 4)
    np.testing.assert_allclose(surface[off_the_line], 128, atol=1e-3)
