"""Progress off a terminal (a log file, a batch job): plain lines at every 10%, nothing when quiet."""

from lookingglass.progress import Reporter


def test_progress_lines_when_not_a_terminal(capsys):
    assert list(Reporter().track(range(20), description="scenes")) == list(range(20))
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("scenes:")]
    assert [line.split()[1] for line in lines] == [f"{k}/20" for k in range(2, 21, 2)]
    assert lines[-1].endswith("~0 s left)")


def test_quiet_prints_nothing(capsys):
    assert list(Reporter(quiet=True).track(iter(range(5)), total=5, description="x")) == list(range(5))
    assert capsys.readouterr().err == ""
