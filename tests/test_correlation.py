"""Time-correlated corner errors (fusion.estimate.correlation, fusion.qr.pnp.bias.frames_bias_and_residuals;
issue 10.3, clipping x2.2): the residuals' autocorrelation per corner class, the integrated
correlation time and its significance rule, the averaging factors against brute force, the
direction-wise inflation, the smoother's pose-scale floor and the pipeline's use."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_pnp import FOUR, WORLD, aim, body_pose, floor_dets

from fusion import pipeline
from fusion.estimate import correlation as co
from fusion.estimate.variance import NoiseGroup, NoiseScales, VarianceComponent, next_noise_scales
from fusion.qr.pnp import pnp_trajectory
from fusion.qr.pnp.bias import FrameCodeResiduals
from fusion.qr.pnp.whitening import CORNER_CLASSES
from fusion.qr.refine import FALLBACK_SIGMA_PX
from fusion.types import Trajectory

DEC = CORNER_CLASSES.index("decoder")
REF = CORNER_CLASSES.index("refined")


def ar1(rng, n: int, phi: float, shape=(8,)) -> np.ndarray:
    """(n, *shape) unit-variance AR(1) series with lag-1 correlation phi."""
    out = np.empty((n, *shape))
    out[0] = rng.normal(size=shape)
    for i in range(1, n):
        out[i] = phi * out[i - 1] + np.sqrt(1 - phi**2) * rng.normal(size=shape)
    return out


def synthetic_frames(rng, n: int, phi_decoder: float, phi_refined: float = 0.0, codes: int = 3):
    """n frames, each seeing `codes` decoder and `codes` refined codes, every code in every
    frame, residuals AR(1) in time per code (and white across coordinates)."""
    dec = [ar1(rng, n, phi_decoder) for _ in range(codes)]
    ref = [ar1(rng, n, phi_refined) for _ in range(codes)]
    frames = []
    for i in range(n):
        frames.append(
            FrameCodeResiduals(
                tuple(f"d{j}" for j in range(codes)) + tuple(f"r{j}" for j in range(codes)),
                np.array([DEC] * codes + [REF] * codes, dtype=np.int8),
                np.stack([d[i] for d in dec] + [r[i] for r in ref]).astype(np.float32),
            )
        )
    return frames


def test_white_residuals_give_no_inflation():
    rng = np.random.default_rng(0)
    frames = synthetic_frames(rng, 120, 0.0)
    acf = co.class_autocorrelation(np.arange(120), frames)
    for name in CORNER_CLASSES:
        rho, pairs, n, codes = acf[name]
        assert n == 360 and codes == 3 and pairs[0] == 357
        assert co.integrated_time(rho, pairs) == (1.0, 0)
        assert abs(rho[0]) < 0.2


def test_correlated_class_is_found_and_the_other_is_not():
    rng = np.random.default_rng(1)
    phi = 0.7
    frames = synthetic_frames(rng, 150, phi)
    acf = co.class_autocorrelation(np.arange(150), frames)
    rho, pairs, _, _ = acf["decoder"]
    np.testing.assert_allclose(rho[:3], phi ** np.arange(1, 4), atol=0.12)
    tau, used = co.integrated_time(rho, pairs)
    # AR(1): tau = (1 + phi) / (1 - phi) = 5.7; Geyer's window runs while the lag pairs are
    # positive (here 13 lags), so the estimate is not truncated to the significant lags
    assert used >= 3 and abs(tau - (1 + phi) / (1 - phi)) < 1.2
    assert co.integrated_time(*acf["refined"][:2]) == (1.0, 0)


def test_a_gap_in_the_frames_is_not_a_neighbour():
    """Residuals two frames apart (a frame missing between them) count at lag 2, not 1."""
    r = np.ones((1, 8), dtype=np.float32)
    frames = [FrameCodeResiduals(("a",), np.array([DEC], np.int8), r) for _ in range(2)]
    t = np.array([0, 200_000_000], dtype=np.int64)  # 10 fps, one frame missing
    acf = co.class_autocorrelation(co.frame_indices(np.r_[t, 300_000_000][:2]), frames)
    assert acf["decoder"][1][0] == 1  # median interval 0.2 s: one lag
    acf = co.class_autocorrelation(np.array([0, 2]), frames)
    assert acf["decoder"][1][0] == 0 and acf["decoder"][1][1] == 1


def test_geyer_pairs_sum_while_positive_and_never_rise():
    """Geyer's initial monotone sequence: Gamma_0 = 1 + rho(1), Gamma_k = rho(2k) + rho(2k + 1)
    summed while positive, each cut to the smallest before it; tau = -1 + 2 sum Gamma_k."""
    pairs = np.full(8, 400)
    # Gamma_1 = 0.45, Gamma_2 = 0.6 -> cut to 0.45, Gamma_3 = -0.1: the sum ends before lag 6
    rho = np.array([0.5, 0.4, 0.05, 0.4, 0.2, -0.2, 0.1, 0.1])
    kept = co.monotone_sequence(rho, pairs)
    np.testing.assert_allclose(kept, [0.5, 0.4, 0.05, 0.4 * 0.75, 0.2 * 0.75])
    assert co.integrated_time(rho, pairs) == pytest.approx((1 + 2 * kept.sum(), 5))
    assert co.integrated_time(rho, np.full(8, 10))[0] == 1.0  # too few pairs
    # a lag with too few pairs ends the window (its pair with it)
    assert co.integrated_time(rho, np.r_[400, 400, 400, 10, 400, 400, 400, 400]) == pytest.approx(
        (2.9, 1 + 2)
    )


def test_a_weak_first_lag_does_not_end_the_sum():
    """The 800x600 sweep flight's refined corners (BENCHMARKS.md, corr15): rho(1) = 0.02 is not
    significant, the later lags are (0.17 at lags 2-3 with ~600 pairs: 4 sigma) and stay ~0.1
    to lag 19.  The former rule (stop at the first lag below the gate) read tau = 1 and left the
    smoother at NEES 13.4; Geyer's window reads tau ~3.7."""
    rho = np.array(
        [0.023, 0.165, 0.167, 0.112, 0.059, 0.176, 0.091, 0.11, 0.118, 0.08]
        + [0.038, 0.127, 0.062, 0.03, 0.082, 0.023, 0.053, 0.059, 0.038, 0.039]
    )
    pairs = np.arange(615, 595, -1)
    assert rho[0] < co.Z_GATE / np.sqrt(pairs[0])  # lag 1 alone is not significant
    tau, used = co.integrated_time(rho, pairs)
    assert used == 19 and 3.5 < tau < 4.0


