"""``pipeline._common.ids_in``: which segment ids are among others, by hash lookup.

``np.isin`` on text ids (object arrays) compares every pair: a stage-2 ``estimate --plan``
at a million segments spent 245 s in it. ``ids_in`` must answer exactly as ``np.isin``.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from bams_cli.pipeline._common import ids_in

ids = st.lists(st.text(max_size=6), max_size=40)


@given(ids, ids)
def test_ids_in_answers_as_numpy_isin(a, b):
    A = np.array(a, dtype=object)
    B = np.array(b, dtype=object)
    got = ids_in(A, B)
    assert got.dtype == bool and got.shape == (len(a),)
    assert got.tolist() == [x in set(b) for x in a]
    if len(a):
        np.testing.assert_array_equal(got, np.isin(A, B))


def test_ids_in_takes_what_the_callers_pass():
    pool = np.array(["s1", "s2", "s 3", "S1"], dtype=object)
    assert ids_in(pool, np.array(["s1", "s 3"], dtype=object)).tolist() == [1, 0, 1, 0]
    assert ids_in(pool, np.array([], dtype=object)).tolist() == [0, 0, 0, 0]
    assert ids_in(pool[:0], np.array(["s1"], dtype=object)).tolist() == []
    assert ids_in(pool.astype(str), ["s2"]).tolist() == [0, 1, 0, 0]  # unicode and a list
