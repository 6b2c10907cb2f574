"""The likelihood of the hierarchical fit: sparse delay marginalisation against a plain reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from quadshank.model import _likelihood as L
from quadshank.model._effects import AngleDelay, Darma, TwitchVariability
from quadshank.model._model import paper_model
from quadshank.data._paper import MAX_DELAY, TWITCH_SAMPLES
from quadshank.data._simulate import simulate_cohort

PASSIVE = ("damping", "gravity", "k1", "k2")


@pytest.fixture(scope="module")
def cohort_truth():
    return simulate_cohort(legs=["TN-left", "JM-right"], minutes=1, seed=3, trials=(1, 2))


def _true_model(number, truth, leg):
    tr = truth["legs"][leg]
    m = paper_model(number).with_params({k: tr["passive"][k] for k in PASSIVE})
    act = tr["active"]
    if number == 2:
        eq = tr["model2_equivalent"]
        return m.with_params(a=jnp.array([eq["a1"], eq["a2"]]), b=jnp.array([eq["b1"], eq["b2"]]))
    if number == 1:
        return m.with_params(gain=act["G2"])
    return m.with_params(gain=act["G2"], gamma_angle=act["gamma_angle"], gamma_velocity=act["gamma_velocity"])


def _window_t(sigma, nu, n):
    """A window of n samples: the Student-t with the sum's variance and (ν > 4) kurtosis."""
    assert nu > 2
    nu_n = nu + (n - 1) * ((nu - 4) ** 2 / (nu - 3.5) if nu > 4 else 0.0)
    var = n * sigma**2 * nu / (nu - 2)
    return np.sqrt(var * (nu_n - 2) / nu_n), nu_n


def _reference_loglik(model, trials, d, sigma, nu, resolution, response_length, cv=None):
    """Per-sample model output built pulse by pulse in NumPy, summed over windows, Student-t with
    the window sum's variance and kurtosis; with random pulse gains of coefficient of variation
    ``cv``, each window's squared scale grows by cv² × Σ over its pulses of (the pulse's output
    summed over the window)²."""
    total = 0.0
    h = np.asarray(L.impulse_response(model.activation, response_length))
    for t in trials:
        angle, vel, acc, stim = t.angle_deg, t.velocity_deg_s, t.acceleration_deg_s2, t.stimulation
        passive = sum(np.asarray(e.acceleration(angle, vel)) for e in model.passives)
        e0 = acc - passive
        F = np.ones_like(angle)
        for g in model.gains:
            F = F * np.asarray(g.factor(L.StepContext(angle, vel, stim, stim)))
        M = np.zeros_like(angle)
        starts = np.flatnonzero(L._windows(stim, resolution))
        Vw = np.zeros(starts.size)
        for p in np.flatnonzero(stim > 0):
            Mp = np.zeros_like(angle)
            for j in range(response_length):
                k = p + d + j
                if k < angle.size:
                    Mp[k] += stim[p] * h[j] * F[k]
            M += Mp
            Vw += np.add.reduceat(Mp, starts) ** 2
        E = np.add.reduceat(e0, starts)
        Mw = np.add.reduceat(M, starts)
        n = np.diff(np.append(starts, angle.size))
        keep = np.ones(starts.size, bool)
        last = np.flatnonzero(stim > 0)[-1]
        if resolution == "twitch" and last + MAX_DELAY + TWITCH_SAMPLES > angle.size:
            keep[starts >= starts[starts <= last][-1]] = False  # the window the trial's end cuts short
        keep &= np.add.reduceat(t.exclude.astype(int), starts) == 0  # a window with an excluded sample
        scale, nu_n = _window_t(sigma, nu, n)
        if cv is not None:
            scale = np.sqrt(scale**2 + cv**2 * Vw)
        total += stats.t.logpdf(E - Mw, df=nu_n, scale=scale)[keep].sum()
    return total


