"""Progress in a log: where stderr is not a terminal (a grid run in the background, a batch job), long work
prints plain lines with its count, rate and ETA as it goes, not one bar when it ends."""
from __future__ import annotations

import pytest
from rich.progress import Progress

from lumibench import progress


class FakeClock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch):
    c = FakeClock()
    monkeypatch.setattr(progress.time, "monotonic", c)
    return c


def _lines(capsys) -> list[str]:
    return capsys.readouterr().err.splitlines()


def test_a_grid_in_a_log_prints_each_finished_job_with_its_rate_and_eta(capsys, clock):
    def jobs():
        for name in ("a", "b", "c", "d"):
            clock.now += 60.0  # each job takes a minute
            yield name

    done = list(progress.track(jobs(), total=4, description="method jobs", unit="jobs",
                               label=lambda j: f"job {j} ok"))
    assert done == ["a", "b", "c", "d"]
    assert _lines(capsys) == [
        "method jobs: 0/4, 0:00:00 elapsed",
        "method jobs (last: job a ok): 1/4, 60 s/job, 0:01:00 elapsed, ETA 0:03:00",
        "method jobs (last: job b ok): 2/4, 60 s/job, 0:02:00 elapsed, ETA 0:02:00",
        "method jobs (last: job c ok): 3/4, 60 s/job, 0:03:00 elapsed, ETA 0:01:00",
        "method jobs (last: job d ok): 4/4, 60 s/job, 0:04:00 elapsed, ETA 0:00:00",
    ]


def test_a_fast_loop_prints_a_line_per_interval_and_always_its_last(capsys, clock):
    with progress.make_progress() as bar:
        assert isinstance(bar, progress.LineProgress)
        task = bar.add_task("stage 1", total=100, completed=0, rate="")
        for it in range(1, 101):
            clock.now += 1.0  # an iteration a second: lines at 30, 60 and 90 s, then the end
            bar.update(task, completed=it, rate="1.0 it/s", description=f"stage 1  loss {1 / it:.3f}")
    lines = _lines(capsys)
    assert [ln.split(":")[0] for ln in lines] == ["stage 1", "stage 1  loss 0.033", "stage 1  loss 0.017",
                                                  "stage 1  loss 0.011", "stage 1  loss 0.010"]
    assert lines[1].endswith("30/100, 1.0 it/s, 0:00:30 elapsed, ETA 0:01:10")
    assert lines[-1].endswith("100/100, 1.0 it/s, 0:01:40 elapsed, ETA 0:00:00")


def test_a_resumed_task_counts_its_rate_from_where_it_resumed(capsys, clock):
    bar = progress.LineProgress(interval=10.0)
    task = bar.add_task("stage 2", total=1500, completed=1000, rate="")
    clock.now += 10.0
    bar.update(task, completed=1100)  # 100 iterations in 10 s since the resume: 400 left take 40 s
    assert _lines(capsys)[-1] == "stage 2: 1100/1500, 0:00:10 elapsed, ETA 0:00:40"


def test_disabled_prints_nothing(capsys, clock):
    assert list(progress.track(range(3), description="quiet", disable=True)) == [0, 1, 2]
    assert capsys.readouterr().err == ""


def test_a_terminal_gets_the_rich_bar(monkeypatch):
    monkeypatch.setattr(progress.Console, "is_terminal", property(lambda self: True))
    assert isinstance(progress.make_progress(), Progress)


@pytest.mark.parametrize("speed, unit, text", [(12.5, "it", "12.50 it/s"), (1 / 312, "jobs", "312 s/job"),
                                               (0.5, "frames", "2 s/frame"), (None, "it", "")])
def test_rates_slower_than_one_a_second_read_as_seconds_each(speed, unit, text):
    assert progress._rate(speed, unit) == text
