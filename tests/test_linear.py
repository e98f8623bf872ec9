"""Continuous-time linear blocks: exact discretisation vs scipy, analytic responses, robustness, derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal as ss
from hypothesis import given, settings, strategies as st

import piezojax as pj

# -- helpers --------------------------------------------------------------------------------------------------------


def random_stable_poles(rng, order):
    """Random stable poles: complex pairs and real poles with magnitudes 0.3..30 rad/s, damping 0.05..0.9."""
    n2 = int(rng.integers(0, order // 2 + 1))
    n1 = order - 2 * n2
    omega = np.exp(rng.uniform(np.log(0.3), np.log(30.0), n2))
    zeta = rng.uniform(0.05, 0.9, n2)
    poles = -np.exp(rng.uniform(np.log(0.3), np.log(30.0), n1))
    return omega, zeta, poles


def rel_err(y, ref):
    y, ref = np.asarray(y), np.asarray(ref)
    return np.max(np.abs(y - ref)) / np.max(np.abs(ref))


def lsim(num, den, u, dt, hold, x0=None):
    t = np.arange(len(u)) * dt
    system = (np.asarray(num), np.asarray(den)) if x0 is None else num
    return ss.lsim(system, np.asarray(u), t, X0=x0, interp=(hold == "foh"))[1]


def polyprod(factors):
    out = np.array([1.0])
    for f in factors:
        out = np.polymul(out, f)
    return out


def random_systems(seed=0):
    """(order, StableTransferFunction with zeros, TransferFunction, StateSpace) for orders 1..6."""
    rng = np.random.default_rng(seed)
    out = []
    for order in range(1, 7):
        omega, zeta, poles = random_stable_poles(rng, order)
        n_zeros = int(rng.integers(0, order + 1))
        n2z = min(len(omega), n_zeros // 2) if rng.uniform() < 0.5 else 0
        n1z = min(n_zeros - 2 * n2z, len(poles) + 2 * (len(omega) - n2z))
        zeros = rng.uniform(-5, 5, n1z)
        zero_omega = np.exp(rng.uniform(np.log(0.3), np.log(30.0), n2z))
        zero_zeta = rng.uniform(-0.5, 0.9, n2z)
        gain = rng.uniform(0.5, 2.0)
        G = pj.StableTransferFunction(gain, omega, zeta, poles, zeros=zeros, zero_omega=zero_omega, zero_zeta=zero_zeta)
        # the same transfer function with numpy polynomials (the reference)
        den = polyprod([[1.0, 2 * z * w, w * w] for w, z in zip(omega, zeta)] + [[1.0, -p] for p in poles])
        N = polyprod([[1.0, 2 * z * w, w * w] for w, z in zip(zero_omega, zero_zeta)] + [[1.0, -z] for z in zeros])
        num = gain * N * den[-1] / N[-1]
        out.append((order, G, num, den))
    return out


SYSTEMS = random_systems()


@eqx.filter_jit
def sim(model, u, dt, hold="zoh", x0=None):
    """Jitted `simulate` with the model as an argument: one compile per model structure, shape and hold."""
    return model.simulate(u, dt, x0, hold)


@eqx.filter_jit
def scan(model, u, dt, hold="zoh", state=None):
    return model.scan(u, dt, state, hold)


@eqx.filter_jit
def sim_batch(model, u, dt, hold="zoh"):
    return jax.vmap(lambda x: model.simulate(x, dt, hold=hold))(u)


# -- against scipy ----------------------------------------------------------------------------------------------


def padded_realisation(model, n=6):
    """The model's own realisation, padded to n states with decoupled states (B = C = 0): same transfer function.

    Lets one compiled simulation serve every order and class (compile time dominates this file).
    """
    A, B, C, D = model.state_space()
    k = A.shape[0]
    Ap = (-jnp.eye(n, dtype=A.dtype)).at[:k, :k].set(A)
    return Ap, jnp.pad(B, (0, n - k)), jnp.pad(C, (0, n - k)), D


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_random_systems_match_scipy(hold):
    """Orders 1-6, random stable poles and zeros, each as StableTransferFunction, TransferFunction and StateSpace
    (scipy's tf2ss realisation): step and random-input responses equal scipy's lsim to 1e-9 relative."""
    dt = 0.02
    u = np.stack([np.random.default_rng(7).normal(size=400), np.ones(400)])  # random input and step
    models, refs = [], []
    for order, G, num, den in SYSTEMS:
        tf = pj.TransferFunction(num, den)
        ss_sys = pj.StateSpace(*ss.tf2ss(num, den))  # scipy's (n, 1), (1, n), (1, 1) shapes
        assert G.order == tf.order == ss_sys.order == order
        models += [G, tf, ss_sys]
        refs += [[lsim(num, den, u[i], dt, hold) for i in range(2)]] * 3
    y = _sim_models(models, jnp.asarray(u), dt, hold)
    for j, ref in enumerate(refs):
        for i in range(2):
            assert rel_err(y[j, i], ref[i]) < 1e-9, (j // 3 + 1, ["stable", "tf", "ss"][j % 3], i)


@eqx.filter_jit
def _sim_models(models, u, dt, hold):
    """Each model's realisation (built in this one trace), padded and simulated by one vmapped simulation."""
    A, B, C, D = (jnp.stack(x) for x in zip(*(padded_realisation(m) for m in models)))
    one = lambda a, b, c, d: jax.vmap(lambda x: pj.StateSpace(a, b, c, d).simulate(x, dt, hold=hold))(u)  # noqa: E731
    return jax.vmap(one)(A, B, C, D)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_discretise_matches_cont2discrete(hold):
    """`discretise` gives scipy's cont2discrete matrices (same realisation), for both holds."""
    A = np.array([[-1.0, 2.0, 0.0], [-3.0, -0.5, 1.0], [0.0, 0.3, -2.0]])
    B, C, D = np.array([1.0, 0.5, -1.0]), np.array([0.3, -1.0, 2.0]), 0.7
    d = eqx.filter_jit(lambda m: m.discretise(0.1, hold))(pj.StateSpace(A, B, C, D))
    Ad, Bd, Cd, Dd, _ = ss.cont2discrete((A, B[:, None], C[None, :], np.array([[D]])), 0.1, method=hold)
    np.testing.assert_allclose(d.Ad, Ad, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(d.Bd, Bd[:, 0], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(d.Cd, Cd[0], rtol=1e-12)
    np.testing.assert_allclose(d.Dd, Dd[0, 0], rtol=1e-12)
    np.testing.assert_allclose(d.delta, Ad - np.eye(3), rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_initial_state_matches_lsim(hold):
    """A given initial state (StateSpace realisation) matches lsim's X0."""
    A = np.array([[0.0, 1.0], [-4.0, -0.4]])
    B, C = np.array([0.0, 1.0]), np.array([1.0, 0.2])
    x0 = np.array([0.5, -1.0])
    u = np.sin(np.arange(300) * 0.05)
    ref = ss.lsim((A, B[:, None], C[None, :], np.zeros((1, 1))), u, np.arange(300) * 0.05, X0=x0, interp=hold == "foh")
    y = sim(pj.StateSpace(A, B, C, 0.0), u, 0.05, hold, x0)
    assert rel_err(y, ref[1]) < 1e-10


@pytest.mark.parametrize("hold", ["foh"])
def test_chunked_scan_continues_exactly(hold):
    """`scan` returns a state that continues a record exactly (FOH: the state is x - Gamma1 u; ZOH is trivial)."""
    G = SYSTEMS[4][1]
    u = np.random.default_rng(1).normal(size=300)
    full = sim(G, u, 0.02, hold)
    state, y1 = scan(G, u[:150], 0.02, hold)
    _, y2 = scan(G, u[150:], 0.02, hold, state)
    np.testing.assert_allclose(np.concatenate([y1, y2]), full, rtol=1e-12, atol=1e-14)


def test_frequency_response_and_dc_gain_match_scipy():
    order, G, num, den = SYSTEMS[5]
    w = np.logspace(-2, 2, 50)
    ref = ss.freqs(num, den, w)[1]
    for model in (G, pj.TransferFunction(num, den)):
        response, dc = eqx.filter_jit(lambda m: (m.frequency_response(w), m.dc_gain()))(model)
        np.testing.assert_allclose(response, ref, rtol=1e-10)
        np.testing.assert_allclose(dc, num[-1] / den[-1], rtol=1e-12)
    np.testing.assert_allclose(G.dc_gain(), G.gain, rtol=1e-12)  # dc_normalised


def test_realisation_and_state_derivatives_with_respect_to_den_match_finite_differences():
    r"""The companion realisation is scaled by $w = \max_j |a_j|^{1/j}$: its matrices, and a state scanned with them,
    depend on `den` through $w$ too (the output does not). Their derivatives match central differences, and a zero
    coefficient gives a finite derivative (not 0 * inf)."""
    num = jnp.array([2e4, 1e7])

    def realisation(a2):
        return pj.TransferFunction(num, jnp.array([1.0, 300.0, a2, 1e7])).state_space()[0][0, 1]

    def state(a2):
        return pj.TransferFunction(num, jnp.array([1.0, 300.0, a2, 1e7])).scan(jnp.ones(50), 1e-3)[0][0]

    for f in (realisation, state):
        fd = (f(4e5 + 1.0) - f(4e5 - 1.0)) / 2.0
        np.testing.assert_allclose(jax.grad(f)(4e5), fd, rtol=1e-6)
        np.testing.assert_allclose(jax.jacfwd(f)(4e5), fd, rtol=1e-6)

    def with_zero(a1):
        return jnp.sum(pj.TransferFunction([1.0], jnp.stack([1.0, a1, 100.0])).state_space()[0])

    for d in (jax.grad(with_zero)(0.0), jax.jacfwd(with_zero)(0.0)):
        np.testing.assert_allclose(d, (with_zero(1e-6) - with_zero(-1e-6)) / 2e-6, rtol=1e-6)


# -- analytic -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_first_order_step_is_analytic(hold):
    tau, dt = 1e-3, 1e-5
    t = np.arange(1000) * dt
    y = sim(pj.TransferFunction([1.0], [tau, 1.0]), np.ones(1000), dt, hold)
    # both holds see u = 1 from t_0 on (the system is at rest before)
    np.testing.assert_allclose(y, 1 - np.exp(-t / tau), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_ramp_response_foh_exact_zoh_lagged(hold):
    """A sampled ramp: FOH reproduces the continuous ramp response of 1/(tau s + 1) exactly; ZOH is a staircase."""
    tau, dt = 0.01, 1e-3
    t = np.arange(200) * dt
    y = sim(pj.StableTransferFunction(1.0, poles=[-1 / tau]), t, dt, hold)
    exact = t - tau * (1 - np.exp(-t / tau))
    if hold == "foh":
        np.testing.assert_allclose(y, exact, rtol=1e-11, atol=1e-15)
    else:  # periodic steady state of the lag behind the ramp: dt / (1 - exp(-dt / tau)) - tau (about dt / 2)
        np.testing.assert_allclose(exact[-1] - y[-1], dt / (1 - np.exp(-dt / tau)) - tau, rtol=1e-8)


def resonance_creep_step(t, w, z, a, zero):
    """Analytic step response of w^2 a (s - zero)/(-zero) / ((s^2 + 2 z w s + w^2)(s + a)) (distinct poles)."""
    pc = -z * w + 1j * w * np.sqrt(1 - z * z)
    poles = np.array([-a, pc, np.conj(pc)])
    gain = w * w * a / (-zero)
    y = np.full(t.shape, 1.0 + 0j)
    for i, p in enumerate(poles):
        r = gain * (p - zero) / np.prod([p - q for j, q in enumerate(poles) if j != i])
        y += r / p * np.exp(p * t)
    return y.real


@pytest.mark.parametrize("with_zero", [False, True])
def test_lightly_damped_resonance_with_creep_pole_over_1e6_samples(with_zero):
    """zeta = 0.01 at 2 pi 500 rad/s in series with a creep pole at 1e-4 rad/s, 1e6 samples at dt = 1e-4."""
    w, z, a, dt, n = 2 * np.pi * 500, 0.01, 1e-4, 1e-4, 10**6
    zero = -1.5 * a if with_zero else -np.inf
    t = np.arange(n) * dt
    if with_zero:
        G = pj.StableTransferFunction(1.0, [w], [z], [-a], zeros=[zero])
        ref = resonance_creep_step(t, w, z, a, zero)
    else:
        G = pj.StableTransferFunction(1.0, [w], [z], [-a])
        ref = resonance_creep_step(t, w, z, a, -1e300)  # (s - zero)/(-zero) -> 1
    y = jax.jit(lambda u: G.simulate(u, dt))(jnp.ones(n))
    assert rel_err(y, ref) < 1e-11
    # the same polynomial through the frequency-scaled companion form
    y_tf = jax.jit(lambda u: G.to_tf().simulate(u, dt))(jnp.ones(n))
    assert rel_err(y_tf, ref) < 1e-9


def test_butterworth_matches_scipy():
    for order in range(1, 9):
        for cutoff in (1.0,) if order != 3 else (1.0, 2 * np.pi * 100.0):
            b, a = ss.butter(order, cutoff, analog=True)
            num, den = pj.butterworth(order, cutoff).transfer_function()
            np.testing.assert_allclose(den, a, rtol=1e-13)
            np.testing.assert_allclose(num[-1], b[-1], rtol=1e-13)
            np.testing.assert_allclose(num[:-1], 0.0)
    lp = pj.butterworth(3, 2 * np.pi * 100.0)
    np.testing.assert_allclose(abs(lp.frequency_response(np.array([2 * np.pi * 100.0]))) ** 2, 0.5, rtol=1e-12)


def _butterworth_step_response(order, z, n):
    """The analog Butterworth's unit-step response at t = k/w_c * z, in closed form: 1 + sum_k r_k/q_k e^{q_k z k}
    (ZOH of a step is exact: these are the samples of the held-input simulation)."""
    q = np.exp(1j * np.pi * (2 * np.arange(1, order + 1) + order - 1) / (2 * order))
    r = np.array([1 / np.prod([q[k] - q[j] for j in range(order) if j != k]) for k in range(order)])
    return 1 + np.real(np.exp(np.outer(np.arange(n) * z, q)) @ (r / q))


def test_butterworth_modal_form_matches_the_step_response_scipy_and_the_cascade():
    from piezojax._linear.butterworth import butterworth_zoh

    bw = jax.jit(butterworth_zoh, static_argnums=0)
    for order in range(1, 9):  # z = w_c dt: a fast filter, 400 samples
        y = bw(order, jnp.asarray(0.05), jnp.ones(400), jnp.asarray(1.0))
        np.testing.assert_allclose(y, _butterworth_step_response(order, 0.05, 400), rtol=0, atol=5e-14)
    for order in (2, 3, 4):  # a slow one (a = e^{qz} within 1e-4 of 1) over 6e4 samples: rounding not integrated
        y = bw(order, jnp.asarray(1e-4), jnp.ones(60_000), jnp.asarray(1.0))
        np.testing.assert_allclose(y, _butterworth_step_response(order, 1e-4, 60_000), rtol=0, atol=1e-13)
    u = np.cumsum(np.random.default_rng(3).standard_normal(2000))
    wc, dt = 2 * np.pi * 20.0, 5e-4
    ref = ss.dlsim(ss.cont2discrete(ss.tf2ss(*ss.butter(3, wc, analog=True)), dt, "zoh"), u)[1][:, 0]
    y = bw(3, jnp.asarray(wc), jnp.asarray(u), jnp.asarray(dt))
    assert rel_err(y, ref) < 1e-12
    assert rel_err(y, pj.butterworth(3, wc).simulate(u, dt)) < 1e-13
    # float32 stays float32; vmap over signals; the cutoff's derivative against central differences
    assert bw(3, jnp.float32(wc), jnp.asarray(u, jnp.float32), jnp.float32(dt)).dtype == jnp.float32
    batch = jax.vmap(lambda x: butterworth_zoh(3, jnp.asarray(wc), x, jnp.asarray(dt)))(jnp.stack([u, -2 * u]))
    np.testing.assert_allclose(batch[1], -2 * batch[0], rtol=1e-13, atol=0)
    d = jax.jacfwd(lambda c: butterworth_zoh(3, c, jnp.asarray(u), jnp.asarray(dt)))(jnp.asarray(wc))
    h = 1e-4 * wc
    fd = (bw(3, jnp.asarray(wc + h), jnp.asarray(u), jnp.asarray(dt))
          - bw(3, jnp.asarray(wc - h), jnp.asarray(u), jnp.asarray(dt))) / (2 * h)
    assert rel_err(d, fd) < 1e-6
    from piezojax._config import parallel_scans

    with parallel_scans("always"):  # the cascade's associative scan
        y_parallel = jax.jit(butterworth_zoh, static_argnums=0)(3, jnp.asarray(wc), jnp.asarray(u), jnp.asarray(dt))
    assert rel_err(y_parallel, y) < 1e-12


def test_from_tf_roundtrip_and_unstable_den():
    num, den = [2.0, 1.0], np.polymul([1.0, 0.3, 9.0], [1.0, 2.0])
    G = pj.StableTransferFunction.from_tf(num, den)
    np.testing.assert_allclose(G.omega, [3.0], rtol=1e-12)
    np.testing.assert_allclose(G.zeta, [0.05], rtol=1e-12)
    np.testing.assert_allclose(G.poles, [-2.0], rtol=1e-12)
    u = np.random.default_rng(0).normal(size=200)
    assert rel_err(sim(G, u, 0.05), lsim(num, den, u, 0.05, "zoh")) < 1e-10
    Gn = pj.StableTransferFunction.from_tf(num, den, dc_normalised=True)
    np.testing.assert_allclose(Gn.dc_gain(), 1.0 / 18.0, rtol=1e-12)
    with pytest.raises(ValueError, match="`den`"):
        pj.StableTransferFunction.from_tf([1.0], [1.0, -0.1, 4.0])
    with pytest.raises(ValueError, match="`den`"):
        pj.StableTransferFunction.from_tf([1.0], [1.0, 1.0, 0.0])  # pole at 0


def test_num_form_equals_zeros_form():
    zeros_form = pj.StableTransferFunction(2.0, [10.0, 3.0], [0.1, 0.5], [-1.0, -2.0], zeros=[-0.5, -4.0, -1.0])
    num = np.poly([-0.5, -4.0, -1.0])
    num_form = pj.StableTransferFunction(2.0, [10.0, 3.0], [0.1, 0.5], [-1.0, -2.0], num=num)
    u = np.random.default_rng(0).normal(size=300)
    assert rel_err(sim(num_form, u, 0.01, "foh"), sim(zeros_form, u, 0.01, "foh")) < 1e-11
    nd = pj.StableTransferFunction(2.0, [10.0], [0.1], [-1.0], num=[1.0, 3.0], dc_normalised=False)
    np.testing.assert_allclose(nd.transfer_function()[0], [0.0, 0.0, 2.0, 6.0])
    np.testing.assert_allclose(nd.dc_gain(), 6.0 / 100.0, rtol=1e-12)


# -- transformations ----------------------------------------------------------------------------------------------


def test_vmap_over_inputs_parameters_and_dt():
    G = SYSTEMS[3][1]
    u = np.random.default_rng(2).normal(size=(5, 200))
    batched = sim_batch(G, u, 0.02)
    _, _, num, den = SYSTEMS[3]
    for i in range(5):
        assert rel_err(batched[i], lsim(num, den, u[i], 0.02, "zoh")) < 1e-9
    omegas = jnp.array([1.0, 5.0, 20.0])
    ys = jax.jit(jax.vmap(lambda w: pj.StableTransferFunction(1.0, w[None], [0.2]).simulate(u[0], 0.02, hold="foh")))(
        omegas
    )
    for i, w in enumerate(omegas):
        ref = lsim([float(w) ** 2], [1.0, 0.4 * float(w), float(w) ** 2], u[0], 0.02, "foh")
        assert rel_err(ys[i], ref) < 1e-9
    ys = jax.jit(jax.vmap(lambda dt: G.simulate(u[3], dt)))(jnp.array([0.01, 0.02]))
    np.testing.assert_allclose(ys[1], batched[3], rtol=1e-12, atol=1e-14)


def test_float32():
    G64 = SYSTEMS[3][1]
    G32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, G64)
    u = np.random.default_rng(3).normal(size=300)
    y32 = sim(G32, u.astype(np.float32), 0.02, "foh")
    assert y32.dtype == jnp.float32
    assert rel_err(y32, sim(G64, u, 0.02, "foh")) < 1e-4


def _fd_check(f, model, eps=1e-6, rtol=1e-5):
    """jax.jacfwd of f wrt every inexact leaf of `model` vs central finite differences."""
    jac = jax.jacfwd(f)(model)
    leaves, treedef = jax.tree_util.tree_flatten(model)
    jac_leaves = jax.tree_util.tree_leaves(jac)
    assert len(jac_leaves) == len([x for x in leaves if eqx.is_inexact_array(x)])
    j = 0
    checked = 0
    for i, leaf in enumerate(leaves):
        if not eqx.is_inexact_array(leaf):
            continue
        J = np.asarray(jac_leaves[j]).reshape(-1, leaf.size) if leaf.size else None
        j += 1
        for k in range(leaf.size):
            h = eps * max(1.0, abs(float(leaf.reshape(-1)[k])))

            def shifted(d, i=i, k=k):
                new = list(leaves)
                new[i] = leaf.reshape(-1).at[k].add(d).reshape(leaf.shape)
                return f(jax.tree_util.tree_unflatten(treedef, new))

            fd = (np.asarray(shifted(h)) - np.asarray(shifted(-h))) / (2 * h)
            scale = max(np.max(np.abs(fd)), 1e-12)
            assert np.max(np.abs(J[:, k] - fd)) / scale < rtol, (i, k)
            checked += 1
    return checked


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_jacfwd_matches_finite_differences(hold):
    """jacfwd wrt every parameter vs central differences: pole/zero/gain parameters (FOH), TF coefficients (ZOH)."""
    u = jnp.asarray(np.random.default_rng(4).normal(size=60))
    if hold == "foh":
        model = pj.StableTransferFunction(
            1.5, [4.0, 12.0], [0.3, 0.05], [-2.0], zeros=[-1.0], zero_omega=[8.0], zero_zeta=[0.2]
        )
        n_params = 9
    else:
        model = pj.TransferFunction([0.3, 1.0, 2.0], [1.0, 2.5, 7.0, 9.0])
        n_params = 8  # the normalised den[0] = 1 is a leaf too (zero derivative)
    assert _fd_check(jax.jit(lambda m: m.simulate(u, 0.02, hold=hold)), model) == n_params


def test_reverse_mode_matches_forward_mode():
    u = jnp.asarray(np.random.default_rng(5).normal(size=50))
    G = pj.StableTransferFunction(1.3, [5.0], [0.2], zeros=[-2.0])
    loss = lambda m: jnp.sum(m.simulate(u, 0.02, hold="foh") ** 2)  # noqa: E731
    g_rev = eqx.filter_jit(jax.grad(loss))(G)
    g_fwd = eqx.filter_jit(jax.jacfwd(loss))(G)
    for a, b in zip(jax.tree_util.tree_leaves(g_rev), jax.tree_util.tree_leaves(g_fwd)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@settings(max_examples=15)
@given(
    w=st.floats(0.5, 50.0),
    zeta=st.floats(0.01, 3.0),
    p=st.floats(0.1, 20.0),
)
def test_superposition_and_dc_property(w, zeta, p):
    """Linearity in u; chunked simulation equals one pass; the step response settles at dc_gain()."""
    G = pj.StableTransferFunction(2.0, [w], [zeta], [-p])
    u = np.sin(np.arange(80) * 0.3)
    v = np.cos(np.arange(80) * 0.7)
    f = _simulate_foh
    np.testing.assert_allclose(f(G, 2 * u - v), 2 * f(G, u) - f(G, v), rtol=1e-9, atol=1e-11)
    state, y1 = _scan_foh(G, u[:40])
    _, y2 = _scan_foh(G, u[40:], state)
    np.testing.assert_allclose(np.concatenate([y1, y2]), f(G, u), rtol=1e-10, atol=1e-12)
    y = _simulate_dt(G, np.ones(20), 100.0 / min(w * zeta, p))  # long after every transient (stiff: ||A dt|| ~ 1e6)
    np.testing.assert_allclose(y[-1], 2.0, rtol=1e-9)


_simulate_foh = jax.jit(lambda G, u: G.simulate(u, 0.05, hold="foh"))
_scan_foh = jax.jit(lambda G, u, state=None: G.scan(u, 0.05, state, hold="foh"))
_simulate_dt = jax.jit(lambda G, u, dt: G.simulate(u, dt))


# -- bad input ----------------------------------------------------------------------------------------------------


def test_bad_input_errors_name_the_argument():
    G = pj.TransferFunction([1.0], [1.0, 1.0])
    u = np.ones(10)
    for bad_dt in (0.0, -1e-3, np.nan, np.inf):
        with pytest.raises(ValueError, match="`dt`"):
            G.simulate(u, bad_dt)
    with pytest.raises(ValueError, match="`dt`"):
        G.simulate(u, np.array([0.1, 0.1]))
    with pytest.raises(RuntimeError, match="`dt`"):
        eqx.filter_jit(lambda d: G.simulate(u, d))(jnp.asarray(-0.1))  # traced: eqx.error_if at run time
    with pytest.raises(ValueError, match="`dt`"):
        eqx.filter_jit(lambda d: G.simulate(u, d))(-0.1)  # a Python float is static: checked at trace time
    with pytest.raises(ValueError, match="`hold`"):
        G.simulate(u, 0.1, hold="linear")
    with pytest.raises(ValueError, match="`u`"):
        G.simulate(np.ones((2, 10)), 0.1)
    with pytest.raises(ValueError, match="`u`"):
        G.simulate(np.ones(0), 0.1)
    with pytest.raises(ValueError, match="`u`"):
        G.simulate(np.array([1.0, np.nan]), 0.1)  # concrete: PiezojaxValueError (traced: eqx.error_if)
    with pytest.raises(ValueError, match="`x0`"):
        G.simulate(u, 0.1, x0=np.zeros(2))
    with pytest.raises(ValueError, match="`num`"):
        pj.TransferFunction([1.0, 2.0, 3.0], [1.0, 1.0])  # improper
    with pytest.raises(ValueError, match="`num`"):
        pj.TransferFunction([np.nan], [1.0, 1.0])
    with pytest.raises(ValueError, match="`den`"):
        pj.TransferFunction([1.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="`den`"):
        pj.TransferFunction([1.0], [])
    with pytest.raises(ValueError, match="`den`"):
        pj.TransferFunction([1.0], [[1.0, 2.0]])
    # leading zeros of num do not make a transfer function improper (as in scipy)
    np.testing.assert_allclose(pj.TransferFunction([0.0, 0.0, 2.0], [1.0, 1.0]).num, [0.0, 2.0])
    # ... but a traced num cannot be stripped: the error says so (it had named a degree of 2)
    with pytest.raises(ValueError, match="a traced `num`.*drop its leading zeros"):
        jax.jit(lambda n: pj.TransferFunction(n, jnp.array([1.0, 3.0])).dc_gain())(jnp.array([0.0, 0.0, 2.0]))
    with pytest.raises(ValueError, match="`B`"):
        pj.StateSpace(np.eye(2), np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="`C`"):
        pj.StateSpace(np.eye(2), np.ones(2), np.ones((2, 2)))
    with pytest.raises(ValueError, match="`A`"):
        pj.StateSpace(np.ones((2, 3)), np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match="`A`"):
        pj.StateSpace([[np.nan]], [1.0], [1.0])


def test_bad_stable_parameters_name_the_argument():
    with pytest.raises(ValueError, match="`zeta`"):
        pj.StableTransferFunction(1.0, [1.0], [-0.1])
    with pytest.raises(ValueError, match="`zeta`"):
        pj.StableTransferFunction(1.0, [1.0], [0.0])
    with pytest.raises(ValueError, match="`omega`"):
        pj.StableTransferFunction(1.0, [-1.0], [0.1])
    with pytest.raises(ValueError, match="`poles`"):
        pj.StableTransferFunction(1.0, poles=[0.5])
    with pytest.raises(ValueError, match="`poles`"):
        pj.StableTransferFunction(1.0, poles=[np.nan])
    with pytest.raises(ValueError, match="`omega`"):
        pj.StableTransferFunction(1.0, [1.0, 2.0], [0.1])
    with pytest.raises(ValueError, match="`num`"):
        pj.StableTransferFunction(1.0, [1.0], [0.1], num=[1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ValueError, match="`num`"):
        pj.StableTransferFunction(1.0, [1.0], [0.1], num=[1.0, 0.0])  # N(0) = 0 with dc normalisation
    with pytest.raises(ValueError, match="`zeros`"):
        pj.StableTransferFunction(1.0, poles=[-1.0], zeros=[-1.0, -2.0])
    with pytest.raises(ValueError, match="`zero_omega`"):
        pj.StableTransferFunction(1.0, poles=[-1.0, -2.0], zero_omega=[1.0], zero_zeta=[0.1])
    with pytest.raises(ValueError, match="`gain`"):
        pj.StableTransferFunction(np.nan, poles=[-1.0])
    # traced parameters: the check fires at run time under jit
    f = eqx.filter_jit(lambda z: pj.StableTransferFunction(1.0, [1.0], z[None]).simulate(jnp.ones(5), 0.1))
    assert np.isfinite(f(jnp.asarray(0.2))).all()
    with pytest.raises(RuntimeError, match="`zeta`"):
        f(jnp.asarray(-0.2))
    # a model moved outside the stable set without __init__ (e.g. by tree_at) is caught when simulated
    G = eqx.tree_at(lambda m: m.poles, pj.StableTransferFunction(1.0, poles=[-1.0]), jnp.array([1.0]))
    with pytest.raises(ValueError, match="`poles`"):
        G.simulate(jnp.ones(5), 0.1)
    with pytest.raises(RuntimeError, match="`poles`"):
        sim(G, jnp.ones(5), 0.1)
    with pytest.raises(ValueError, match="`order`"):
        pj.butterworth(0, 1.0)
    with pytest.raises(ValueError, match="`cutoff`"):
        pj.butterworth(2, -1.0)


def test_time_step_checks_uniform_increasing_time():
    np.testing.assert_allclose(pj.time_step(np.arange(100) * 1e-4), 1e-4, rtol=1e-12)
    t = np.arange(100) * 1e-4
    t_bad = t.copy()
    t_bad[50] += 3e-5
    # concrete: the library's error naming `t`; traced: the same message through eqx.error_if
    with pytest.raises(pj.PiezojaxValueError, match="`t` must be uniformly sampled"):
        pj.time_step(t_bad)
    with pytest.raises(pj.PiezojaxValueError, match="`t` must be strictly increasing"):
        pj.time_step(t[::-1])
    with pytest.raises(RuntimeError, match="increasing"):
        eqx.filter_jit(pj.time_step)(jnp.asarray(t[::-1]))
    with pytest.raises(RuntimeError, match="uniform"):
        eqx.filter_jit(pj.time_step)(jnp.asarray(t_bad))
    with pytest.raises(ValueError, match="`t`"):
        pj.time_step(np.array([0.0]))