def test_white_residuals_rarely_read_correlated():
    """The window is chosen on the same data as the test of its sum: the false-alarm rate on
    white rho stays near the gate's one-sided 5 % (8 % in 2 x 10^4 trials), and a false alarm
    reads a small tau (conservative covariances, not a fault)."""
    rng = np.random.default_rng(7)
    pairs = np.full(co.MAX_LAG, 600)
    taus = [co.integrated_time(rng.normal(0.0, 1.0 / np.sqrt(600), co.MAX_LAG), pairs) for _ in range(5000)]
    hits = [tau for tau, used in taus if used > 0]
    assert len(hits) <= 500  # 10 %
    assert max(hits) < 2.0 and np.median(hits) < 1.5


def test_a_moderate_correlation_is_not_read_white():
    """The fps10_vel5_to5 sweep flight's refined corners (BENCHMARKS.md, twenty-seventh session):
    rho(1..11) 0.09 / 0.08 / 0.05 / 0.10 / ... / 0.02 on 270 to 170 pairs a lag (the lags after
    them made negative here): the window's sum is 2.0 standard errors, tau 1.9.  The former gate
    (3.09, one-sided 10^-3) read it white (tau 1), which left the smoother without inflation or
    pose-scale floor (NEES 7.2; 5.1 with tau applied)."""
    rho = np.array(
        [0.0935, 0.0813, 0.0495, 0.0999, 0.0395, 0.0492, 0.0195, -0.0093, 0.0224, 0.0014, 0.0238]
        + [-0.02] * 9
    )
    pairs = np.r_[[269, 253, 240, 229, 219, 208, 199, 190, 182, 175, 166], np.arange(158, 122, -4)]
    kept = co.monotone_sequence(rho, pairs)
    z = kept.sum() / np.sqrt(np.sum(1.0 / pairs[: len(kept)]))
    assert 1.645 < z < 3.09
    tau, used = co.integrated_time(rho, pairs)
    assert used >= 9 and 1.7 < tau < 2.1


