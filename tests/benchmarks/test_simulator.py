"""benchmarks/_simulator.py: the simulator's tools run a few at a time, each report kept only once
its tool finished well, a finished one not run again, a failing one named. A stand-in tool (this
Python, a script in a temporary folder) plays the simulator's: tests never read ../shared."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from benchmarks._simulator import SimJob, run_sim_jobs

TOOL = '''
import json, sys
arg, report = sys.argv[1], sys.argv[sys.argv.index("--json") + 1]
if arg != "crash":
    json.dump({"arg": arg}, open(report, "w"))
sys.exit({"ok": 0, "checks_failed": 2}.get(arg, 1))
'''


@pytest.fixture()
def tools(tmp_path: Path) -> Path:
    folder = tmp_path / "tools"
    folder.mkdir()
    (folder / "tool.py").write_text(TOOL)
    return folder


def test_every_report_is_written_and_a_finished_job_is_not_run_again(tools: Path, tmp_path: Path) -> None:
    done = tmp_path / "out" / "done.json"
    done.parent.mkdir()
    done.write_text('{"arg": "from an earlier run"}')
    jobs = [SimJob("tool.py", ("ok",), tmp_path / "out" / f"job_{k}.json") for k in range(5)]
    run_sim_jobs(Path(sys.executable), [*jobs, SimJob("tool.py", ("ok",), done)], tools=tools)
    assert all(json.loads(job.report.read_text()) == {"arg": "ok"} for job in jobs)
    assert json.loads(done.read_text()) == {"arg": "from an earlier run"}
    assert not list((tmp_path / "out").glob("*.part"))


@pytest.mark.parametrize("arg, ok_codes, message", [
    ("checks_failed", (0,), "exited 2"),
    ("crash", (0, 1, 2), "without writing"),
])
def test_a_failing_tool_stops_the_run_and_is_named(tools: Path, tmp_path: Path, arg: str,
                                                     ok_codes: tuple[int, ...], message: str) -> None:
    job = SimJob("tool.py", (arg,), tmp_path / "bad.json")
    with pytest.raises(RuntimeError, match=f"tool.py {arg} .*{message}"):
        run_sim_jobs(Path(sys.executable), [job], ok_codes=ok_codes, tools=tools)
    assert not job.report.exists()


def test_an_exit_the_caller_accepts_keeps_its_report(tools: Path, tmp_path: Path) -> None:
    job = SimJob("tool.py", ("checks_failed",), tmp_path / "checked.json")
    run_sim_jobs(Path(sys.executable), [job], ok_codes=(0, 2), tools=tools)
    assert json.loads(job.report.read_text()) == {"arg": "checks_failed"}
