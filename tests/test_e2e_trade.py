"""bench/trade.py: knobs reach the program generator; the summary counts right."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from bench import trade as e2e_trade
from bench.trade import KNOBS
from operator_site import session


@pytest.mark.parametrize("name", list(KNOBS))
def test_every_knob_lists_its_default_among_its_allowed_values(name: str) -> None:
    knob = KNOBS[name]
    assert knob.default in knob.values and len(set(knob.values)) == len(knob.values) >= 2
    assert knob.target in ("sim", "deform", "command", "work_site")
    if knob.target != "work_site":
        for value in knob.values:  # the parameters' own checks accept every value
            e2e_trade._program_maker(knob, value)


def test_a_knob_value_reaches_the_program_generator(monkeypatch) -> None:
    seen = {}

    class _Generated:
        program = "the program"

    def fake_generate(program_id, scene, workpiece, history, X_GP, **kw):
        seen.update(kw)
        return _Generated()

    class _Session:
        scene = SimpleNamespace(robot=SimpleNamespace(X_WB=None, q_home_rad=None))
        robot = workpiece = X_GP = start_X_WO = X_WO = None
        fingers_O = ()
        params = "session params"

        def path_history(self):
            return []

    monkeypatch.setattr(session, "generate_program", fake_generate)
    monkeypatch.setattr(session, "choose_grasp_yaw", lambda *a: None)
    make = e2e_trade._program_maker(KNOBS["sim_dt"], 0.1)
    assert make(_Session(), "p").program == "the program"
    assert seen["sim_params"].dt_s == 0.1 and seen["command_params"] is None
    make = e2e_trade._program_maker(KNOBS["deform_sweeps"], 10)
    make(_Session(), "p")
    assert seen["deform_params"].max_sweeps == 10 and isinstance(
        seen["deform_params"].max_sweeps, int
    )
    assert seen["sim_params"] == "session params"  # untouched knobs keep the session's own


def test_summary_counts_successes_and_takes_errors_of_successes_only() -> None:
    rows = [
        {"seed": 0, "success": True, "final_error_mm": 0.2, "computation_s": 1.0,
         "execute_s": 20.0, "outcome": "done"},
        {"seed": 1, "success": False, "final_error_mm": 40.0, "computation_s": 3.0,
         "execute_s": None, "outcome": "failed: force"},
    ]  # fmt: skip
    s = e2e_trade._summary(rows)
    assert (s["runs"], s["success"], s["final_error_mm_median"]) == (2, 1, 0.2)
    assert s["computation_s_median"] == 2.0 and s["execute_s_median"] == 20.0
    assert s["failures"] == {"1": "failed: force"}


def test_knobs_run_a_few_at_a_time_add_up_and_reuse_the_defaults(monkeypatch, tmp_path) -> None:
    calls: list[tuple] = []

    def fake_run(task, seed, log, work_site_args=(), make_program=None, time_scale=1.0):
        calls.append((seed, work_site_args, make_program is not None, time_scale))
        return {"success": seed != 0, "final_error_mm": 0.2, "final_error_deg": 0.01,
                "stage_s": {"computation": 0.4, "execute": 18.0}, "commands": 9,
                "execution": "done: program complete"}  # fmt: skip

    plotted: list[set] = []
    monkeypatch.setattr(e2e_trade, "run_scripted", fake_run)
    # matplotlib comes with the [bench] extra only; the plot's input is what is checked here.
    monkeypatch.setattr(
        e2e_trade, "_plot", lambda _out, _task, summary: plotted.append(set(summary))
    )
    first = e2e_trade.run(tmp_path, 2, "corner", ("contact_speed",), log=lambda _: None)
    assert len(calls) == 2 * 3  # the default and the two other speeds, two seeds each
    second = e2e_trade.run(tmp_path, 2, "corner", ("surface_stiffness",), log=lambda _: None)
    assert len(calls) == 2 * 3 + 2  # only the one non-default stiffness: the defaults reused
    assert calls[-1][1] == ("--surface-stiffness", "1000.0")
    assert set(second["knobs"]) == {"contact_speed", "surface_stiffness"}
    assert second["knobs"]["contact_speed"] == first["knobs"]["contact_speed"]
    assert second["knobs"]["surface_stiffness"]["1000.0"]["success"] == 1
    lines = (tmp_path / "trade.csv").read_text().splitlines()
    assert len(lines) == 1 + 2 * 4  # header; default, two speeds, one stiffness: two seeds each
    assert plotted == [{"contact_speed"}, {"contact_speed", "surface_stiffness"}]
    # At another time scale nothing is reused: the defaults run again with the knob asked.
    third = e2e_trade.run(
        tmp_path, 2, "corner", ("surface_stiffness",), log=lambda _: None, time_scale=3.0
    )
    assert len(calls) == 2 * 3 + 2 + 2 * 2 and {c[3] for c in calls[-4:]} == {3.0}
    assert set(third["knobs"]) == {"surface_stiffness"} and third["time_scale"] == 3.0