def test_a_series_with_no_lag_1_correlation_but_a_slow_part_is_found():
    """Residuals = a slow AR(1) part (phi 0.9) + a differenced white part whose lag-1
    correlation cancels the slow part's: rho(1) ~ 0, rho(2) ~ 0.3."""
    rng = np.random.default_rng(11)
    n, codes = 200, 3
    frames = []
    slow = [0.45 * ar1(rng, n + 1, 0.9) for _ in range(codes)]
    e = [rng.normal(size=(n + 1, 8)) for _ in range(codes)]
    series = [slow[c][1:] + 0.4 * (e[c][1:] - e[c][:-1]) for c in range(codes)]
    for i in range(n):
        frames.append(
            FrameCodeResiduals(
                tuple(f"r{c}" for c in range(codes)),
                np.array([REF] * codes, dtype=np.int8),
                np.stack([series[c][i] for c in range(codes)]).astype(np.float32),
            )
        )
    rho, pairs, _, _ = co.class_autocorrelation(np.arange(n), frames)["refined"]
    assert abs(rho[0]) < co.Z_GATE / np.sqrt(pairs[0]) < rho[1]
    tau, used = co.integrated_time(rho, pairs)
    assert used >= 5 and tau > 2.5


def test_a_removed_common_error_is_not_counted_again():
    """A constant error per code (a common bias, carried by its consider term) correlates the
    residuals at every lag by its share of their sum of squares; given that sum of squares the
    class reads white again, and its share is reported."""
    rng = np.random.default_rng(12)
    n, codes = 150, 3
    common = rng.normal(0.0, 0.7, size=(codes, 8))
    frames = [
        FrameCodeResiduals(
            tuple(f"r{c}" for c in range(codes)),
            np.array([REF] * codes, dtype=np.int8),
            (common + rng.normal(size=(codes, 8))).astype(np.float32),
        )
        for _ in range(n)
    ]
    traj = trajectory(np.tile(np.eye(6), (n, 1, 1)), n=n)
    G = np.tile(0.5 * np.eye(6), (n, 2, 1, 1))
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2))
    assert inf is not None and report["classes"]["refined"]["tau"] > 5
    sum_sq = n * float(np.sum(common**2))
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2), common_sum_sq={"refined": sum_sq})
    assert inf is None and report["classes"]["refined"]["tau"] == 1.0
    total = sum(float(np.sum(f.whitened.astype(float) ** 2)) for f in frames)
    assert report["classes"]["refined"]["common_share"] == pytest.approx(sum_sq / total, abs=1e-4)


def inflation(rho_dec, used_dec, n=4, share=None):
    """A CorrelationInflation of n frames with the decoder class's rho and lags (refined white),
    class terms: decoder `share` of an identity covariance, refined the rest."""
    share = 0.5 if share is None else share
    L = len(rho_dec)
    rho = np.zeros((2, co.MAX_LAG))
    rho[DEC, :L] = rho_dec
    terms = np.zeros((n, 2, 6, 6))
    terms[:, DEC] = share * np.eye(6)
    terms[:, REF] = (1 - share) * np.eye(6)
    taus = np.ones(2)
    taus[DEC] = 1 + 2 * np.sum(rho_dec[:used_dec])
    used = np.zeros(2, dtype=int)
    used[DEC] = used_dec
    t = np.arange(n, dtype=np.int64) * 100_000_000
    return co.CorrelationInflation(t, terms, rho, used, taus, 50_000_000)


