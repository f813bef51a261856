"""Run and report files on a full disk or after a kill (issue 32, item 6): `bh8 eval --out` replaces
each report file whole or not at all, and a row of evaluations.csv cut short (a kill or a full disk
mid-append) is left out by its readers, said so, and never merged with the next row.
"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from bh8_gym.agents.evaluation.run_files import (
    EVALUATION_COLUMNS,
    append_evaluation,
    drop_evaluations_after,
    read_evaluations,
)
from bh8_gym.cli import main

HEADER = ",".join(EVALUATION_COLUMNS) + "\r\n"


def _row(timesteps: int, rate: float = 0.5) -> str:
    return f"{timesteps},{rate},0.3,0.7,12.5,1.5,300.0,10\r\n"


def _eval(out, seed: int, file_size_limit: int | None = None) -> subprocess.CompletedProcess:
    def limit():
        if file_size_limit is not None:
            import resource

            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit, resource.RLIM_INFINITY))

    return subprocess.run(
        [sys.executable, "-m", "bh8_gym.cli", "eval", "--baseline", "loop", "--objects", "primitives-test",
         "--episodes", "1", "--seed", str(seed), "--gif-episodes", "0", "--no-progress", "--out", str(out)],
        capture_output=True, text=True, timeout=300, preexec_fn=limit)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE")
def test_a_report_the_disk_cannot_take_leaves_the_last_one_whole(tmp_path):
    """On a full disk results.json was cut short and the previous report lost with it (the file
    was truncated, then written). Here the kernel refuses writes past 1,000 bytes (RLIMIT_FSIZE:
    table.md fits, results.json of about 1.9 KB does not): the previous results.json stays as it
    was, and the command says so in one line, exit 1."""
    out = tmp_path / "report"
    first = _eval(out, seed=100_000)
    assert first.returncode == 0, first.stderr[-1000:]
    previous = (out / "results.json").read_text()
    assert len(previous) > 1000 and json.loads(previous)["seed"] == 100_000
    second = _eval(out, seed=100_001, file_size_limit=1000)
    assert second.returncode == 1, second.stderr[-1000:]
    assert (out / "results.json").read_text() == previous
    errors = [line for line in second.stderr.splitlines() if line.startswith("bh8 eval:")]
    assert errors == [f"bh8 eval: cannot write the report in {str(out)!r}: [Errno 27] File too large"]
    assert "Traceback" not in second.stderr
    assert not [path.name for path in out.iterdir() if path.name.endswith(".tmp")]  # no temporary left behind


def test_readers_leave_out_rows_cut_short_and_say_which(tmp_path):
    """A kill or a full disk mid-append leaves the last row without its line break (and maybe
    without fields); an older append then ran the next row into it. The reader keeps the complete
    rows and names the others' lines."""
    (tmp_path / "evaluations.csv").write_text(
        HEADER + _row(100) + "200,0.5,0.3,0.7,12.5" + _row(300) + _row(400) + "500,0.75,0.", newline="")
    skipped = []
    rows = read_evaluations(tmp_path, skipped)
    assert [row["timesteps"] for row in rows] == [100.0, 400.0]
    assert skipped == [3, 5]
    assert read_evaluations(tmp_path) == rows  # without `skipped`, the same rows


def test_an_append_after_a_cut_row_starts_a_new_line(tmp_path):
    """The row appended after a cut one (what a resumed run or the next evaluation writes) is read
    back whole instead of being merged into the cut row; a resume drops the cut row and says so."""
    path = tmp_path / "evaluations.csv"
    path.write_text(HEADER + _row(100) + "200,0.5,0.3", newline="")
    append_evaluation(tmp_path, {"timesteps": 300, **{key: 0.25 for key in EVALUATION_COLUMNS[1:]}})
    assert [row["timesteps"] for row in read_evaluations(tmp_path)] == [100.0, 300.0]
    assert drop_evaluations_after(tmp_path, 1000) == [3]
    assert path.read_bytes().decode() == HEADER + _row(100) + "300,0.25,0.25,0.25,0.25,0.25,0.25,0.25\r\n"
    assert drop_evaluations_after(tmp_path, 1000) == []


def test_eval_plots_a_curve_with_a_cut_row_and_says_so(tmp_path, capsys):
    """`bh8 eval --out` plotted evaluations.csv and crashed (a raw traceback) on a row cut short;
    now it plots the complete rows and names the line it left out."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "evaluations.csv").write_text(HEADER + _row(100, 0.2) + _row(200, 0.4) + "300,0.6,0.", newline="")
    out = tmp_path / "report"
    assert main(["eval", "--baseline", "loop", "--objects", "primitives-test", "--episodes", "1", "--gif-episodes",
                 "0", "--no-progress", "--curve", str(run), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"bh8 eval: {str(run / 'evaluations.csv')!r}: left out line(s) 4, cut short" in err
    assert (out / "training_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
