"""Progress (issue 42): the library says it through its callback (lines, and Steps that count),
the command line draws it on stderr (a bar with the time left on a terminal, lines elsewhere),
quiet with -q."""
from __future__ import annotations

import io
import sys

import pytest

from combined_reality.cli import main
from combined_reality.cli.common import ProgressView
from combined_reality.progress import Step, counter, stage_steps


def test_a_step_is_a_line_that_counts():
    s = Step("  iteration  3: cost 12.5", "iterations", 3, cost=12.5)
    assert s == "  iteration  3: cost 12.5" and isinstance(s, str)  # a printer of lines prints it as it is
    assert (s.task, s.done, s.total, s.figures) == ("iterations", 3, None, {"cost": 12.5})
    heard = []
    staged = stage_steps(heard.append, "1/3 force balance")
    staged("  start from the equation-error fit: ...")  # a fit's own lines: left out
    staged(s)
    assert heard == ["  1/3 force balance: iteration 3, cost 12.5"] and heard[0].task == "1/3 force balance: iterations"
    tick = counter(heard.append, "candidate fits", 4)
    tick("a result")
    tick()
    assert heard[-1] == "  2/4 candidate fits" and (heard[-1].done, heard[-1].total) == (2, 4)
    assert stage_steps(None, "x") is None and counter(None, "x", 3) is None


def test_lines_elsewhere_than_a_terminal_carry_the_time_left(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    clock = iter([0.0, 10.0, 20.0])
    monkeypatch.setattr("combined_reality.cli.common.time.perf_counter", lambda: next(clock))
    view = ProgressView()
    view(Step("  1/4 candidate fits", "candidate fits", 1, 4))
    view(Step("  2/4 candidate fits", "candidate fits", 2, 4))  # 10 s per fit since the first: 20 s left
    view("a plain line")
    assert err.getvalue().splitlines() == ["  1/4 candidate fits", "  2/4 candidate fits (about 20 s left)",
                                           "a plain line"]


def test_a_terminal_gets_a_bar_with_the_cost(monkeypatch):
    err = io.StringIO()
    err.isatty = lambda: True
    monkeypatch.setattr(sys, "stderr", err)
    view = ProgressView()
    for it, cost in ((1, 2.4e6), (2, 8.1e4)):
        view(Step(f"  iteration {it}: cost {cost:g}", "iterations", it, cost=cost))
    view(Step("  1/3 stages", "stages", 1, 3))  # a second task: a bar of its own
    view("wrote result.json")  # clears the bars, printed above
    out = err.getvalue()
    assert "iterations: 2" in out and "cost 8.1e+04" in out and "stages: 1/3" in out
    assert out.rstrip().endswith("wrote result.json") and view.bars == {}


def test_identify_reports_its_iterations_with_the_cost_and_is_quiet_with_q(cyl_a, run_a, tmp_path, capsys):
    from combined_reality.files import write_run
    from combined_reality.identify import IdentifyOptions, identify

    heard = []
    identify(cyl_a, [run_a.slice(0, 4000)], IdentifyOptions(max_iter=3, restart_misfit=False), progress=heard.append)
    steps = [s for s in heard if isinstance(s, Step)]
    assert [s.done for s in steps] == list(range(1, len(steps) + 1)) and len(steps) >= 2
    assert all(s.task == "iterations" and s.figures["cost"] > 0 for s in steps)
    path = tmp_path / "r.csv"
    write_run(path, run_a.slice(0, 4000))
    assert main(["identify", "--config", str(cyl_a.source), str(path), "--max-iter", "2", "-q"]) in (0, 1)
    err = capsys.readouterr().err
    assert "iteration  1" not in err and "identifying" not in err


@pytest.mark.parametrize("argv", [["simulate", "--duration", "6", "-o", "{tmp}/s.csv"]])
def test_simulate_of_a_long_run_says_the_time_left(argv, cyl_a, tmp_path, capsys):
    assert main([a.format(tmp=tmp_path) for a in argv] + ["--config", str(cyl_a.source)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert any(line.startswith("  simulated") and "left)" in line for line in err), err