def test_long_average_variance_factor_is_the_share_weighted_tau_and_unit_free():
    """Decoder share s of an identity covariance at tau: 1 + (tau - 1) s; the same when the
    pose's rotation and translation blocks are in very different units (a trace ratio would be
    the translation block's alone)."""
    inf = inflation(np.array([0.6, 0.45]), 2, share=0.25)
    tau = inf.taus[DEC]  # 1 + 2 (0.6 + 0.45) = 3.1
    traj = Trajectory(
        "pnp", inf.timestamps_ns.copy(), np.tile(np.eye(4), (4, 1, 1)), np.tile(np.eye(6), (4, 1, 1))
    )
    assert inf.long_average_variance_factor(traj) == pytest.approx(1.0 + (tau - 1.0) * 0.25)
    # rotation (rad^2) and translation (m^2) of very different sizes, the correlated class
    # holding half the rotation and none of the translation: the mean over whitened directions
    # is 1 + (tau - 1) (3 * 0.5) / 6; a trace ratio would read ~1 (the translation's alone)
    D = np.diag([1e-8] * 3 + [1.0] * 3)
    terms = np.zeros((4, 2, 6, 6))
    terms[:, DEC] = np.diag([0.5e-8] * 3 + [0.0] * 3)
    terms[:, REF] = D - terms[:, DEC]
    scaled = co.CorrelationInflation(inf.timestamps_ns, terms, inf.rho, inf.lags_used, inf.taus, 50_000_000)
    traj_d = Trajectory("pnp", traj.timestamps_ns, traj.T_world_body, np.tile(D, (4, 1, 1)))
    assert scaled.long_average_variance_factor(traj_d) == pytest.approx(1.0 + (tau - 1.0) * 0.25)
    assert inf.long_average_variance_factor(Trajectory("pnp", traj.timestamps_ns, traj.T_world_body)) == 1.0


@pytest.mark.parametrize("two_sided", [False, True])
def test_average_factor_matches_brute_force(two_sided):
    """sum_ij w_i w_j rho(|i - j|) / sum w^2 of the exponential weights, computed directly, and
    n_eff = (sum w)^2 / sum w^2, against average_taus' closed forms."""
    rho_dec = np.array([0.6, 0.45, 0.3, 0.2])
    inf = inflation(rho_dec, 4)
    for a in (0.3, 0.7, 0.9):
        i = np.arange(-400, 401) if two_sided else np.arange(0, 801)
        w = a ** np.abs(i)
        n_eff = w.sum() ** 2 / (w**2).sum()
        full = np.r_[1.0, rho_dec]
        num = sum(
            (1.0 if lag == 0 else 2.0) * full[lag] * np.sum(w[: len(w) - lag] * w[lag:]) for lag in range(5)
        )
        expected = num / (w**2).sum()
        got = inf.average_taus(np.array([[n_eff]]), two_sided)
        assert got[0, DEC, 0] == pytest.approx(expected, rel=2e-3)
        assert got[0, REF, 0] == 1.0


def test_average_factor_limits():
    inf = inflation(np.array([0.5, 0.3]), 2)
    for two_sided in (False, True):
        f = inf.average_taus(np.array([[1.0, 1e9]]), two_sided)
        assert f[0, DEC, 0] == pytest.approx(1.0)
        assert f[0, DEC, 1] == pytest.approx(inf.taus[DEC], rel=1e-4)


def trajectory(covs, n=4):
    T = np.tile(np.eye(4), (n, 1, 1))
    return Trajectory("x", np.arange(n, dtype=np.int64) * 100_000_000, T, np.asarray(covs, dtype=float))


def test_directional_inflation_follows_the_average_per_direction():
    """Where the fused pose holds one frame's information nothing is added; where it holds
    ~10^9 frames' the full (tau - 1) s G; the two directions of one frame independently."""
    inf = inflation(np.array([0.5, 0.3]), 2, share=0.5)
    raw = trajectory(np.tile(np.eye(6), (4, 1, 1)))
    same = inf.directional(raw, raw, two_sided=True)
    np.testing.assert_allclose(same.covariances, raw.covariances, atol=1e-9)
    tight = inf.directional(raw, trajectory(np.tile(1e-9 * np.eye(6), (4, 1, 1))), two_sided=False)
    np.testing.assert_allclose(tight.covariances, inf.add_to(raw).covariances, rtol=1e-6)
    np.testing.assert_allclose(tight.covariances[0], (1 + 0.5 * (inf.taus[DEC] - 1)) * np.eye(6), rtol=1e-6)
    mixed = np.diag([1.0, 1.0, 1.0, 1e-9, 1e-9, 1e-9])
    out = inf.directional(raw, trajectory(np.tile(mixed, (4, 1, 1))), two_sided=False).covariances[0]
    np.testing.assert_allclose(np.diag(out)[:3], 1.0, atol=1e-6)
    np.testing.assert_allclose(np.diag(out)[3:], 1 + 0.5 * (inf.taus[DEC] - 1), rtol=1e-5)


