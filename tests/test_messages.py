"""The words of jaxnh's messages about a user's mistakes: each names the argument or function at
fault, what came and what was expected. And how a status reads: its repr, `help(jaxnh.STATUS)`, and
testing a batch's status under `jax.vmap`."""

import pydoc
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnh as nh
from jaxnh.models import variator as V


TS = jnp.linspace(0.0, 0.5, 6)


def T3(q, qd, t, p):
    return 0.5 * (qd[0] ** 2 + 2.0 * qd[1] ** 2 + 3.0 * qd[2] ** 2)


def c3(q, qd, t, p):
    return jnp.stack([qd[0] - qd[1]])


def raises(pattern, mech, q0, qd0, params=None):
    with pytest.raises(ValueError, match=pattern) as info:
        nh.simulate(mech, {} if params is None else params, q0, qd0, TS)
    return str(info.value)


# --- case 1: q0 and qd0 against each other and against the mechanism ----------------------------


def test_a_short_q0_is_blamed_on_q0_when_names_are_given():
    mech = nh.Mechanism(T3, constraints=c3, names=("x", "y", "z"))
    msg = raises(r"the coordinates q0 have shape \(2,\)", mech, jnp.zeros(2), jnp.ones(3))
    assert "s = 3 coordinates" in msg and "names=('x', 'y', 'z')" in msg
    assert "expected q0 of shape (3,)" in msg and "qd0 has shape (3,), which agrees" in msg
    assert "qd must have the shape of q" not in msg  # the old message blamed qd


def test_a_short_qd0_is_blamed_on_qd0_when_names_are_given():
    mech = nh.Mechanism(T3, constraints=c3, names=("x", "y", "z"))
    msg = raises(r"the velocities qd0 have shape \(2,\)", mech, jnp.zeros(3), jnp.ones(2))
    assert "(3,)" in msg and "q0 has shape (3,), which agrees" in msg


def test_both_short_against_names():
    mech = nh.Mechanism(T3, constraints=c3, names=("x", "y", "z"))
    msg = raises(r"q0 and qd0 have shapes \(2,\) and \(2,\)", mech, jnp.zeros(2), jnp.ones(2))
    assert "s = 3 coordinates" in msg and "`names`" in msg


def test_without_names_the_functions_tell_which_is_wrong():
    """T indexes qd[2]: JAX clamps an index past the end silently, so the check looks for it."""
    mech = nh.Mechanism(T3, constraints=c3)
    msg = raises(r"the coordinates q0 have shape \(2,\), but the mechanism has s = 3", mech, jnp.zeros(2), jnp.ones(3))
    assert "expected q0 of shape (3,)" in msg
    msg = raises(r"the velocities qd0 have shape \(2,\)", mech, jnp.zeros(3), jnp.ones(2))
    assert "expected qd0 of shape (3,)" in msg


def test_without_names_forces_tell_which_is_wrong():
    mech = nh.Mechanism(V.kinetic, constraints=V.constraint, forces=V.torques)
    msg = raises(r"the velocities qd0 have shape \(3,\)", mech, jnp.zeros(2), jnp.ones(3), V.default_params())
    assert "expected qd0 of shape (2,)" in msg


def test_undecidable_lengths_say_both():
    def T(q, qd, t, p):
        return 0.5 * jnp.sum(qd**2)

    msg = raises(r"q0 has shape \(2,\) and qd0 shape \(3,\)", nh.Mechanism(T), jnp.zeros(2), jnp.ones(3))
    assert "names=" in msg  # how to get a sharper message


def test_a_batch_of_states_points_to_vmap():
    mech = nh.Mechanism(T3, constraints=c3)
    msg = raises(r"q0 must be a vector of the coordinates", mech, jnp.zeros((4, 3)), jnp.ones(3))
    assert "got shape (4, 3)" in msg and "jax.vmap" in msg


# --- case 2: what a user function returned, and what it must return ------------------------------