@pytest.mark.parametrize("cv", [None, 0.25])
@pytest.mark.parametrize("number", [1, 2, 3])
def test_sparse_delay_loglik_matches_reference(cohort_truth, number, cv):
    """Without and with random pulse gains (``twitch_variability``), on the pulse-level path
    (models 1, 3), the (pulse, lag) path on twitch windows (the same models without the
    pulse-level tables) and on samples (model 2)."""
    cohort, truth = cohort_truth
    leg = "JM-right"
    model = _true_model(number, truth, leg)
    if cv is not None:
        model = model.add(TwitchVariability(twitch_cv=cv))
    data = L.prepare(cohort, model, trials=(1, 2), legs=[leg])
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    ll = np.asarray(L.leg_loglik_by_delay(model, {"sigma": 35.0, "nu": 6.0}, x, data.response_length))[:, 0]
    general = np.asarray(L.leg_loglik_by_delay(model, {"sigma": 35.0, "nu": 6.0}, _general(x), data.response_length))[:, 0]
    trials = cohort.trials_of(leg)
    plain = np.asarray(L.leg_loglik_by_delay(_true_model(number, truth, leg), {"sigma": 35.0, "nu": 6.0}, x, data.response_length))[:, 0]
    for d in (0, 4, MAX_DELAY):
        ref = _reference_loglik(model, trials, d, 35.0, 6.0, data.resolution, data.response_length, cv)
        assert ll[d] == pytest.approx(ref, rel=2e-5, abs=0.5), d
        assert general[d] == pytest.approx(ref, rel=2e-5, abs=0.5), d
        if cv is not None:  # the random gains change the likelihood by more than the tolerance
            assert abs(plain[d] - ref) > 50.0, d


def _excluding(cohort, leg, stretches):
    """The cohort with the samples ``stretches`` [(trial, start, stop)] of ``leg`` excluded and
    their acceleration replaced by nonsense."""
    trials = []
    for t in cohort.trials:
        exclude, acc = t.exclude.copy(), t.acceleration_deg_s2.copy()
        for trial, a, b in stretches:
            if t.key == leg and t.trial == trial:
                exclude[a:b] = True
                acc[a:b] = 1e5
        trials.append(t.replace(exclude=exclude, acceleration_deg_s2=acc))
    return type(cohort)(tuple(trials), cohort.attrs)