def test_add_to_matches_stamps_within_half_a_frame():
    inf = inflation(np.array([0.5]), 1, n=3)
    raw = Trajectory(
        "x",
        np.array([0, 100_000_000 + 2_000_000, 260_000_000], dtype=np.int64),  # 2 ms late; 60 ms late
        np.tile(np.eye(4), (3, 1, 1)),
        np.tile(np.eye(6), (3, 1, 1)),
    )
    out = inf.add_to(raw).covariances
    added = 0.5 * (inf.taus[DEC] - 1)
    np.testing.assert_allclose(np.diag(out[0]), 1 + added)
    np.testing.assert_allclose(np.diag(out[1]), 1 + added)
    np.testing.assert_allclose(np.diag(out[2]), 1.0)  # 60 ms from the nearest: not within half a frame


def test_solve_inflated_solves_twice_and_inflates_the_second_input():
    inf = inflation(np.array([0.5, 0.3]), 2)
    raw = trajectory(np.tile(np.eye(6), (4, 1, 1)))
    seen = []

    class Result:
        def __init__(self, traj):
            self.trajectory, self.stats = traj, {}

    def fn(frame_t, imu, raw_, load_obs, **kw):
        seen.append(raw_.covariances.copy())
        assert kw == {"config": "c"}
        return Result(trajectory(np.tile(1e-6 * np.eye(6), (4, 1, 1))))

    res = co.solve_inflated(fn, None, None, raw, [], inflation=inf, two_sided=True, config="c")
    assert len(seen) == 2
    np.testing.assert_allclose(seen[0], raw.covariances)
    assert np.all(np.diagonal(seen[1], axis1=1, axis2=2) > 1.5)
    assert res.stats["correlation_inflation"]["trace_ratio_median"] > 1.5


def test_solve_inflated_lets_the_first_solve_go_before_the_second():
    """The first solve's result is only read for the inflation and its noise scales: nothing
    holds it while the second solve runs (a whole flight's poses and covariances)."""
    import gc
    import weakref

    inf = inflation(np.array([0.5, 0.3]), 2)
    raw = trajectory(np.tile(np.eye(6), (4, 1, 1)))
    firsts: list = []

    class Result:
        def __init__(self, traj):
            self.trajectory, self.stats = traj, {"noise_scales": None}

    def fn(frame_t, imu, raw_, load_obs, **kw):
        if firsts:
            gc.collect()
            assert firsts[0]() is None, "the first solve's result is still referenced"
        res = Result(trajectory(np.tile(1e-6 * np.eye(6), (4, 1, 1))))
        firsts.append(weakref.ref(res))
        return res

    for keep in (False, True):
        firsts.clear()
        res = co.solve_inflated(
            fn, None, None, raw, [], inflation=inf, two_sided=True, keep_noise_scales=keep
        )
        assert len(firsts) == 2 and res.stats["correlation_inflation"]["trace_ratio_median"] > 1.5


