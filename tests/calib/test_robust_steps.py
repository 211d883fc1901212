"""The thesis's IQR step filter (section 4.2.2.1) against an independent re-implementation, and its edge cases."""

import statistics

import numpy as np
import pytest

from dstereo.calib.robust_steps import SURVIVES, UNUSABLE, run_steps, thesis_quartiles
from dstereo.config.calibration import Step, load_config
from dstereo.errors import DstereoError

ABSOLUTE = ("re", "stereo_re")


def _halves_quartiles(values):
    """Q1, Q3 by explicit half-splitting of a sorted list (odd count: the middle value goes to neither half)."""
    s = sorted(values)
    n = len(s)
    if n == 1:
        return s[0], s[0]
    lower = s[: n // 2]
    upper = s[n // 2 + 1:] if n % 2 else s[n // 2:]
    return statistics.median(lower), statistics.median(upper)


def reference_removed_at(table, columns, steps, usable=None):
    """Independent rule: per step, repeat {bounds from the survivors; drop every row outside any bound}.
    Returns removed_at per row: 0 survives, k removed at step k, -1 unusable."""
    rows = range(len(table))
    alive = {i for i in rows if usable is None or usable[i]}
    fate = {i: (0 if i in alive else -1) for i in rows}
    for k, step in enumerate(steps, 1):
        while True:
            drop = set()
            for name, alpha in zip(step.parameters, step.max_error):
                j = columns.index(name)
                if name in ABSOLUTE:
                    drop |= {i for i in alive if table[i][j] > alpha}
                    continue
                q1, q3 = _halves_quartiles([table[i][j] for i in alive])
                lo, hi = q1 - alpha * (q3 - q1), q3 + alpha * (q3 - q1)
                drop |= {i for i in alive if not lo <= table[i][j] <= hi}
            if not drop:
                break
            for i in drop:
                fate[i] = k
            alive -= drop
    return np.array([fate[i] for i in rows])


def test_quartiles_are_medians_of_halves():
    assert thesis_quartiles([7, 1, 3, 5, 2, 6, 4]) == (2.0, 6.0)  # odd: 4 belongs to neither half
    assert thesis_quartiles([8, 1, 3, 5, 2, 6, 4, 7]) == (2.5, 6.5)
    assert thesis_quartiles([1, 2, 3]) == (1.0, 3.0)
    assert thesis_quartiles([2, 5]) == (2.0, 5.0)
    assert thesis_quartiles([4]) == (4.0, 4.0)
    assert thesis_quartiles([6, 7, 15, 36, 39, 40, 41, 42, 43, 47, 49]) == (15.0, 43.0)  # differs from np.percentile
    assert np.percentile([6, 7, 15, 36, 39, 40, 41, 42, 43, 47, 49], 25) != 15.0


def _random_table(seed, n=180):
    rng = np.random.default_rng(seed)
    columns = ("re", "fx", "fy", "k1", "p1")
    table = np.column_stack([
        0.4 + 0.08 * rng.standard_normal(n),
        500 + 5 * rng.standard_t(2, n),  # heavy tails: several IQR passes
        500 + 5 * rng.standard_t(3, n),
        -0.2 + 0.01 * rng.standard_t(2, n),
        1e-3 * rng.standard_t(1.5, n),
    ])
    return columns, table


@pytest.mark.parametrize("seed", range(6))
def test_matches_independent_reimplementation(seed):
    columns, table = _random_table(seed)
    steps = (Step(("re",), (0.5,)), Step(("p1",), (1.5,)), Step(("k1", "fx"), (1.0, 1.5)), Step(("fy",), (0.5,)))
    usable = np.random.default_rng(100 + seed).random(len(table)) > 0.05
    got = run_steps(table, columns, steps, usable)
    expected = reference_removed_at(table.tolist(), columns, steps, usable)
    np.testing.assert_array_equal(got.removed_at, expected)
    assert [s.after for s in got.steps] == [int(((expected == 0) | (expected > k)).sum()) for k in range(1, 5)]
    assert any(s.passes > 1 for s in got.steps)  # the iteration matters on these tables


def test_absolute_limit_removes_above_it_only():
    columns = ("re", "fx")
    table = np.array([[0.3, 1.0], [0.6, 1.0], [0.5, 1.0], [0.51, 1.0]])
    got = run_steps(table, columns, [Step(("re",), (0.5,))])
    np.testing.assert_array_equal(got.removed_at, [0, 1, 0, 1])
    assert got.steps[0].passes == 1 and got.steps[0].after == 2


def test_joint_step_removes_a_row_failing_any_parameter():
    base = np.linspace(0.0, 1.0, 21)
    table = np.column_stack([base, base[::-1]])
    table[3, 0] = 10.0  # fails only a
    table[7, 1] = -10.0  # fails only b
    joint = run_steps(table, ("a", "b"), [Step(("a", "b"), (1.0, 1.0))])
    assert set(np.flatnonzero(joint.removed_at)) == {3, 7}
    only_a = run_steps(table, ("a", "b"), [Step(("a",), (1.0,))])
    assert set(np.flatnonzero(only_a.removed_at)) == {3}


def test_iterates_until_none_is_outside():
    x = np.arange(12.0)  # passes: [1.9, 9.1] on 0..11, [3.1, 7.9] on 2..9, [4.3, 6.7] on 4..7, 5 and 6 stay
    got = run_steps(x[:, None], ("a",), [Step(("a",), (0.1,))])
    assert got.steps[0].passes == 3
    assert list(np.flatnonzero(got.survivors)) == [5, 6]
    alive = x[got.survivors]
    q1, q3 = thesis_quartiles(alive)
    assert alive.min() >= q1 - 0.5 * (q3 - q1) and alive.max() <= q3 + 0.5 * (q3 - q1)
    expected = reference_removed_at(x[:, None].tolist(), ("a",), [Step(("a",), (0.1,))])
    np.testing.assert_array_equal(got.removed_at, expected)


def test_minimum_stops_the_step_and_says_so():
    columns, table = _random_table(1)
    step = Step(("fx",), (0.1,))
    free = run_steps(table, columns, [step])
    assert free.steps[0].after < 120
    stopped = run_steps(table, columns, [step], min_subsets=120)
    s = stopped.steps[0]
    assert s.stopped_by_minimum and s.after >= 120 and "minimum 120" in s.message
    per_step = run_steps(table, columns, [Step(("fx",), (0.1,), min_subsets=150)], min_subsets=120)
    assert per_step.steps[0].after >= 150  # the step's own minimum wins
    assert not run_steps(table, columns, [Step(("re",), (10.0,))], min_subsets=500).steps[0].stopped_by_minimum


def test_step_leaving_no_subset_is_an_error_unless_a_minimum_stops_it():
    columns, table = _random_table(2)
    with pytest.raises(DstereoError, match=r"step 2 \(re <= 0.01 px\) would remove all"):
        run_steps(table, columns, [Step(("fx",), (3.0,)), Step(("re",), (0.01,))])
    kept = run_steps(table, columns, [Step(("re",), (0.01,))], min_subsets=1)
    assert kept.steps[0].stopped_by_minimum and kept.steps[0].after == len(table)


def test_unusable_rows_never_count():
    table = np.array([[1.0], [2.0], [3.0], [4.0], [1000.0], [np.nan]])
    usable = np.array([True, True, True, True, False, False])
    got = run_steps(table, ("a",), [Step(("a",), (1.0,))], usable)
    assert list(got.removed_at) == [SURVIVES] * 4 + [UNUSABLE] * 2
    assert got.stats(1)["a"]["count"] == 4 and got.stats(1)["a"]["mean"] == 2.5


def test_stats_are_the_thesis_numbers():
    table = np.array([[0.3, -2.0], [0.5, -4.0], [0.4, -6.0]])
    s = run_steps(table, ("re", "k1"), []).stats(0)
    assert s["k1"]["mean"] == -4.0 and s["k1"]["std"] == pytest.approx(np.sqrt(8 / 3))
    assert s["k1"]["error_percent"] == pytest.approx(100 * np.sqrt(8 / 3) / 4)
    assert (s["re"]["min"], s["re"]["max"]) == (0.3, 0.5)


def test_generic_over_stereo_columns():
    """The stereo steps of Figure 5.14 run on a stereo table with the same code."""
    from pathlib import Path

    from conftest import require_seed

    seed = require_seed("init-stereo.ini")
    steps = load_config(seed).stereo_steps
    columns = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
    rng = np.random.default_rng(5)
    table = np.column_stack([2.0 + 0.8 * rng.standard_normal(286)] + [rng.standard_t(2, 286) for _ in columns[1:]])
    got = run_steps(table, columns, steps)
    np.testing.assert_array_equal(got.removed_at, reference_removed_at(table.tolist(), columns, steps))
    assert got.steps[0].removed > 0 and got.steps[1].removed > 0


def test_unknown_column_is_an_error():
    with pytest.raises(DstereoError, match=r"step 1: parameter\(s\) \['k3'\]"):
        run_steps(np.zeros((4, 2)), ("re", "fx"), [Step(("k3",), (1.0,))])
