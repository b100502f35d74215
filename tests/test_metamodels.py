"""The meta-model library (paper Table 1): evaluation, separable form, coordinates, rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.twin.metamodels import META_MODELS, TABLE_1, get_meta_model, working_conditions

WORKING_CONDITIONS = working_conditions()

# One parameter set per kind, with the input range each is used on (z > 0 for power/log).
CASES = {
    "linear": ([0.7, -1.5], np.linspace(-2, 3, 50)),
    "exponential": ([2.0, 1.3], np.linspace(0, 4, 50)),
    "negative_exponential": ([-3.0, 0.8], np.linspace(0, 4, 50)),
    "power": ([1.5, 0.5], np.linspace(0.1, 9, 50)),
    "logarithmic": ([2.0, 0.3], np.linspace(0.1, 9, 50)),
    "periodic": ([5.0, 10.0, 0.4, 0.2], np.linspace(0, 2, 200)),
}
EXPECTED = {
    "linear": lambda p, z: p[0] * z + p[1],
    "exponential": lambda p, z: p[0] * p[1] ** z,
    "negative_exponential": lambda p, z: p[0] * np.exp(-p[1] * z),
    "power": lambda p, z: p[0] * z ** p[1],
    "logarithmic": lambda p, z: p[0] * np.log(z) + p[1],
    "periodic": lambda p, z: p[0] * np.sin(p[1] * z + p[2]) + p[3],
}


def test_the_library_is_table_1() -> None:
    assert set(TABLE_1) == set(EXPECTED) and set(TABLE_1) <= set(META_MODELS)
    assert set(META_MODELS) == set(WORKING_CONDITIONS)
    assert "unbalanced shaft" in get_meta_model("periodic").meaning
    assert "leaking" in get_meta_model("exponential").meaning
    with pytest.raises(ValueError, match="unknown meta-model 'cubic'; choose from"):
        get_meta_model("cubic")


@pytest.mark.parametrize("kind", sorted(CASES))
def test_evaluate_matches_table_1(kind: str) -> None:
    p, z = CASES[kind]
    m = get_meta_model(kind)
    got = m.evaluate(np.array([p, p]), z)
    assert got.shape == (2, z.size)
    np.testing.assert_allclose(got[1], EXPECTED[kind](p, z), rtol=1e-12)


@pytest.mark.parametrize("kind", sorted(CASES))
def test_separable_form_reproduces_the_term(kind: str) -> None:
    """U = sum_j coef_j basis_j(z; nonlinear): the search solves the coefficients linearly."""
    p, z = CASES[kind]
    m = get_meta_model(kind)
    nl = np.array([p[m.params.index(n)] for n in m.nonlinear])
    basis = m.basis(nl[None, :], z)[0]
    if kind == "periodic":
        coef = np.array([p[0] * math.cos(p[2]), p[0] * math.sin(p[2]), p[3]])
    else:
        coef = np.array([p[m.params.index(c)] for c in m.columns])
    np.testing.assert_allclose(coef @ basis, EXPECTED[kind](p, z), rtol=1e-10, atol=1e-12)
    back = m.from_separable(nl, coef)
    np.testing.assert_allclose(m.evaluate(back, z)[0], EXPECTED[kind](p, z), rtol=1e-10)


@pytest.mark.parametrize("kind", sorted(CASES))
def test_normalised_and_raw_coordinates_agree(kind: str) -> None:
    p, z = CASES[kind]
    m = get_meta_model(kind)
    z_ref = 3.7
    p_norm = m.from_raw(np.array(p), z_ref)
    np.testing.assert_allclose(m.evaluate(p_norm, z / z_ref)[0], m.evaluate(p, z)[0],
                               rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(m.to_raw(p_norm, z_ref), p, rtol=1e-12)


def test_periodic_equivalent_forms_are_canonical() -> None:
    """a sin(bz + c) = -a sin(bz + c + pi) = a sin(-bz - c + pi): one representative."""
    m = get_meta_model("periodic")
    z = np.linspace(0, 3, 300)
    ref = m.evaluate([4.92, 9.98, 2.68, 0.0], z)[0]
    for p in ([-4.92, 9.98, 2.68 - math.pi, 0.0], [4.92, -9.98, math.pi - 2.68, 0.0],
              [-4.92, -9.98, -2.68, 0.0]):
        q = m.canonical(np.array(p))
        assert q[0] > 0 and q[1] > 0 and -math.pi < q[2] <= math.pi
        np.testing.assert_allclose(m.evaluate(q, z)[0], ref, atol=1e-12)
    # The paper's discovered form 4.92*sin(-9.98 t - 0.46) is the same kind of term.
    q = m.canonical(np.array([4.91985774, -9.97780433, -0.46427915, 0.0]))
    assert q[1] == pytest.approx(9.97780433)


@pytest.mark.parametrize("kind", ["periodic", "linear"])
def test_time_origin_shift_keeps_the_values(kind: str) -> None:
    p, _ = CASES[kind]
    m = get_meta_model(kind)
    t = np.linspace(160.0, 162.0, 100)
    q, t_ref = m.shift_origin(np.array(p), 160.0)
    assert t_ref == 0.0
    np.testing.assert_allclose(m.evaluate(q, t)[0], m.evaluate(p, t - 160.0)[0], atol=1e-9)


def test_rendering_is_a_readable_equation() -> None:
    per = get_meta_model("periodic")
    assert per.render(np.array([4.98, 10.0, 2.12, 0.0]), "t") == "4.98*sin(10.00*t + 2.12)"
    assert per.render(np.array([4.98, 10.0, -2.12, 0.5]), "t") == \
        "4.98*sin(10.00*t - 2.12) + 0.50"
    lin = get_meta_model("linear")
    assert lin.render(np.array([0.0, 0.2]), "t", 4) == "0.2000"
    assert lin.render(np.array([-0.3, 1.5]), "omega") == "-0.30*omega + 1.50"
    assert get_meta_model("negative_exponential").render(np.array([2.0, 0.003]), "t") == \
        "2.00*exp(-0.0030*t)"
    assert get_meta_model("logarithmic").render(np.array([1.0, 0.0]), "ia") == "1.00*ln(ia)"
