"""The meta-model library (paper Table 1): evaluation, separable form, coordinates, rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.twin.discovery.metamodels import (
    META_MODELS,
    TABLE_1,
    get_meta_model,
    working_conditions,
)

WORKING_CONDITIONS = working_conditions()

# One parameter set per kind, with the input range each is used on (z > 0 for power/log).
CASES = {
    "linear": ([0.7, -1.5], np.linspace(-2, 3, 50)),
    "exponential": ([2.0, 1.3], np.linspace(0, 4, 50)),
    "negative_exponential": ([-3.0, 0.8], np.linspace(0, 4, 50)),
    "power": ([1.5, 0.5], np.linspace(0.1, 9, 50)),
    "logarithmic": ([2.0, 0.3], np.linspace(0.1, 9, 50)),
    "periodic": ([5.0, 10.0, 0.4, 0.2], np.linspace(0, 2, 200)),
    "rectifier": ([0.8, 1.2, -0.3], np.linspace(-2, 3, 51)),
    "dead_zone": ([1.5, 0.7], np.linspace(-2, 3, 51)),
    "coulomb": ([-2.5, 0.4], np.linspace(-2, 3, 51)),
    "saturation": ([3.0, 0.6], np.linspace(-2, 3, 51)),
    "input_dead_zone": ([-1.486, 0.7], np.linspace(-2, 3, 51)),
}
EXPECTED = {
    "linear": lambda p, z: p[0] * z + p[1],
    "exponential": lambda p, z: p[0] * p[1] ** z,
    "negative_exponential": lambda p, z: p[0] * np.exp(-p[1] * z),
    "power": lambda p, z: p[0] * z ** p[1],
    "logarithmic": lambda p, z: p[0] * np.log(z) + p[1],
    "periodic": lambda p, z: p[0] * np.sin(p[1] * z + p[2]) + p[3],
    "rectifier": lambda p, z: np.where(z > p[1], p[0] * (z - p[1]), 0.0) + p[2],
    "dead_zone": lambda p, z: np.where(z > p[1], p[0] * (z - p[1]),
                                       np.where(z < -p[1], p[0] * (z + p[1]), 0.0)),
    "coulomb": lambda p, z: np.where(z > 0, p[0], np.where(z < 0, -p[0], 0.0)) + p[1],
    "saturation": lambda p, z: p[0] * np.tanh(z / p[1]),
    "input_dead_zone": lambda p, z: p[0] * np.where(z > p[1], p[1], np.where(z < -p[1], -p[1],
                                                                             z)),
}
#: Paper Table 1, in its order; the rest of the library is what real drives need (issue 9).
PAPER_TABLE_1 = ("linear", "exponential", "negative_exponential", "power", "logarithmic",
                 "periodic")


def test_the_library_is_table_1_and_the_terms_real_drives_need() -> None:
    assert TABLE_1 == PAPER_TABLE_1  # the default candidates stay the paper's six
    assert set(META_MODELS) == set(EXPECTED) == set(WORKING_CONDITIONS)
    assert "one way only" in get_meta_model("rectifier").meaning
    assert "backlash" in get_meta_model("dead_zone").meaning
    assert "Coulomb" in get_meta_model("coulomb").meaning
    assert "current limiting" in get_meta_model("saturation").meaning
    assert "no voltage while |Va| <= b" in get_meta_model("input_dead_zone").meaning
    for kind in set(EXPECTED) - set(TABLE_1):  # separable: at most one nonlinear parameter
        assert len(get_meta_model(kind).nonlinear) <= 1
    assert "unbalanced shaft" in get_meta_model("periodic").meaning
    assert "leaking" in get_meta_model("exponential").meaning
    with pytest.raises(ValueError, match="unknown meta-model 'cubic'; known: coulomb, dead_zone"):
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


@pytest.mark.parametrize(("kind", "p", "flipped"), [
    ("saturation", [3.0, 0.6], [-3.0, -0.6]),   # a tanh(z/b) = -a tanh(-z/b)
    ("dead_zone", [1.5, 0.7], [1.5, -0.7]),     # the band is symmetric
    ("input_dead_zone", [-1.5, 0.7], [-1.5, -0.7]),
])
def test_new_kinds_equivalent_forms_are_canonical(kind: str, p: list[float],
                                                  flipped: list[float]) -> None:
    m = get_meta_model(kind)
    z = np.linspace(-2, 3, 51)
    q = m.canonical(np.array(flipped))
    np.testing.assert_allclose(q, p)
    np.testing.assert_allclose(m.evaluate(q, z)[0], m.evaluate(np.array(flipped), z)[0])


@pytest.mark.parametrize("kind", ["periodic", "linear", "exponential", "negative_exponential",
                                  "rectifier"])
def test_move_origin_rewrites_the_same_function_of_time(kind: str) -> None:
    """U_q(z - d) = U_p(z): a kept time term is refined in the current window's coordinates."""
    p, _ = CASES[kind]
    m = get_meta_model(kind)
    z = np.linspace(0.0, 4.0, 100)
    d = 1.7
    q = m.move_origin(np.array(p), d)
    assert q is not None
    np.testing.assert_allclose(m.evaluate(q, z - d)[0], m.evaluate(p, z)[0], rtol=1e-10,
                               atol=1e-12)
    back = m.move_origin(q, -d)
    np.testing.assert_allclose(back, p, rtol=1e-12, atol=1e-12)
    # kinds whose origin cannot move say so
    assert get_meta_model("dead_zone").move_origin(np.array([1.0, 0.5]), d) is None


