import numpy as np
import pytest

from gpomap.errors import EmptyDataError
from gpomap.metrics import expected_calibration_error, fpr_at_tpr, iou, log_loss, reliability_bins, roc_auc, roc_curve


def mann_whitney(labels, scores):
    y = np.asarray(labels, bool)
    s = np.asarray(scores, float)
    pos, neg = s[y][:, None], s[~y][None, :]
    return ((pos > neg).sum() + 0.5 * (pos == neg).sum()) / (pos.size * neg.size)


def test_perfect_and_reversed_rankings():
    y = [False, False, True, True]
    assert roc_auc(y, [0.1, 0.2, 0.8, 0.9]) == 1.0
    assert roc_auc(y, [0.9, 0.8, 0.2, 0.1]) == 0.0
    assert roc_auc(y, [0.5, 0.5, 0.5, 0.5]) == 0.5


def test_small_mixed_case_by_hand():
    # Scores 0.9 P, 0.8 N, 0.7 P, 0.6 N, 0.5 P. Pairs (P, N) ranked right: P0.9 beats both N,
    # P0.7 beats N0.6 only, P0.5 beats none: 3 of 6 pairs = 0.5.
    y = [True, False, True, False, True]
    s = [0.9, 0.8, 0.7, 0.6, 0.5]
    assert roc_auc(y, s) == pytest.approx(3 / 6)
    fpr, tpr, thr = roc_curve(y, s)
    np.testing.assert_allclose(fpr, [0, 0, 0.5, 0.5, 1, 1])
    np.testing.assert_allclose(tpr, [0, 1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])
    np.testing.assert_allclose(thr, [np.inf, 0.9, 0.8, 0.7, 0.6, 0.5])


def test_ties_form_one_step_and_count_half():
    # Scores: P 0.9; a tie at 0.5 of one P and one N; N 0.1.
    y = [True, True, False, False]
    s = [0.9, 0.5, 0.5, 0.1]
    fpr, tpr, thr = roc_curve(y, s)
    np.testing.assert_allclose(thr, [np.inf, 0.9, 0.5, 0.1])
    np.testing.assert_allclose(fpr, [0, 0, 0.5, 1])
    np.testing.assert_allclose(tpr, [0, 0.5, 1, 1])
    # Pairs: (0.9, 0.5) 1, (0.9, 0.1) 1, (0.5, 0.5) half, (0.5, 0.1) 1 -> 3.5 / 4.
    assert roc_auc(y, s) == pytest.approx(0.875)
    # The tie can't be split: reaching TPR 1 (or even 0.95) takes the whole tie, FPR 0.5.
    assert fpr_at_tpr(y, s, 0.95) == pytest.approx(0.5)
    assert fpr_at_tpr(y, s, 0.5) == pytest.approx(0.0)


def test_auc_is_mann_whitney_on_random_tied_data():
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = int(rng.integers(5, 60))
        y = rng.random(n) < 0.4
        y[0], y[1] = True, False
        s = rng.integers(0, 6, n) / 5.0  # few distinct values: many ties
        assert roc_auc(y, s) == pytest.approx(mann_whitney(y, s))


def test_fpr_at_tpr_hand_computed():
    # 20 positives, 10 negatives. Negatives score 0.0..0.9; positives 19 at 1.0 and one at 0.45.
    y = np.r_[np.ones(20, bool), np.zeros(10, bool)]
    s = np.r_[np.full(19, 1.0), 0.45, np.arange(10) / 10]
    # TPR 0.95 (19/20) is reached at threshold 1.0 with no false positives.
    assert fpr_at_tpr(y, s, 0.95) == 0.0
    # TPR 1 needs the threshold down to 0.45: negatives 0.5..0.9 are positive, FPR 5/10.
    assert fpr_at_tpr(y, s, 1.0) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="tpr"):
        fpr_at_tpr(y, s, 0.0)