@pytest.mark.parametrize(
    "field,fn,words",
    [
        (
            "constraints",
            lambda q, qd, t, p: [qd[0] - qd[1]],
            r"`constraints` must return a vector of shape \(m,\); got a Python list of 1 item, not a JAX array"
            r"(.|\n)*jnp\.stack",
        ),
        (
            "constraints",
            lambda q, qd, t, p: qd[0] - qd[1],
            r"`constraints` must return a vector of shape \(m,\); got shape \(\) \(a scalar\)(.|\n)*jnp\.stack",
        ),
        (
            "forces",
            lambda q, qd, t, p: [1.0, 0.0, 0.0],
            r"`forces` must return shape \(3,\); got a Python list of 3 items, not a JAX array(.|\n)*jnp\.stack",
        ),
        (
            "forces",
            lambda q, qd, t, p: (jnp.zeros(2), 0.0),
            r"`forces` must return shape \(3,\); got a Python tuple of 2 items",
        ),
        ("potential", lambda q, t, p: None, r"`potential` must return a scalar; got None \(does the function end"),
        ("potential", lambda q, t, p: q, r"`potential` must return a scalar; got shape \(3,\)(.|\n)*shape \(\)"),
        (
            "holonomic",
            lambda q, t, p: [q[0] - 1.0],
            r"`holonomic` must return a vector of shape \(h,\); got a Python list of 1 item(.|\n)*jnp\.stack",
        ),
        (
            "acceleration_energy",
            lambda q, qd, qdd, t, p: [qdd[0]],
            r"`acceleration_energy` must return a scalar; got a Python list of 1 item",
        ),
    ],
)
def test_a_function_returning_the_wrong_thing_is_named_with_what_it_returned(field, fn, words):
    mech = nh.Mechanism(T3, **{field: fn})
    q0 = jnp.array([1.0, 0.0, 0.0])
    msg = raises(words, mech, q0, jnp.zeros(3))
    assert "None" not in msg or field == "potential"  # never "got shape None"


@pytest.mark.parametrize(
    "T,words",
    [
        (lambda q, qd, t, p: 0.5 * qd**2, r"`kinetic` must return a scalar; got shape \(3,\)(.|\n)*jnp\.sum"),
        (lambda q, qd, t, p: [0.5 * qd[0] ** 2], r"`kinetic` must return a scalar; got a Python list of 1 item"),
    ],
)
def test_kinetic_energy_not_a_scalar(T, words):
    raises(words, nh.Mechanism(T), jnp.zeros(3), jnp.ones(3))


# --- cases 3 and 4: how a status reads, alone and in a batch ------------------------------------


def test_status_repr_is_not_empty():
    assert repr(nh.STATUS.successful) == "jaxnh.STATUS<successful>"
    assert repr(nh.STATUS.max_steps_reached).startswith("jaxnh.STATUS<The maximum number of solver steps")
    assert nh.STATUS[nh.STATUS.successful] == "successful"  # the public lookup agrees with the repr


def test_help_lists_every_member_with_its_message():
    doc = pydoc.render_doc(nh.STATUS, renderer=pydoc.plaintext)  # pyright: ignore[reportAttributeAccessIssue] (untyped in typeshed)
    for name in ("successful", "max_steps_reached", "non_finite_input", "inconsistent_velocities", "stiff"):
        assert f"`{name}`" in doc, name
    assert "`non_finite_input`: The initial state (q0, qd0)" in doc
    assert "sol.status == STATUS.successful" in doc  # how to test one, or a batch


def test_batch_status_is_tested_by_comparison():
    """Under vmap the status is one item holding the batch: `==` gives a boolean array of its shape,
    while np.asarray of the item is a 0-dimensional object array (the reported trap)."""
    mech, p = V.mechanism(), V.default_params()
    qd0 = jnp.array([2.0, float(p.U21(0.0)) * 2.0])

    def one(J1):
        return nh.simulate(mech, V.VariatorParams(J1, p.J2, p.U21, p.M1, p.M2), jnp.zeros(2), qd0, TS, throw=False)

    sol = jax.vmap(one)(jnp.array([0.02, -0.02, 0.03, 0.04]))
    assert np.asarray(sol.status).shape == ()  # not the batch: compare instead
    ok = sol.status == nh.STATUS.successful
    assert ok.shape == (4,) and ok.tolist() == [True, False, True, True]
    assert np.asarray(sol.success).tolist() == [True, False, True, True]
    bad = sol.status == nh.STATUS.mass_matrix_not_positive_definite
    assert bad.tolist() == [False, True, False, False]
    assert re.match(r"1 of 4 failed: 3 × success; 1 × solve failed: The mass matrix", sol.message)
    assert sol.messages[1].startswith("solve failed: The mass matrix") and sol.messages[0] == "success"