@pytest.mark.parametrize("block_rows", [1, 3, 7, 4096])
def test_directional_inflation_in_blocks_is_the_whole_to_the_bit(monkeypatch, block_rows):
    """Frames are independent: any block size gives the same covariances, bit for bit (random
    covariances, three classes, frames without a fused pose or finite covariance left as they were)."""
    rng = np.random.default_rng(21)
    n, k = 53, 3

    def spd(m):
        A = rng.normal(size=(m, 6, 6))
        return A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(6)

    t = np.arange(n, dtype=np.int64) * 100_000_000
    terms = spd(n * k).reshape(n, k, 6, 6) * 0.1
    rho = np.zeros((k, co.MAX_LAG))
    rho[:, :3] = rng.uniform(0.1, 0.4, (k, 3))
    inf = co.CorrelationInflation(t, terms, rho, np.array([3, 2, 1]), 1 + 2 * rho.sum(axis=1), 50_000_000)
    R = spd(n)
    R[5, 0, 0] = np.nan  # not finite: left as it was
    raw = Trajectory("pnp", t, np.tile(np.eye(4), (n, 1, 1)), R)
    fused_t = np.delete(t, [9, 30])  # no fused pose at two frames
    fused_T = np.tile(np.eye(4), (len(fused_t), 1, 1))
    fused = Trajectory("smoother", fused_t, fused_T, 0.01 * spd(len(fused_t)))
    monkeypatch.setattr(co, "DIRECTIONAL_BLOCK_ROWS", 10**6)
    whole = inf.directional(raw, fused, two_sided=True).covariances
    monkeypatch.setattr(co, "DIRECTIONAL_BLOCK_ROWS", block_rows)
    for two_sided in (True, False):
        ref = whole if two_sided else None
        if ref is None:
            monkeypatch.setattr(co, "DIRECTIONAL_BLOCK_ROWS", 10**6)
            ref = inf.directional(raw, fused, two_sided=False).covariances
            monkeypatch.setattr(co, "DIRECTIONAL_BLOCK_ROWS", block_rows)
        got = inf.directional(raw, fused, two_sided=two_sided).covariances
        assert np.array_equal(got, ref, equal_nan=True)
    assert not np.array_equal(whole, R, equal_nan=True)  # something was inflated
    assert np.array_equal(whole[[5, 9, 30]], R[[5, 9, 30]], equal_nan=True)


def test_estimate_inflation_white_flight_is_none_and_lengths_checked():
    rng = np.random.default_rng(3)
    frames = synthetic_frames(rng, 60, 0.0)
    traj = trajectory(np.tile(np.eye(6), (60, 1, 1)), n=60)
    G = np.tile(0.5 * np.eye(6), (60, 2, 1, 1))
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2))
    assert inf is None and not report["applied"]
    assert report["classes"]["decoder"]["tau"] == 1.0
    frames = synthetic_frames(rng, 60, 0.8)
    report, inf = co.estimate_inflation(traj, frames, G, np.array([1.0, 2.0]))
    assert inf is not None and report["applied"] and report["classes"]["decoder"]["tau"] > 2
    # only the inflated class's terms are kept: scale 2 x share 0.5
    assert list(inf.classes) == [DEC] and inf.terms(np.arange(60)).shape == (60, 1, 6, 6)
    np.testing.assert_allclose(inf.terms([0])[0, 0], 1.0 * np.eye(6))
    assert co.estimate_inflation(traj, frames, G, np.ones(2), apply=False)[1] is None
    with pytest.raises(ValueError, match="60 frames of residuals"):
        co.estimate_inflation(trajectory(np.tile(np.eye(6), (4, 1, 1))), frames, G, np.ones(2))


def test_terms_of_the_inflated_classes_alone_give_the_same_covariances_to_the_bit():
    """CorrelationInflation keeps the terms of the classes with tau > 1 only, each 6 x 6 as its
    upper triangle in float32 (a 30-minute flight's float64 terms were 31 MB per class, alive at
    the run's peak): add_to and directional are those of all classes' terms, to the bit."""
    rng = np.random.default_rng(13)
    n = 40
    A = rng.normal(size=(n, 2, 6, 6))
    G = np.einsum("ncij,nckj->ncik", A, A)  # (n, 2, 6, 6), PSD
    full = dataclasses.replace(inflation(np.array([0.6, 0.45, 0.3]), 3, n=n, share=0.3), class_terms=G)
    compact = dataclasses.replace(full, class_terms=G[:, [DEC]], classes=np.array([DEC]))
    assert compact.class_terms.shape == (n, 1, 21) and compact.class_terms.dtype == np.float32
    # unpacked symmetric, within float32's rounding
    np.testing.assert_allclose(compact.terms(np.arange(n)), G[:, [DEC]], rtol=1e-6, atol=1e-6)
    B = rng.normal(size=(n, 6, 6))
    raw = trajectory(np.einsum("nij,nkj->nik", B, B) + np.eye(6), n=n)
    fused = trajectory(0.2 * raw.covariances, n=n)
    assert np.array_equal(compact.add_to(raw).covariances, full.add_to(raw).covariances)
    for two_sided in (False, True):
        assert np.array_equal(
            compact.directional(raw, fused, two_sided).covariances,
            full.directional(raw, fused, two_sided).covariances,
        )


