"""The trunk controller's friction-constrained weight distribution (control/trunk.py) against SciPy's SLSQP."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize as so

from hyqjax.control import trunk


@pytest.fixture(autouse=True)
def _x64():
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", False)


def _instance(rng, swing=True):
    r = np.c_[np.array([[.37, .2], [.37, -.2], [-.37, .2], [-.37, -.2]]) + rng.uniform(-.1, .1, (4, 2)),
              rng.uniform(-.7, -.4, 4)]
    st = np.ones(4)
    if swing:
        st[rng.integers(4)] = 0.0
    force = np.array([rng.normal(0, 150), rng.normal(0, 150), 830 + rng.normal(0, 100)])
    return r, st, force, rng.normal(0, 60, 3), rng.uniform(0.3, 1.0)


def _slsqp(r, st, force, torque, mu):
    """The same QP (module docstring) in float64 by SLSQP, in the solver's normalised units."""
    a = np.asarray(trunk.wrench_matrix(jnp.asarray(r)))
    s = np.r_[np.ones(3), np.full(3, 1 / trunk.L_MOMENT**2)]
    sc = np.linalg.norm(force)
    b = np.r_[force, torque] / sc
    p = a.T @ (s[:, None] * a) + trunk.REGULARISATION * np.eye(12)
    q = -a.T @ (s * b)
    c, lo, hi, _ = [np.asarray(x) for x in trunk.friction_constraints(jnp.asarray(st), mu, jnp.array([0., 0., 1.]))]
    cons = [dict(type="ineq", fun=lambda x, k=k: c[k] @ x - lo[k], jac=lambda x, k=k: c[k]) for k in range(20)
            if np.isfinite(lo[k])]
    cons += [dict(type="ineq", fun=lambda x, k=k: hi[k] - c[k] @ x, jac=lambda x, k=k: -c[k]) for k in range(20)
             if np.isfinite(hi[k])]
    res = so.minimize(lambda x: 0.5 * x @ p @ x + q @ x, np.zeros(12), jac=lambda x: p @ x + q, constraints=cons,
                      method="SLSQP", options=dict(ftol=1e-14, maxiter=500))
    assert res.success
    return res.x.reshape(4, 3) * sc, (p, q, sc)


@pytest.mark.slow
def test_qp_matches_slsqp_on_random_instances():
    rng = np.random.default_rng(0)
    solve = jax.jit(trunk.solve_wrench_qp)
    errs, gaps = [], []
    for i in range(30):
        r, st, force, torque, mu = _instance(rng, swing=i % 2 == 1)
        f_ref, (p, q, sc) = _slsqp(r, st, force, torque, mu)
        f = np.asarray(solve(jnp.asarray(r), jnp.asarray(st), jnp.asarray(force), jnp.asarray(torque), mu))
        errs.append(np.abs(f - f_ref).max())
        x, x_ref = f.reshape(-1) / sc, f_ref.reshape(-1) / sc
        gaps.append((0.5 * x @ p @ x + q @ x) - (0.5 * x_ref @ p @ x_ref + q @ x_ref))
        # Feasible: unilateral, inside the pyramid, swing leg carries nothing.
        fn = f[:, 2]
        assert np.all(fn >= -1e-9)
        assert np.all(np.abs(f[:, :2]) <= mu / np.sqrt(2) * fn[:, None] + 1e-6)
        assert np.all(f[st == 0] == 0.0)
    assert max(errs) < 2.0, errs  # N, against forces of 200-400 N
    assert max(gaps) < 1e-5, gaps


def test_qp_meets_the_wrench_where_clipping_the_least_norm_solution_does_not():
    """Low friction and a large lateral force: the least-norm forces leave the cones; clipping them loses part of
    the wrench, the QP redistributes and meets more of it."""
    rng = np.random.default_rng(1)
    better = 0
    clip = jax.jit(lambda a, st, b, mu: trunk.project_to_cones(trunk.least_norm_forces(a, st, b).reshape(4, 3), mu,
                                                               jnp.array([0., 0., 1.])))
    solve = jax.jit(trunk.solve_wrench_qp)
    for _ in range(20):
        r, st, force, torque, _ = _instance(rng)
        force = force + np.array([0.0, 200.0, 0.0])
        mu = 0.4
        a = trunk.wrench_matrix(jnp.asarray(r))
        b = jnp.asarray(np.r_[force, torque])
        f_clip = clip(a, jnp.asarray(st), b, mu)
        f_qp = solve(jnp.asarray(r), jnp.asarray(st), jnp.asarray(force), jnp.asarray(torque), mu)
        s = np.r_[np.ones(3), np.full(3, 1 / trunk.L_MOMENT)]
        e_clip = np.linalg.norm(s * (np.asarray(a @ f_clip.reshape(-1)) - np.asarray(b)))
        e_qp = np.linalg.norm(s * (np.asarray(a @ f_qp.reshape(-1)) - np.asarray(b)))
        assert e_qp <= e_clip + 0.01 * np.linalg.norm(force)  # the regulariser costs < 1% of the wrench
        better += e_qp < 0.5 * e_clip
    assert better >= 10


@pytest.mark.slow
def test_qp_is_exact_when_the_cones_are_inactive():
    """CoM moved 7 cm into the support triangle of LF, RF, LH (as a body phase does): the weight is met within
    the regulariser's bias (< 1% of the weight, the tie-break toward small forces)."""
    r = np.array([[.37, .2, -.56], [.37, -.2, -.56], [-.37, .2, -.56], [-.37, -.2, -.56]]) - np.array([.05, .05, 0.])
    weight = 84.756 * 9.81
    f = trunk.distribute_weight(jnp.asarray(r), jnp.array([1., 1., 1., 0.]), 84.756, 0.7)
    a = trunk.wrench_matrix(jnp.asarray(r))
    w = np.asarray(a @ f.reshape(-1))
    np.testing.assert_allclose(w[:3], [0, 0, weight], atol=0.01 * weight)
    np.testing.assert_allclose(w[3:], 0.0, atol=0.01 * weight * trunk.L_MOMENT)
    assert float(f[3].sum()) == 0.0


@pytest.mark.slow
def test_qp_forward_and_reverse_derivatives_match_finite_differences():
    rng = np.random.default_rng(2)
    r, st, force, torque, mu = _instance(rng)

    def g(x):  # the forces as a function of (force, torque, mu)
        return trunk.solve_wrench_qp(jnp.asarray(r), jnp.asarray(st), x[:3], x[3:6], x[6]).reshape(-1)

    x0 = jnp.asarray(np.r_[force, torque, mu])
    jf = np.asarray(jax.jit(jax.jacfwd(g))(x0))
    jr = np.asarray(jax.jit(jax.jacrev(g))(x0))
    eps = 1e-4
    steps = eps * np.eye(7)
    gs = np.asarray(jax.jit(jax.vmap(g))(jnp.concatenate([x0 + steps, x0 - steps])))  # (14, 12)
    fd = ((gs[:7] - gs[7:]) / (2 * eps)).T
    np.testing.assert_allclose(jf, jr, atol=1e-8)
    assert np.abs(jf - fd).max() < 1e-3 * max(1.0, np.abs(fd).max())
    # vmap over instances equals the per-instance solve.
    xs = jnp.stack([x0, x0 * 1.1])
    np.testing.assert_allclose(np.asarray(jax.vmap(g)(xs))[1], np.asarray(g(xs[1])), atol=1e-9)