def test_one_class_is_a_clear_error():
    with pytest.raises(ValueError, match="both classes"):
        roc_auc([True, True], [0.1, 0.2])
    with pytest.raises(EmptyDataError, match="1 negative"):
        roc_curve([False], [0.3])


def test_log_loss_by_hand():
    y = [True, False, True]
    p = [0.8, 0.4, 0.5]
    expected = -(np.log(0.8) + np.log(0.6) + np.log(0.5)) / 3
    assert log_loss(y, p) == pytest.approx(expected)
    # Confident mistakes are capped at -log(eps).
    assert log_loss([True], [0.0], eps=1e-6) == pytest.approx(-np.log(1e-6))
    assert log_loss([1, 0], [1.0, 0.0]) == pytest.approx(-np.log(1 - 1e-6))
    with pytest.raises(ValueError, match="probabilities"):
        log_loss([True], [1.5])


def test_mismatched_lengths_and_bad_labels():
    with pytest.raises(ValueError, match="same length"):
        roc_auc([True, False], [0.1])
    with pytest.raises(ValueError, match="boolean or 0/1"):
        roc_auc([2, 0], [0.1, 0.2])


def test_log_loss_clips_at_1e6_by_default():
    # A grid's hard 0 for an occupied point costs -log(1e-6) = 13.8 nats, not 27.6 (1e-12).
    assert log_loss([True, False], [0.0, 0.0]) == pytest.approx(-np.log(1e-6) / 2)
    assert log_loss([True], [1 - 1e-9]) == pytest.approx(-np.log(1 - 1e-6))


def test_ece_on_a_tiny_set_by_hand():
    # Bins of 0.1. Points: 0.05 (free), 0.15 (occupied), 0.15 (free), 0.95 (occupied), 1.0 (free).
    # Bin 0: mean p 0.05, 0 of 1 occupied -> |0 - 0.05| = 0.05, weight 1/5.
    # Bin 1: mean p 0.15, 1 of 2 -> |0.5 - 0.15| = 0.35, weight 2/5.
    # Bin 9 (holds p = 1): mean p 0.975, 1 of 2 -> 0.475, weight 2/5.
    y = [False, True, False, True, False]
    p = [0.05, 0.15, 0.15, 0.95, 1.0]
    expected = (0.05 + 2 * 0.35 + 2 * 0.475) / 5
    assert expected_calibration_error(y, p) == pytest.approx(expected)
    mean_p, frac, counts = reliability_bins(y, p)
    np.testing.assert_array_equal(counts, [1, 2, 0, 0, 0, 0, 0, 0, 0, 2])
    np.testing.assert_allclose(mean_p[[0, 1, 9]], [0.05, 0.15, 0.975])
    np.testing.assert_allclose(frac[[0, 1, 9]], [0.0, 0.5, 0.5])
    assert np.isnan(frac[2])
    # Perfectly calibrated: half of the 0.5s are occupied.
    assert expected_calibration_error([True, False], [0.5, 0.5]) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="probabilities"):
        expected_calibration_error([True], [1.2])


def test_ece_against_brute_force():
    rng = np.random.default_rng(3)
    p = rng.random(500)
    y = rng.random(500) < p**2
    total = 0.0
    for k in range(10):
        lo, hi = k / 10, (k + 1) / 10
        sel = (p >= lo) & ((p < hi) if k < 9 else (p <= hi))
        if sel.any():
            total += sel.sum() * abs(y[sel].mean() - p[sel].mean())
    assert expected_calibration_error(y, p) == pytest.approx(total / 500)


def test_iou_by_hand():
    a = np.array([[1, 1, 0], [0, 1, 0]], bool)
    b = np.array([[1, 0, 0], [0, 1, 1]], bool)
    assert iou(a, b) == pytest.approx(2 / 4)
    assert np.isnan(iou(np.zeros(3, bool), np.zeros(3, bool)))