@pytest.mark.parametrize("number", [1, 2, 3])
def test_excluded_samples_leave_the_likelihood_but_their_pulses_act(cohort_truth, number):
    """Excluded samples (and, on twitch windows, the whole window they fall in) are not compared,
    whatever they hold; the pulses delivered in them still act on the samples after them."""
    cohort, truth = cohort_truth
    leg = "JM-right"
    model = _true_model(number, truth, leg)
    pulses = cohort.get(leg, 1).pulse_indices
    # a stretch holding a pulse whose response runs out into compared samples (at the sample
    # resolution), and one sample inside a twitch window of trial 2
    p = int(pulses[len(pulses) // 2])
    q = int(cohort.get(leg, 2).pulse_indices[3])
    stretches = [(1, 200, 900), (1, p - 2, p + 2), (2, q + 5, q + 6)]
    dirty = _excluding(cohort, leg, stretches)
    data = L.prepare(dirty, model, trials=(1, 2), legs=[leg])
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": 35.0, "nu": 6.0}
    ll = np.asarray(L.leg_loglik_by_delay(model, noise, x, data.response_length))[:, 0]
    for d in (0, 4, MAX_DELAY):
        ref = _reference_loglik(model, dirty.trials_of(leg), d, 35.0, 6.0, data.resolution, data.response_length)
        assert np.isfinite(ref) and ll[d] == pytest.approx(ref, rel=2e-5, abs=0.5), d
    compared = int(data.sample_mask.sum())
    clean = int(L.prepare(cohort, model, trials=(1, 2), legs=[leg]).sample_mask.sum())
    excluded = sum(b - a for _, a, b in stretches)
    if data.resolution == "sample":
        assert clean - compared == excluded
        # the excluded pulse still acts: without it the likelihood of the samples after it differs
        silent = dirty.trials_of(leg)[0].stimulation.copy()
        silent[p] = 0.0
        without = _excluding(cohort, leg, stretches)
        without = type(cohort)(tuple(t.replace(stimulation=silent) if t.key == leg and t.trial == 1 else t
                                     for t in without.trials), cohort.attrs)
        data0 = L.prepare(without, model, trials=(1, 2), legs=[leg])
        x0 = {k: v[0] for k, v in data0.leg_arrays().items()}
        ll0 = np.asarray(L.leg_loglik_by_delay(model, noise, x0, data0.response_length))[:, 0]
        assert abs(ll0[4] - ll[4]) > 1.0
    else:
        assert clean - compared > excluded  # whole windows go


def test_pointwise_segments_sum_to_the_delay_loglik(cohort_truth):
    cohort, truth = cohort_truth
    model = _true_model(3, truth, "TN-left")
    data = L.prepare(cohort, model, trials=(1,), legs=["TN-left"])
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": 40.0, "nu": 8.0}
    by_d = L.leg_loglik_by_delay(model, noise, x, data.response_length)[:, 0]
    seg = L.leg_pointwise(model, noise, x, 5, data.response_length, data.n_segments)
    assert seg.shape == (data.n_segments,)
    assert data.n_segments == 60  # one minute in 1-s segments
    assert float(jnp.sum(seg)) == pytest.approx(float(by_d[5]), rel=1e-5)


def test_twitch_windows_hold_whole_bursts():
    stim = np.zeros(400)
    stim[[10, 14, 20, 200]] = 1.0  # a burst of three, then an isolated pulse
    starts = L._windows(stim, "twitch")
    span = MAX_DELAY + TWITCH_SAMPLES
    assert starts[10] and not starts[11:20 + span].any()  # the burst is one window
    assert starts[20 + span]  # then single samples again
    assert starts[200] and not starts[201:200 + span].any()
    assert starts[:10].all()
    assert L._windows(stim, "sample").all()
    with pytest.raises(ValueError, match="resolution"):
        L._windows(stim, "minute")


@pytest.mark.parametrize("number", [1, 2])
def test_windows_split_into_one_sample_and_longer(cohort_truth, number):
    """The base takes one-sample windows with scalar σ, ν and only the longer ones from the
    noise table: the two sets must cover every compared window once."""
    cohort, truth = cohort_truth
    data = L.prepare(cohort, _true_model(number, truth, "TN-left"), trials=(1, 2))
    for i in range(data.n_legs):
        multi = np.zeros_like(data.window_mask[i])
        multi[data.multi_window[i][data.multi_mask[i]]] = True
        assert data.multi_mask[i].sum() == multi.sum()  # no window twice
        assert not (multi & data.single_mask[i]).any()
        np.testing.assert_array_equal(multi | data.single_mask[i], data.window_mask[i])
        np.testing.assert_array_equal(multi, data.window_mask[i] & (data.window_len[i] > 1))
    if number == 2:  # sample resolution: no table at all
        assert data.multi_window.shape[-1] == 0
    else:
        assert data.multi_mask.any(axis=1).all()


@pytest.mark.parametrize("tail", [2, MAX_DELAY + TWITCH_SAMPLES - 1, MAX_DELAY + TWITCH_SAMPLES + 5])
def test_model1_likelihood_does_not_see_the_delay_even_at_the_end_of_a_trial(cohort_truth, tail):
    """Model 1's twitch lies whole in its window for every d, also when the trial ends soon after a pulse."""
    from quadshank import Cohort, Trial

    cohort, truth = cohort_truth
    t = cohort.get("TN-left", 1)
    pulses = np.flatnonzero(t.stimulation > 0)
    gaps = np.diff(pulses)
    last = int(pulses[:-1][gaps > MAX_DELAY + TWITCH_SAMPLES + 10][-1])  # the trial will end `tail` after it
    n = last + tail
    cut = Trial.from_signals("TN", "left", 1, 0.01, t.angle_deg[:n], t.acceleration_deg_s2[:n], t.stimulation[:n])
    model = _true_model(1, truth, "TN-left")
    data = L.prepare(Cohort((cut,)), model, trials=(1,))
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    ll = np.asarray(L.leg_loglik_by_delay(model, {"sigma": 40.0, "nu": 8.0}, x, data.response_length))[:, 0]
    assert np.ptp(ll) < 1e-5 * abs(ll[0]), ll  # float32 sums
    # the window the end cuts short is what is left out, and only that
    assert (int(data.sample_mask[0].sum()) < n) == (tail < MAX_DELAY + TWITCH_SAMPLES)


def test_model2_likelihood_peaks_at_the_onset_delay(cohort_truth):
    cohort, truth = cohort_truth
    for leg in ("TN-left", "JM-right"):
        model = _true_model(2, truth, leg)
        data = L.prepare(cohort, model, trials=(1,), legs=[leg])
        x = {k: v[0] for k, v in data.leg_arrays().items()}
        ll = L.leg_loglik_by_delay(model, {"sigma": 40.0, "nu": 10.0}, x, data.response_length)[:, 0]
        # DARMA's first output comes one sample after u_{k-d}: d = floor of the true onset
        assert int(jnp.argmax(ll)) == int(np.floor(truth["legs"][leg]["active"]["delay_samples"]))


def test_gradient_is_finite_for_every_parameter(cohort_truth):
    cohort, truth = cohort_truth
    model = _true_model(3, truth, "TN-left")
    data = L.prepare(cohort, model, trials=(1,), legs=["TN-left"])
    x = {k: v[0] for k, v in data.leg_arrays().items()}

    def f(m):
        return jax.scipy.special.logsumexp(L.leg_loglik_by_delay(m, {"sigma": 40.0, "nu": 8.0}, x, 1))

    grads = jax.grad(f, allow_int=True)(model)  # the delay leaf is an integer
    leaves = [g for g in jax.tree_util.tree_leaves(grads) if np.issubdtype(np.asarray(g).dtype, np.floating)]
    assert len(leaves) == 7  # gain, two gammas, four passive parameters
    assert all(np.all(np.isfinite(np.asarray(g))) for g in leaves)
    assert abs(float(grads.effect("zero_order").gain)) > 0


def test_impulse_response_of_darma_follows_its_recursion():
    a, b = jnp.array([-1.5, 0.6]), jnp.array([400.0, 300.0])
    h = np.asarray(L.impulse_response(Darma(a=a, b=b), 6))
    ref = np.zeros(6)
    u = np.zeros(6)
    u[0] = 1
    for k in range(6):
        ref[k] = sum(-a[i] * ref[k - 1 - i] + b[i] * u[k - 1 - i] for i in range(2) if k - 1 - i >= 0)
    np.testing.assert_allclose(h, ref, rtol=1e-5)


def test_stateful_gains_are_refused(scratch_registry):
    import dataclasses

    from quadshank.model._effects import Effect, register_effect

    @register_effect
    @dataclasses.dataclass(frozen=True)
    class CountingGain(Effect):
        kind = "gain"
        name = "test_counting_gain"
        params = ()

        def init_state(self):
            return 0.0

        def gain(self, state, ctx):
            return state + ctx.u, 1.0

    model = paper_model(1).add(CountingGain())
    with pytest.raises(ValueError, match="test_counting_gain"):
        L.gain_factors(model, jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))


@pytest.mark.parametrize("number", [2, 3])
def test_angle_delay_reduces_to_plain_delays_at_its_limits(cohort_truth, number):
    """Shift 0 is no effect; a threshold above every angle shortens every pulse: delay d − shift."""
    cohort, truth = cohort_truth
    leg = "TN-left"
    plain = _true_model(number, truth, leg)
    data0 = L.prepare(cohort, plain, trials=(1,), legs=[leg])
    x0 = {k: v[0] for k, v in data0.leg_arrays().items()}
    noise = {"sigma": 40.0, "nu": 8.0}
    ref = np.asarray(L.leg_loglik_by_delay(plain, noise, x0, data0.response_length))[:, 0]
    for threshold, shortened in ((500.0, True), (-500.0, False)):
        model = plain.add(AngleDelay(threshold=threshold))
        data = L.prepare(cohort, model, trials=(1,), legs=[leg])
        assert data.max_shift == AngleDelay.max_shift
        x = {k: v[0] for k, v in data.leg_arrays().items()}
        ll = np.asarray(L.leg_loglik_by_delay(model, noise, x, data.response_length, data.max_shift))
        np.testing.assert_allclose(ll[:, 0], ref, rtol=2e-6)
        for shift in range(1, data.max_shift + 1):
            want = ref[: MAX_DELAY + 1 - shift] if shortened else ref[shift:]
            np.testing.assert_allclose(ll[shift:, shift], want, rtol=2e-6)


@pytest.mark.parametrize("number,cv", [(2, None), (3, None), (2, 0.2), (3, 0.2)])
def test_threshold_states_are_the_hard_step_at_thresholds_between_pulse_angles(cohort_truth, number, cv):
    """leg_loglik_by_threshold's state j equals the (d, shift) log-likelihood of the hard step at a
    threshold between the j-th and (j+1)-th pulse angle (two trials, so the pulses of both are ranked
    together); the states' prior masses are the Normal prior's between those angles."""
    cohort, truth = cohort_truth
    leg = "JM-right"
    plain = _true_model(number, truth, leg)
    plain = plain if cv is None else plain.add(TwitchVariability(twitch_cv=cv))
    model = plain.add(AngleDelay())
    data = L.prepare(cohort, model, trials=(1, 2), legs=[leg])
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": 40.0, "nu": 8.0}
    R, K = data.response_length, data.max_shift
    ll = np.asarray(L.leg_loglik_by_threshold(model, noise, x, R, K))
    angles = np.sort(data.angle[0][data.pulse_sample[0][data.pulse_u[0] > 0]].astype(np.float64))
    n = angles.size
    assert ll.shape == (MAX_DELAY + 1, K + 1, data.pulse_sample.shape[1] + 1) and n > 40
    for j in (0, 1, n // 3, n // 2, n - 1, n):
        if 0 < j < n and angles[j] == angles[j - 1]:
            continue
        threshold = -1e3 if j == 0 else 1e3 if j == n else 0.5 * (angles[j - 1] + angles[j])
        hard = plain.add(AngleDelay(threshold=threshold, softness_deg=0.0))
        want = np.asarray(L.leg_loglik_by_delay(hard, noise, x, R, K))
        np.testing.assert_allclose(ll[:, :, j], want, rtol=1e-6, err_msg=f"state {j}")
    mass = np.exp(np.asarray(L.step_log_mass(model, x, 0.0, 25.0), np.float64))
    edges = np.concatenate([[-np.inf], angles, [np.inf]])
    np.testing.assert_allclose(mass[: n + 1], np.diff(stats.norm.cdf(edges, 0.0, 25.0)), atol=2e-7)
    assert np.all(mass[n + 1 :] == 0.0)  # padding pulses


@pytest.mark.parametrize("number,cv", [(2, None), (2, 0.2), (3, 0.2)])
def test_pointwise_segments_with_an_angle_delay_sum_to_its_loglik(cohort_truth, number, cv):
    """Pointwise segments with an angle-dependent delay sum to the (d, shift) log-likelihood,
    with random pulse gains too."""
    cohort, truth = cohort_truth
    model = _true_model(number, truth, "TN-left").add(AngleDelay(threshold=-20.0))
    model = model if cv is None else model.add(TwitchVariability(twitch_cv=cv))
    data = L.prepare(cohort, model, trials=(1,), legs=["TN-left"])
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": 40.0, "nu": 8.0}
    ll = L.leg_loglik_by_delay(model, noise, x, data.response_length, data.max_shift)
    seg = L.leg_pointwise(model, noise, x, 5, data.response_length, data.n_segments, data.max_shift, 1)
    assert float(jnp.sum(seg)) == pytest.approx(float(ll[5, 1]), rel=1e-5)


def test_student_t_cdf_matches_scipy():
    z = np.linspace(-8.0, 8.0, 41)
    for nu in (1.2, 4.0, 30.0):
        np.testing.assert_allclose(np.asarray(L.student_t_cdf(jnp.asarray(z), nu)), stats.t.cdf(z, nu), atol=2e-6)


@pytest.mark.parametrize("nu", [3.0, 5.0, 8.0])
def test_window_noise_matches_a_sum_of_student_t_samples(nu):
    """A window's Student-t has its sum's variance exactly and, for ν > 4, its quantiles: the
    interquartile and 99 % ranges of 200,000 simulated sums of n samples of σ·t_ν come within
    5 % and at least twice as close as σ√n·t_ν's (the plain scaling).  For ν ≤ 4 and for one
    sample it is σ√n and ν."""
    sigma = 30.0
    rng = np.random.default_rng(11)
    for n in (1, 5, 20):
        scale, nu_n = (float(v) for v in L.window_noise(sigma, nu, float(n)))
        if nu <= 4 or n == 1:
            assert scale == pytest.approx(sigma * np.sqrt(n), rel=1e-6) and nu_n == pytest.approx(nu, rel=1e-6)
            continue
        assert scale**2 * nu_n / (nu_n - 2) == pytest.approx(n * sigma**2 * nu / (nu - 2), rel=1e-5)
        sums = sigma * rng.standard_t(nu, size=(200_000, n)).sum(axis=1)
        for lo, hi in ((0.25, 0.75), (0.005, 0.995)):
            want = np.quantile(sums, hi) - np.quantile(sums, lo)
            fitted = scale * (stats.t.ppf(hi, nu_n) - stats.t.ppf(lo, nu_n))
            plain = sigma * np.sqrt(n) * (stats.t.ppf(hi, nu) - stats.t.ppf(lo, nu))
            assert abs(fitted / want - 1) < 0.05, (n, lo, fitted, want)
            assert abs(fitted / want - 1) < 0.5 * abs(plain / want - 1), (n, lo, fitted, plain, want)


def _general(x):
    """The leg's arrays without the pulse-level tables: the (pulse, lag) path."""
    return {k: v for k, v in x.items() if k not in L.PULSE_LEVEL_FIELDS}


@pytest.mark.parametrize("cv", [None, 0.2])
@pytest.mark.parametrize("effect", [AngleDelay(threshold=-20.0), AngleDelay(threshold=5.0, softness_deg=0.0), None])
def test_pulse_level_path_equals_the_pulse_lag_path(cohort_truth, effect, cv):
    """On twitch windows the pulse-level path (one term per pulse) gives the (pulse, lag) path's
    log-likelihood for every delay and every shift the prior allows, and so do its threshold
    states; the data include windows holding several pulses, so the running sums within a
    window are exercised."""
    cohort, truth = cohort_truth
    leg = "TN-left"
    model = _true_model(3, truth, leg)
    model = model if effect is None else model.add(effect)
    model = model if cv is None else model.add(TwitchVariability(twitch_cv=cv))
    data = L.prepare(cohort, model, trials=(1, 2), legs=[leg])
    assert data.pulse_slot is not None
    n_pulses = int((data.pulse_u[0] > 0).sum())
    n_slots = int(data.slot_mask[0].sum())
    assert n_slots < n_pulses - 10  # several windows hold more than one pulse
    noise = {"sigma": 40.0, "nu": 6.0}
    R, K = data.response_length, data.max_shift
    allowed = np.arange(K + 1)[None, :] <= np.arange(MAX_DELAY + 1)[:, None]  # shift ≤ d
    with jax.enable_x64(True):  # in double precision the two agree to rounding
        x = {k: jnp.asarray(v[0], jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v[0] for k, v in data.leg_arrays().items()}
        model = model.with_params(jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), model.params()))
        # the twitch's sum Σh is taken at the data's single precision on the pulse-level path, so a
        # window's variance (a square of sums) agrees to single precision's rounding of Σh²
        rtol = 1e-12 if cv is None else 1e-9
        fast = np.asarray(L.leg_loglik_by_delay(model, noise, x, R, K))
        slow = np.asarray(L.leg_loglik_by_delay(model, noise, _general(x), R, K))
        np.testing.assert_allclose(fast[allowed], slow[allowed], rtol=rtol)
        assert np.ptp(fast) > 10.0  # the delay matters to model 3
        if data.step_order is not None:
            fast = np.asarray(L.leg_loglik_by_threshold(model, noise, x, R, K))
            slow = np.asarray(L.leg_loglik_by_threshold(model, noise, _general(x), R, K))
            np.testing.assert_allclose(fast[allowed], slow[allowed], rtol=rtol)
            assert np.ptp(fast[5, 1]) > (1.0 if cv is None else 0.3)  # the states differ (less, where twitches vary)


def test_pulse_level_path_only_where_a_twitch_stays_in_its_window(cohort_truth):
    """prepare takes the pulse-level path for the zero-order activation, not for DARMA's shaped
    twitch; pulse_tables declines when a pulse's response would leave its window."""
    cohort, truth = cohort_truth
    assert L.prepare(cohort, _true_model(1, truth, "TN-left"), legs=["TN-left"]).pulse_slot is not None
    assert L.prepare(cohort, _true_model(2, truth, "TN-left"), legs=["TN-left"]).pulse_slot is None
    n, p = 100, 40
    window = np.arange(n)[None, :].copy()
    window[0, p : p + MAX_DELAY + 1] = p  # one window of MAX_DELAY + 1 samples from the pulse
    mask = np.ones((1, n), bool)
    pulse, u = np.array([[p]]), np.array([[1.0]])
    assert L.pulse_tables(window, mask, pulse, u, 1, n)["pulse_slot"].tolist() == [[0]]
    assert L.pulse_tables(window, mask, pulse, u, 2, n) == {}  # a response of two samples leaves it at d = MAX_DELAY
    mask[0, p + 3] = False
    assert L.pulse_tables(window, mask, pulse, u, 1, n) == {}  # a sample it reaches is not compared


def test_psis_loo_units_are_seconds_that_hold_a_compared_window(cohort_truth):
    """A segment is a second of a trial at any sampling period, and one with nothing compared in it
    (every sample excluded) is no PSIS-LOO unit: its log-likelihood would be 0 in every draw."""
    cohort, truth = cohort_truth
    leg = "TN-left"
    model = _true_model(3, truth, leg)
    dirty = _excluding(cohort, leg, [(1, 2900, 3100)])  # 29.00–31.00 s of trial 1: segments 29 and 30
    data = L.prepare(dirty, model, trials=(1,), legs=[leg])
    assert data.n_segments == 60
    mask = data.segment_mask[0]
    assert not mask[29] and not mask[30] and mask[28] and mask[31] and mask.sum() == 58
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    seg = np.asarray(L.leg_pointwise(model, {"sigma": 40.0, "nu": 8.0}, x, 4, data.response_length, data.n_segments))
    assert np.all(seg[~mask] == 0.0) and np.all(seg[mask] != 0.0)
    assert L.segment_samples(0.02) == 50 and L.segment_samples(0.005) == 200 and L.segment_samples(0.01) == 100


def test_a_leg_without_a_requested_trial_is_refused(cohort_truth):
    """Fitting trials 1 and 2 where one leg has only trial 1 would fit that leg to trial 1 and say
    both: refused, naming the leg and the trial."""
    cohort, truth = cohort_truth
    short = type(cohort)(tuple(t for t in cohort.trials if not (t.key == "JM-right" and t.trial == 2)), cohort.attrs)
    with pytest.raises(KeyError, match=r"leg JM-right has no trial 2 \(it has \[1\]\)"):
        L.prepare(short, _true_model(3, truth, "TN-left"), trials=(1, 2))


def _ops(jaxpr):
    """Every equation of a jaxpr and of the jaxprs inside it: (primitive, output dtype, output size)."""
    for eqn in jaxpr.eqns:
        for v in eqn.outvars:
            yield eqn.primitive.name, v.aval.dtype, int(np.prod(v.aval.shape))
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else (p,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from _ops(inner)


def test_sums_at_mixed_precision_are_taken_in_double():
    """The likelihood's sums over a leg's terms are taken in double precision (where JAX's x64 is
    on) whatever the terms' precision: 100 001 terms of 0.1 in single precision sum to 100 001
    times 0.1f to double's rounding, which no single-precision sum can (its neighbouring values
    lie 1e-3 apart there)."""
    with jax.enable_x64(True):
        a = jnp.full(100_001, 0.1, jnp.float32)
        want = 100_001 * float(np.float32(0.1))
        assert L._total(a).dtype == jnp.float64
        assert float(L._total(a)) == pytest.approx(want, rel=1e-12)
        assert abs(float(jnp.sum(a)) - want) > 1e-9 * want  # what the sum in single precision gives
    assert L._total(jnp.ones(3, jnp.float32)).dtype == jnp.float32  # without x64 there is no double


@pytest.mark.parametrize("general", [False, True])
def test_mixed_precision_computes_each_term_in_single_and_agrees_with_double(cohort_truth, general):
    """Given single-precision data and double-precision parameters (the fit's ``precision="mixed"``),
    the windows' log density kernels are computed in single precision, and the leg's log-likelihood
    of every delay, shift and threshold state agrees with the one computed in double throughout to
    within 2e-3 (on values of ~1e4), on the pulse-level path and on the (pulse, lag) path."""
    cohort, truth = cohort_truth
    leg = "TN-left"
    model = _true_model(3, truth, leg).add(AngleDelay(threshold=-20.0))
    data = L.prepare(cohort, model, trials=(1, 2), legs=[leg])
    R, K = data.response_length, data.max_shift
    with jax.enable_x64(True):
        model = model.with_params(jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), model.params()))
        noise = {"sigma": jnp.float64(40.0), "nu": jnp.float64(6.0)}
        x32 = {k: jnp.asarray(v[0]) for k, v in data.leg_arrays().items()}
        x64 = {k: v.astype(jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v for k, v in x32.items()}
        if general:
            x32, x64 = _general(x32), _general(x64)
        mixed = np.asarray(L.leg_loglik_by_threshold(model, noise, x32, R, K))
        double = np.asarray(L.leg_loglik_by_threshold(model, noise, x64, R, K))
        assert mixed.dtype == np.float64 and np.abs(double).max() > 5e3
        np.testing.assert_allclose(mixed, double, rtol=0, atol=2e-3)
        ops = list(_ops(jax.make_jaxpr(lambda x: L.leg_loglik_by_threshold(model, noise, x, R, K))(x32).jaxpr))
        W = x32["window_mask"].shape[-1]
        assert any(p == "log1p" and d == jnp.float32 and n >= W for p, d, n in ops)  # the windows' kernels
        assert not any(p == "log1p" and d == jnp.float64 and n >= W for p, d, n in ops)
        ops = list(_ops(jax.make_jaxpr(lambda x: L.leg_loglik_by_threshold(model, noise, x, R, K))(x64).jaxpr))
        assert not any(p == "log1p" and d == jnp.float32 for p, d, n in ops)  # double data: double throughout