def test_pose_scale_floor():
    comps = {NoiseGroup.POSE: VarianceComponent(50.0, 100.0, 10)}
    assert next_noise_scales(NoiseScales(), comps).pose == pytest.approx(0.5)
    assert next_noise_scales(NoiseScales(), comps, pose_floor=1.0) is None  # held at 1: converged
    assert next_noise_scales(NoiseScales(pose=1.5), comps, pose_floor=1.0).pose == 1.0  # 0.75 held at 1
    up = {NoiseGroup.POSE: VarianceComponent(200.0, 100.0, 10)}
    assert next_noise_scales(NoiseScales(), up, pose_floor=1.0).pose == pytest.approx(2.0)


def pnp_flight(n: int, seed: int, phi: float):
    """{ts: detections} of n frames over the four codes from slowly moving poses, every code's
    corners with a per-code AR(1) error in time (0.5 px, lag-1 correlation phi), marked as
    decoder-fallback corners."""
    rng = np.random.default_rng(seed)
    err = {c: ar1(rng, n, phi, shape=(4, 2)) * 0.5 for c in range(4)}
    frames = {}
    for i in range(n):
        T = aim(body_pose(0, 0, 2.5 + 0.1 * np.sin(i / 10), 20 + i, 1.0, -1.0), (0.5, 0.5))
        ts = (i + 1) * 100_000_000
        dets = floor_dets(T, FOUR, ts=ts)
        frames[ts] = [
            dataclasses.replace(
                d, corners_px=np.asarray(d.corners_px) + err[c][i], corner_sigma_px=FALLBACK_SIGMA_PX
            )
            for c, d in enumerate(dets)
        ]
    return frames


def test_pnp_residuals_show_the_corner_errors_correlation():
    from test_pnp import FLOOR_CAM

    for phi, correlated in ((0.0, False), (0.8, True)):
        frames = pnp_flight(80, 5, phi)
        traj, stats = pnp_trajectory(frames, FLOOR_CAM, WORLD, 0.15)
        assert len(stats.frame_code_residuals) == len(traj) == 80
        for r in stats.frame_code_residuals:
            assert r.whitened.shape == (4, 8) and list(r.classes) == [DEC] * 4
        report, inf = co.estimate_inflation(
            traj, stats.frame_code_residuals, stats.frame_class_covariance, np.ones(2)
        )
        assert (inf is not None) == correlated, report
        if correlated:
            assert report["classes"]["decoder"]["tau"] > 2.5


def test_pipeline_carries_the_inflation_only_when_asked():
    from test_pnp import FLOOR_CAM

    frames = pnp_flight(60, 6, 0.8)
    parts = [pipeline.localize_floor_chunk((FLOOR_CAM, WORLD, pipeline.RunConfig(), None), frames)]
    on = pipeline.merge_floor_parts(parts, pipeline.RunConfig())
    assert on.correlation is not None and on.stats["pnp"]["correlation"]["applied"]
    off = pipeline.merge_floor_parts(parts, pipeline.RunConfig(inflate_correlated=False))
    assert off.correlation is None and not off.stats["pnp"]["correlation"]["applied"]
    # the PnP trajectory itself keeps its per-frame covariances
    np.testing.assert_array_equal(on.trajectories["pnp"].covariances, off.trajectories["pnp"].covariances)


def test_excluded_class_is_reported_not_applied():
    rng = np.random.default_rng(4)
    frames = synthetic_frames(rng, 60, 0.8, phi_refined=0.8)
    traj = trajectory(np.tile(np.eye(6), (60, 1, 1)), n=60)
    G = np.tile(0.5 * np.eye(6), (60, 2, 1, 1))
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2), exclude={"refined": "bias"})
    assert report["classes"]["refined"]["tau"] > 2 and report["classes"]["refined"]["not_applied"] == "bias"
    assert inf is not None and inf.taus[REF] == 1.0 and inf.taus[DEC] > 2 and inf.lags_used[REF] == 0
    report, inf = co.estimate_inflation(traj, frames, G, np.ones(2), exclude={"refined": "x", "decoder": "y"})
    assert inf is None and not report["applied"]