def test_periodic_align_unwraps_the_phase_towards_a_reference() -> None:
    m = get_meta_model("periodic")
    ref = np.array([5.0, 10.0, 3.0, 0.0])
    q = m.align(np.array([5.0, 10.0, -3.1, 0.0]), ref)  # -3.1 is 3.18 one turn later
    assert q[2] == pytest.approx(-3.1 + 2 * math.pi)
    z = np.linspace(0, 2, 50)
    np.testing.assert_allclose(m.evaluate(q, z)[0], m.evaluate([5.0, 10.0, -3.1, 0.0], z)[0],
                               atol=1e-12)


def test_rendering_of_the_terms_real_drives_need() -> None:
    assert get_meta_model("rectifier").render(np.array([0.5, 3.2, 0.1]), "Va") == \
        "0.50*max(0, Va - 3.20) + 0.10"
    assert get_meta_model("rectifier").render(np.array([-2.0, -1.0, 0.0]), "omega") == \
        "-2.00*max(0, omega + 1.00)"
    assert get_meta_model("dead_zone").render(np.array([2.0, 0.3]), "Va") == "2.00*dz(Va, 0.30)"
    assert get_meta_model("coulomb").render(np.array([-12.5, 0.0]), "omega") == \
        "-12.50*sign(omega)"
    assert get_meta_model("saturation").render(np.array([3.0, 0.5]), "ia") == \
        "3.00*tanh(ia/0.50)"
    assert get_meta_model("input_dead_zone").render(np.array([-1.486, 2.0]), "Va") == \
        "-1.49*clip(Va, 2.00)"


def test_a_knee_lies_inside_the_data_and_a_sign_must_change() -> None:
    """A knee (a band) with every sample on one side is a line or a constant, and so is the
    sign of a speed that never reverses: such candidates are not searched."""
    u = np.linspace(-0.2, 1.0, 200)
    lo, hi = get_meta_model("rectifier").data_range(u)  # type: ignore[misc]
    assert -0.2 < lo < -0.1 and 0.9 < hi < 1.0
    assert get_meta_model("rectifier").identifiable(u)
    assert not get_meta_model("rectifier").identifiable(np.full(200, 0.3))
    lo, hi = get_meta_model("dead_zone").data_range(u)  # type: ignore[misc]
    assert lo == 0.0 and 0.9 < hi < 1.0
    coulomb = get_meta_model("coulomb")
    assert coulomb.identifiable(np.sin(np.linspace(0, 6, 200)))
    assert not coulomb.identifiable(np.linspace(0.1, 1.0, 200))       # never reverses
    start = np.concatenate([np.zeros(20), np.linspace(0.1, 1.0, 180)])  # from rest: friction
    assert coulomb.identifiable(start)                                # acts only once moving
    # the dead zone of an input: its band between the input's smallest and largest
    # magnitudes; an input that stays far from zero (every sample beyond any band) is b*sign
    clip = get_meta_model("input_dead_zone")
    assert clip.identifiable(u) and clip.data_range(u)[0] < 0.05  # type: ignore[index]
    assert not clip.identifiable(np.linspace(0.8, 1.0, 200))


def test_coulomb_sign_is_the_average_over_each_sample_interval() -> None:
    """At a reversal the plant's friction switches inside a sample interval while the twin
    holds one value: the held value is the interval's average of sign(omega), exact for a
    speed linear between samples."""
    from twinwatch.twin.discovery.metamodels.coulomb import sampled_sign

    t = np.arange(0.0, 1.0, 0.01)
    omega = 3.0 * (t - 0.4237)  # crosses zero inside the interval [0.42, 0.43)
    fine = np.linspace(0.0, 1.0, 100 * 1000, endpoint=False)
    exact = np.sign(3.0 * (fine - 0.4237)).reshape(100, 1000).mean(axis=1)
    mid = omega + 0.015  # the twin evaluates an additive term at mid-step
    np.testing.assert_allclose(sampled_sign(mid)[1:-1], exact[1:-1], atol=2e-3)
    assert sampled_sign(mid)[42] == pytest.approx(1 - 2 * 0.37, abs=2e-3)  # 37 % negative
    m = get_meta_model("coulomb")
    np.testing.assert_allclose(m.evaluate([-2.0, 0.5], mid)[0], -2.0 * sampled_sign(mid) + 0.5)
