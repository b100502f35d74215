"""The covariance and residual moments found again at the same arguments (fit._Recent): the
same numbers as computed afresh, and never another argument's."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.estimation import fit
from twinwatch.twin.estimation.fit import parameter_covariance, relative_std


def _problem(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(398, 4)), 1e-3 * rng.normal(size=398)


def _fresh(jac: np.ndarray, r: np.ndarray, **kw: object) -> np.ndarray:
    """parameter_covariance with the memos emptied first."""
    fit._COVARIANCES._entries = []
    fit._MOMENTS._entries = []
    return parameter_covariance(jac, r, 2, 1e-4, **kw)  # type: ignore[arg-type]


def test_a_result_found_again_is_the_one_computed_afresh() -> None:
    jac, r = _problem(1)
    first = _fresh(jac, r, numerical=0.01)
    again = parameter_covariance(jac.copy(), r.copy(), 2, 1e-4, numerical=0.01)
    assert np.array_equal(first, again) and again is not first
    # the caller may write to what it gets: the stored result stays
    again[:] = 0.0
    assert np.array_equal(parameter_covariance(jac, r, 2, 1e-4, numerical=0.01), first)
    # the moments reused across column counts: the standard errors of each subset as afresh
    for cols in ([0], [0, 1], [0, 1, 2, 3], [2, 3]):
        sd = relative_std(jac[:, cols], r, 2, 1e-4, 0.01)
        fit._MOMENTS._entries = []
        fit._COVARIANCES._entries = []
        assert np.array_equal(sd, relative_std(jac[:, cols], r, 2, 1e-4, 0.01))


def test_another_argument_is_never_given_a_stored_result() -> None:
    jac, r = _problem(2)
    base = _fresh(jac, r)
    # an argument written to in place after the call: its new values, not the stored ones
    r2 = 1.5 * r
    parameter_covariance(jac, r2, 2, 1e-4)
    r2[5] *= 3.0
    assert np.array_equal(parameter_covariance(jac, r2, 2, 1e-4), _fresh(jac, r2))
    # one bit of one entry, the sign of a zero, the layout, a number's value or type
    jac_b = jac.copy()
    jac_b[7, 1] = np.nextafter(jac_b[7, 1], np.inf)
    assert not np.array_equal(parameter_covariance(jac_b, r, 2, 1e-4), base)
    zeros, neg = np.zeros((10, 2)), -np.zeros((10, 2))
    _, key = fit._COVARIANCES.get((zeros, 1.0))
    fit._COVARIANCES.put(key, "positive")
    assert fit._COVARIANCES.get((neg, 1.0))[0] is None
    assert fit._COVARIANCES.get((zeros.copy(), 1.0))[0] == "positive"
    assert fit._COVARIANCES.get((np.asfortranarray(zeros), 1.0))[0] is None
    assert fit._COVARIANCES.get((zeros, 1))[0] is None
    assert fit._COVARIANCES.get((zeros, 2.0))[0] is None
    zeros[0, 0] = 1.0   # the stored key is a copy: writing to the array changes nothing
    assert fit._COVARIANCES.get((np.zeros((10, 2)), 1.0))[0] == "positive"
    assert fit._COVARIANCES.get((zeros, 1.0))[0] is None
    assert not np.array_equal(parameter_covariance(jac, r, 2, 2e-2), base)
