"""The benchmark's table (estimator.bench.summary), from hand-made rows."""
from __future__ import annotations

from tapecell.estimator.bench import Row, summary


def _row(method: str, tip_mm: float, time_s: float, cameras: int) -> Row:
    return Row("c", method, tip_mm, tip_mm, 1.0, time_s, 0.1, cameras)


def test_summary_reports_medians_speedup_and_time_per_camera_count():
    rows = [_row("default", 0.5, 0.010, 2), _row("default", 12.0, 0.012, 2), _row("default", 1.0, 0.020, 3),
            _row("paper", 6.0, 0.100, 2), _row("paper", 7.0, 0.140, 2), _row("paper", 9.0, 0.300, 3)]
    lines = summary(rows, ["default", "paper"]).splitlines()
    default = next(line for line in lines if line.startswith("default ") and "t med by" not in line).split()
    assert default[1] == "3"                       # n
    assert default[2] == "1.00"                    # tip median
    assert default[5] == "1"                       # one gross failure (> 10 mm)
    assert default[8] == "12.00"                   # fit time median [ms]
    assert default[10] == "11.7x"                  # paper's median 140 ms / 12 ms
    by_count = next(line for line in lines if line.startswith("default ") and "t med by" in line)
    assert "2 cameras 11.00 ms (n=2)" in by_count and "3 cameras 20.00 ms (n=1)" in by_count


def test_summary_has_no_camera_split_for_one_camera_count():
    rows = [_row("default", 0.5, 0.010, 2), _row("default", 0.7, 0.012, 2)]
    assert "t med by" not in summary(rows, ["default"])


def test_the_verdict_summary_counts_the_tape_captures_apart_from_garbage():
    """bench.verdict_summary: the "all" row over every capture, and a "not garbage" row over
    the captures of a tape, where "ok" can be right (a garbage mask's "ok" never is)."""
    from tapecell.estimator.bench import VerdictRow, verdict_summary

    rows = [VerdictRow("clean", "c-1", 2, "ok", 0.4, 1.0, 0.02, 2),
            VerdictRow("clean", "c-2", 2, "hidden", 0.5, 1.0, 0.02, 2),
            VerdictRow("garbage", "g-1", 2, "poor_fit", 9.0, 9.0, 0.02, 2, garbage=True)]
    lines = {line.split()[0] if not line.startswith("not garbage") else "not garbage": line
             for line in verdict_summary(rows).splitlines()[1:]}
    assert lines["all"].split()[1:3] == ["3", "33.3"]
    assert lines["not garbage"].split()[2:4] == ["2", "50.0"]
    assert "not garbage" not in verdict_summary(rows[:2])