def test_solve_inflated_keeps_the_first_solves_noise_scales():
    """The batch smoother's second (inflated) solve takes the first solve's per-camera scales
    as they are (poses x cam0, loads x cam1, tight corners x cam0) and estimates none."""
    from types import SimpleNamespace

    from fusion.estimate import FusionConfig
    from fusion.types import LoadObservation

    inf = inflation(np.array([0.5, 0.3]), 2)
    raw = trajectory(np.tile(np.eye(6), (4, 1, 1)))
    report = {"cameras": {"cam0": {"scale": 1.5}, "cam1": {"scale": 0.25}}}
    load = [LoadObservation(0, "L", np.zeros(3), np.eye(3), p_cam=np.zeros(3), cov_cam=np.eye(3))]
    calls = []

    def fn(frame_t, imu, raw_, load_obs, config):
        calls.append((raw_.covariances.copy(), load_obs[0].cov_cam.copy(), config))
        traj = trajectory(np.tile(1e-6 * np.eye(6), (4, 1, 1)))
        return SimpleNamespace(
            trajectory=traj, stats={"noise_scales": dict(report) if len(calls) == 1 else {}}
        )

    cfg = FusionConfig(corner_noise_scale=2.0)
    res = co.solve_inflated(
        fn, None, None, raw, load, inflation=inf, two_sided=True, keep_noise_scales=True, config=cfg
    )
    (c1, l1, cfg1), (c2, l2, cfg2) = calls
    assert cfg1 is cfg and cfg2.noise_scale_iterations == 0 and cfg2.corner_noise_scale == pytest.approx(3.0)
    assert cfg1.check_noise and not cfg2.check_noise  # the second solve's chi2 is not measured
    np.testing.assert_allclose(l2, 0.25 * np.eye(3))
    inflated = inf.directional(raw, trajectory(np.tile(1e-6 * np.eye(6), (4, 1, 1))), True).covariances
    np.testing.assert_allclose(c2, 1.5 * inflated)
    assert (
        res.stats["noise_scales"]["cameras"] == report["cameras"]
        and res.stats["noise_scales"]["inflated_solve"]
    )


def test_placement_inflated_poses_take_the_placement_class_alone():
    """The floor mount check weighs its poses as the batch smoother does for the floor codes'
    placement (pipeline.placement_inflated): each pose's placement share times its correlation
    time added, the corner classes' left as they are; a floor laid exactly (no placement class)
    leaves the poses unchanged.  A 10 s flight over codes 2 cm / 2 deg off read a 1.30 +- 0.27 deg
    mount pitch as independent frames (thirty-second session)."""
    from fusion.pipeline import placement_inflated

    n, k = 4, co.PLACEMENT + 1
    terms = np.zeros((n, k, 6, 6))
    terms[:, 0] = 0.25 * np.eye(6)
    terms[:, co.PLACEMENT] = 0.5 * np.eye(6)
    taus = np.ones(k)
    taus[0], taus[co.PLACEMENT] = 3.0, 9.0
    t = np.arange(n, dtype=np.int64) * 100_000_000
    both = co.CorrelationInflation(
        t, terms, np.zeros((k, co.MAX_LAG)), np.zeros(k, dtype=int), taus, 50_000_000
    )
    np.testing.assert_array_equal(both.placement_taus(), [1.0] * co.PLACEMENT + [9.0])
    traj = Trajectory("pnp", t, np.tile(np.eye(4), (n, 1, 1)), np.tile(np.eye(6), (n, 1, 1)))
    out = placement_inflated(traj, both)
    np.testing.assert_allclose(out.covariances, np.tile((1.0 + 8.0 * 0.5) * np.eye(6), (n, 1, 1)))
    assert both.long_average_variance_factor(traj) == pytest.approx(1.0 + 2.0 * 0.25 + 8.0 * 0.5)
    exact = inflation(np.array([0.6, 0.45]), 2, n=n)  # corner classes only
    np.testing.assert_array_equal(placement_inflated(traj, exact).covariances, traj.covariances)
    assert placement_inflated(traj, None) is traj and placement_inflated(None, both) is None
