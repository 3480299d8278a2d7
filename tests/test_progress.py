"""Progress by callback: msk_core reports (done, total, task) and draws nothing; the command line draws the bars."""

from __future__ import annotations

from msk_core.progress import counted
from services.commands.progress import ProgressBar


def test_counted_reports_each_finished_step_and_nothing_without_a_callback():
    calls: list[tuple[int, int, str]] = []
    seen = [x for x in counted("abc", lambda done, total, task: calls.append((done, total, task)), "letters")]
    assert seen == ["a", "b", "c"]
    assert calls == [(0, 3, "letters"), (1, 3, "letters"), (2, 3, "letters"), (3, 3, "letters")]
    assert list(counted(range(4), None, "silent")) == [0, 1, 2, 3]


def _run_tasks(bar: ProgressBar) -> None:
    for task, total in (("first (poses)", 3), ("second (frames)", 2)):
        for done in range(total + 1):
            bar(done, total, task)
    bar(0, 5, "aborted (loads)")
    bar(2, 5, "aborted (loads)")
    bar.close()  # a task that stopped early: closed by the caller's close


def test_off_a_terminal_each_task_is_a_line_when_it_starts_and_one_when_it_ends(capsys):
    """Found by a new user's walk: in a log file the bars' carriage returns piled up into one long line."""
    _run_tasks(ProgressBar())
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" done in ")[0] for line in lines] == [
        "first (poses): 3 ...",
        "first (poses): 3",
        "second (frames): 2 ...",
        "second (frames): 2",
        "aborted (loads): 5 ...",
        "aborted (loads): 2",
    ]
    assert "\r" not in "".join(lines)


def test_the_bar_follows_the_tasks(capsys, monkeypatch):
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: tqdm's bars
    bar = ProgressBar()
    for task, total in (("first (poses)", 3), ("second (frames)", 2)):
        for done in range(total + 1):
            bar(done, total, task)
    bar(0, 5, "aborted (loads)")
    bar(2, 5, "aborted (loads)")
    bar.close()  # a task that stopped early: its bar is closed by the caller's close
    err = capsys.readouterr().err
    assert "first (poses): 100%" in err and "3/3" in err
    assert "second (frames): 100%" in err and "2/2" in err
    assert "aborted (loads):  40%" in err and "2/5" in err
