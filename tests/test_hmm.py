"""The cyclic HMM of Izo–Grimson §6: transitions, eq. 9 emissions, Viterbi."""

import itertools

import numpy as np
import pytest

from estimator.hmm import PhaseHMM, cyclic_transitions, phase_log_emission, posterior, viterbi


def test_transitions_are_cyclic_feed_forward():
    A = cyclic_transitions(20, (0.1, 0.35, 0.3, 0.25))
    np.testing.assert_allclose(A.sum(axis=1), 1.0)
    assert A[19, 0] == pytest.approx(0.35) and A[18, 1] == pytest.approx(0.25) and A[5, 5] == pytest.approx(0.1)
    assert A[5, 4] == 0 and A[5, 9] == 0  # never backwards, never more than 3 on
    with pytest.raises(ValueError, match="non-negative"):
        cyclic_transitions(20, (0.1, -0.2, 0.3, 0.3))


def brute_force(log_start, log_trans, log_em):
    T, K = log_em.shape
    best = (-np.inf, None)
    for path in itertools.product(range(K), repeat=T):
        lp = log_start[path[0]] + log_em[0, path[0]]
        lp += sum(log_trans[path[t - 1], path[t]] + log_em[t, path[t]] for t in range(1, T))
        best = max(best, (lp, path), key=lambda x: x[0])
    return best


@pytest.mark.parametrize("seed", range(5))
def test_viterbi_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    K, T = 4, 5
    log_start = np.log(rng.dirichlet(np.ones(K)))
    log_trans = np.log(rng.dirichlet(np.ones(K), size=K))
    log_em = rng.normal(size=(T, K))
    lp, states = viterbi(log_start, log_trans, log_em)
    blp, bpath = brute_force(log_start, log_trans, log_em)
    assert lp == pytest.approx(blp)
    assert tuple(states) == bpath


def test_viterbi_worked_example_with_stub_emission():
    """Two states that must alternate; the emission favours state 0 at t = 0 only."""
    with np.errstate(divide="ignore"):
        log_trans = np.log(np.array([[0.0, 1.0], [1.0, 0.0]]))
    log_em = np.log(np.array([[0.9, 0.1], [0.5, 0.5], [0.5, 0.5]]))
    lp, states = viterbi(np.log([0.5, 0.5]), log_trans, log_em)
    assert list(states) == [0, 1, 0]
    assert lp == pytest.approx(np.log(0.5 * 0.9 * 0.5 * 0.5))


def test_emission_is_the_2c_mixture_of_eq_9():
    """The factorised emission equals the explicit 2^c-component mixture."""
    rng = np.random.default_rng(0)
    p, c, sigma = 20, 3, 0.07
    obs = rng.uniform(size=(4, c))
    got = phase_log_emission(obs, p, sigma=sigma)
    explicit = np.zeros((4, p))
    for i in range(p):
        total = 0.0
        for e in itertools.product((0, 1), repeat=c):
            mu = (i + np.array(e) * p / 2) % p / p
            d = (obs - mu + 0.5) % 1.0 - 0.5
            total = total + np.prod(np.exp(-0.5 * (d / sigma) ** 2) / np.sqrt(2 * np.pi * sigma**2), axis=1) / 2**c
        explicit[:, i] = np.log(total)
    np.testing.assert_allclose(got, explicit, rtol=1e-10)


def test_missing_camera_contributes_nothing():
    obs = np.array([[0.25, np.nan], [np.nan, np.nan]])
    got = phase_log_emission(obs, 20, sigma=0.05)
    np.testing.assert_allclose(got[0], phase_log_emission(obs[:1, :1], 20, sigma=0.05)[0])
    np.testing.assert_allclose(got[1], 0.0)


def _noisy_path(rng, T=40, c=2, speed=1.6, flip=0.3, noise=0.02, missing=0.1):
    true = (rng.uniform() * 20 + speed * np.arange(T)) % 20
    obs = (true[:, None] / 20 + rng.normal(0, noise, (T, c))) % 1.0
    flips = rng.uniform(size=(T, c)) < flip
    obs[flips] = (obs[flips] + 0.5) % 1.0
    obs[rng.uniform(size=(T, c)) < missing] = np.nan
    return true, obs


def _cycle_error(states, true):
    return np.abs((states - true + 10) % 20 - 10)


def test_recovers_phase_path_despite_opposite_phase_confusions():
    rng = np.random.default_rng(1)
    hmm = PhaseHMM(opposite_weight=0.3)
    errors = []
    for _ in range(20):
        true, obs = _noisy_path(rng)
        _, states = hmm.decode(obs)
        errors.append(_cycle_error(states, true))
        # Raw per-frame observations are wrong by half a cycle where flipped.
    err = np.concatenate(errors)
    assert np.mean(err <= 1.0) > 0.9, np.mean(err <= 1.0)


def test_equal_mixture_recovers_path_up_to_half_cycle():
    """The paper's equal weights cannot tell a phase from its opposite; the path is still found."""
    rng = np.random.default_rng(2)
    true, obs = _noisy_path(rng, flip=0.3)
    _, states = PhaseHMM().decode(obs)
    err = np.minimum(_cycle_error(states, true), _cycle_error(states + 10, true))
    assert np.mean(err <= 1.0) > 0.9
    steps = np.diff(states) % 20
    assert np.all(steps <= 3)  # feed-forward


def test_bad_observations_rejected():
    with pytest.raises(ValueError, match=r"\(T, c\)"):
        PhaseHMM().decode(np.zeros(5))


@pytest.mark.parametrize("seed", range(3))
def test_posterior_is_the_marginal_over_all_paths(seed):
    """Forward-backward against enumerating every path: P(state k at t | all observations)."""
    rng = np.random.default_rng(seed)
    K, T = 4, 5
    log_start = np.log(rng.dirichlet(np.ones(K)))
    log_trans = np.log(cyclic_transitions(K, (0.2, 0.4, 0.3, 0.1)))
    log_em = rng.normal(0.0, 2.0, (T, K))
    marg = np.zeros((T, K))
    for path in itertools.product(range(K), repeat=T):
        lp = log_start[path[0]] + log_em[0, path[0]]
        lp += sum(log_trans[path[t - 1], path[t]] + log_em[t, path[t]] for t in range(1, T))
        marg[np.arange(T), list(path)] += np.exp(lp)
    np.testing.assert_allclose(posterior(log_start, log_trans, log_em), marg / marg.sum(axis=1, keepdims=True),
                               atol=1e-10)


def test_posterior_spreads_where_nothing_was_seen():
    hmm = PhaseHMM()
    obs = (np.arange(30)[:, None] * 0.09 + np.array([0.0, 0.0])) % 1.0
    obs[12:18] = np.nan  # six frames no camera saw
    with np.errstate(divide="ignore"):
        post = posterior(np.log(hmm.startprob_), np.log(hmm.transmat_), hmm.log_emission(obs))
    np.testing.assert_allclose(post.sum(axis=1), 1.0)
    best = post.argmax(axis=1)
    near = post[np.arange(30)[:, None], (best[:, None] + np.arange(-1, 2)) % hmm.n_states].sum(axis=1)
    assert near[14] < 0.8 * np.median(near[:10])  # inside the gap: less sure (0.36 against 0.48)
    assert near[14] < near[12] and near[14] < near[17]  # least sure farthest from the observations
