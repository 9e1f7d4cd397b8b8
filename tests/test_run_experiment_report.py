"""``curlnav experiment``'s report is made from saved runs alone and marks each finding by our
numbers (the runs themselves are exercised by tests/test_scheduler_curriculum.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from curlnav.run.experiment import BUDGETS, fig4_plan, write_experiment_report
from curlnav.run.record import EVAL_FIELDS, CsvLog
from curlnav.sim import get_world
from curlnav.worlds.difficulty.rank import rank, write_outputs


def _eval_rows(run_dir, successes):
    log = CsvLog(run_dir / "eval.csv", EVAL_FIELDS)
    for i, success in enumerate(successes):
        log.write({"evaluation": i + 1, "env_steps": 1000 * (i + 1), "world": run_dir.name, "pair": "held-out",
                   "episodes": 10, "success_rate": success, "collisions_per_episode": 0.0, "rows": 1})
    log.close()


def test_the_report_states_finding_1_from_table_i_runs_and_picks_the_fine_tuning_source_the_papers_way(tmp_path):
    rows = rank([get_world(w) for w in ("open-room", "door-corridor", "bench-36m")])
    write_outputs(rows, tmp_path / "ranking")
    ranked = [{"name": r.name, "difficulty": r.difficulty, "category": r.category} for r in rows]
    easy = [r.name for r in rows if r.category == "easy"]
    assert easy and len(easy) < len(rows)
    for i, r in enumerate(rows):  # easier worlds train better, as the paper found
        (tmp_path / "table1" / r.name).mkdir(parents=True)
        _eval_rows(tmp_path / "table1" / r.name, [0.1, 0.9 - 0.3 * i])
    report = write_experiment_report(tmp_path, BUDGETS["small"]).read_text()
    assert "| 1. The difficulty metrics predict which worlds train from scratch (Table I) | reproduced |" in report
    assert "**Reduced budgets**" in report and "No ablation runs yet." in report
    assert "| 3. S1+S2 is the most sample-efficient curriculum (Fig. 5) | not reproduced | no runs |" in report
    assert (tmp_path / "table1.png").stat().st_size > 10_000
    source, hard = fig4_plan(tmp_path, ranked, BUDGETS["small"], {r.name: tmp_path for r in rows})
    assert source == rows[0].name and hard and all(h not in easy for h in hard)


@pytest.mark.slow
def test_report_only_without_runs_is_one_line_and_exit_2(tmp_path):
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "experiment", "--out", str(tmp_path),
                             "--report-only"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "no ranking in" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_report_only_names_the_budget_the_runs_were_made_with(tmp_path):
    import json

    rows = rank([get_world(w) for w in ("open-room", "door-corridor")])
    write_outputs(rows, tmp_path / "ranking")
    (tmp_path / "experiment.json").write_text(json.dumps({"budget": {"name": "small"}}))
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "experiment", "--out", str(tmp_path),
                             "--report-only", "--budget", "full"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "made with the small budget" in result.stdout
    assert (tmp_path / "report.md").read_text().startswith("# curlnav experiment report (small budget)")
