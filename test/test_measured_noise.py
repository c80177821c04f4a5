"""σ of U where the scan's noise is measured (judge/measured_noise.py): the compiled one-pass rule against the
formula written in numpy, with NaN σ̂ rows, unmeasured (NaN / inf) noise, rows without a class and non-finite
normals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hst
from hypothesis.extra import numpy as hnp

from xmetro_ros.judge.measured_noise import effective_sigma


def _rule(sig, normals, cls, noise):
    has = np.isfinite(noise)
    cls_eff = np.where(has, cls, -1).astype(np.int8)
    use = has & (cls_eff >= 0)
    return np.where(use[:, None], np.maximum(sig, noise[:, None] * np.abs(normals.astype(np.float64))), sig), cls_eff


_VAL = hst.one_of(hst.floats(0.0, 0.05), hst.sampled_from([np.nan, 0.0, 0.01]))
_NOISE = hst.one_of(hst.floats(0.0, 0.05), hst.sampled_from([np.nan, np.inf, 0.0]))
_NORMAL = hst.one_of(hst.floats(-1.0, 1.0, width=32), hst.sampled_from([np.nan, 0.0, -1.0]))


@settings(max_examples=150, deadline=None)
@given(hst.integers(1, 40).flatmap(lambda m: hst.tuples(
    hnp.arrays(np.float64, (m, 3), elements=_VAL), hnp.arrays(np.float32, (m, 3), elements=_NORMAL),
    hnp.arrays(np.int8, m, elements=hst.integers(-1, 4)), hnp.arrays(np.float64, m, elements=_NOISE))),
    hst.sampled_from([np.int8, np.int64]), hst.booleans())
def test_effective_sigma_is_the_rule_bit_for_bit(arrays, cls_dtype, normals64) -> None:
    sig, normals, cls, noise = arrays
    normals = normals.astype(np.float64) if normals64 else normals
    got_s, got_c = effective_sigma(sig, normals, cls.astype(cls_dtype), noise)
    want_s, want_c = _rule(sig, normals, cls, noise)
    assert got_c.dtype == np.int8 and got_c.tolist() == want_c.tolist()
    assert np.array_equal(got_s, want_s, equal_nan=True)


def test_effective_sigma_refuses_rows_that_do_not_match() -> None:
    with pytest.raises(ValueError, match="rows of sigma"):
        effective_sigma(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros(3, np.int8), np.zeros(3))
