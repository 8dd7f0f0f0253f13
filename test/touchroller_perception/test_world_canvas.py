"""world_canvas: the map's value of its layers (level * band / flat where known), written in place or not."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from touchroller_perception.world_canvas import _value

_cells = st.sampled_from([0.0, 1e-7, 1e-3, 0.5, 1.0, 37.25, 255.0, -1.0, np.inf, np.nan])
_layer = arrays(np.float32, (6, 7), elements=st.one_of(_cells, st.floats(-10, 300, width=32)))


@settings(max_examples=60, deadline=None)
@given(band=_layer, flat=_layer, weight=_layer, level=st.floats(0.01, 10.0))
def test_the_value_written_over_its_own_copies_is_the_same_bits(band, flat, weight, level):
    """IntensityView reads its layers as copies and has the value written over them: the same bits as the
    value made in new arrays, whatever the cells hold (zero, tiny or negative flat fields and weights, NaN,
    infinities), and the caller's other arrays untouched."""
    grey, kept = _value(band.copy(), flat.copy(), weight.copy(), level)
    own_band, own_flat, own_weight = band.copy(), flat.copy(), weight.copy()
    grey2, kept2 = _value(own_band, own_flat, own_weight, level, in_place=True)
    assert grey2 is own_band and kept2 is own_weight
    assert grey.tobytes() == grey2.tobytes() and kept.tobytes() == kept2.tobytes()
    assert own_flat.tobytes() == flat.tobytes()
