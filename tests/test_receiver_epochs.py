"""A receiver's epochs found online from its fixes' stamps alone (a live link's)."""

from __future__ import annotations

import numpy as np

from quadformer.sensors.receiver_epochs import MIN_FIXES, WINDOW_S, ReceiverEpochs


def stamps(n=400, period=0.2, slope=1.0, jitter=0.06, skip=(), seed=0):
    """Epochs every ``period`` s of the receiver's time on an autopilot clock running at ``slope``,
    and their stamps: read 50 ms plus 0 to ``jitter`` s later; the fixes at ``skip`` lost."""
    rng = np.random.default_rng(seed)
    k = np.array([i for i in range(n) if i not in set(skip)])
    epochs = 7.0 + slope * period * k
    return epochs, epochs + 0.05 + rng.uniform(0.0, jitter, len(k))


def restamp(t):
    clock = ReceiverEpochs()
    return np.array([clock.epoch(x) for x in t]), clock


def test_the_stamps_jitter_is_removed_on_a_slow_clock_and_across_lost_fixes():
    for slope in (1.0, 0.97):
        epochs, t = stamps(slope=slope, skip=(150, 151, 260))
        out, clock = restamp(t)
        late = out - epochs
        # every fix after the warm-up near one grid: its epoch plus about the fastest read's 50 ms,
        # within 25 ms from the first restamps and 15 ms once the window holds 12 s of fixes, where
        # the stamps spread over 60 ms
        assert np.ptp(late[MIN_FIXES:]) < 0.025, np.ptp(late[MIN_FIXES:])
        assert np.ptp(late[60:]) < 0.015, np.ptp(late[60:])
        assert abs(np.median(late[60:]) - 0.05) < 6e-3
        assert np.ptp(t[MIN_FIXES + 5:] - epochs[MIN_FIXES + 5:]) > 0.05
        # the IMU must be held back for the late reads: about the jitter's span
        assert 0.04 < clock.allowance < 0.065
        assert clock.restarts == 0 and "epochs" in clock.note()


def test_the_first_fixes_keep_their_stamps_and_times_stay_increasing():
    epochs, t = stamps(n=60)
    out, clock = restamp(t)
    assert np.array_equal(out[:MIN_FIXES - 1], t[:MIN_FIXES - 1])
    assert np.all(np.diff(out) > 0)
    assert ReceiverEpochs().note() is None


def test_a_broken_count_starts_the_clock_again_and_a_long_gap_empties_its_window():
    epochs, t = stamps(n=200)
    t = np.concatenate([t[:100], t[100:] + 0.1])       # half a period lost: the count cannot go on
    out, clock = restamp(t)
    assert clock.restarts == 1
    assert np.all(np.diff(out) > 0)
    # after the restart the stamps are kept until the window holds enough fixes again
    assert np.array_equal(out[100:100 + MIN_FIXES - 1], t[100:100 + MIN_FIXES - 1])
    late = out[100 + MIN_FIXES:] - epochs[100 + MIN_FIXES:] - 0.1
    assert np.ptp(late) < 0.025

    epochs, t = stamps(n=200)
    epochs[60:] += 5 * WINDOW_S + 0.2 * 3
    gap = np.concatenate([t[:60], t[60:] + 5 * WINDOW_S + 0.2 * 3])   # 150 s without a fix, whole periods
    out, clock = restamp(gap)
    assert clock.restarts == 0 and np.all(np.diff(out) > 0)
    # a fresh window: the stamps kept again until it holds enough fixes, then the jitter removed
    assert np.array_equal(out[60:60 + MIN_FIXES - 1], gap[60:60 + MIN_FIXES - 1])
    assert np.ptp(out[60 + MIN_FIXES:] - epochs[60 + MIN_FIXES:]) < 0.025


def test_stamps_too_jittery_for_the_count_are_kept():
    # a 10 Hz receiver read with up to 80 ms of jitter: the count is unreliable, nothing restamped
    epochs, t = stamps(period=0.1, jitter=0.08)
    out, clock = restamp(t)
    moved = np.abs(out - t) > 1e-9
    assert moved.mean() < 0.1, moved.mean()


def test_a_1_hz_receiver_is_restamped_once_its_window_holds_enough_fixes():
    epochs, t = stamps(n=120, period=1.0, jitter=0.06)
    out, clock = restamp(t)
    assert np.array_equal(out[:MIN_FIXES - 1], t[:MIN_FIXES - 1])
    late = out[MIN_FIXES:] - epochs[MIN_FIXES:]
    assert clock.restarts == 0 and np.ptp(late) < 0.02 < np.ptp(t[MIN_FIXES:] - epochs[MIN_FIXES:])
