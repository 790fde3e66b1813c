"""The work site's reports in an operator's words: each message the work site sends is named
in a sentence; an unknown one is shown as it is; the program's own id is shortened."""

from __future__ import annotations

import pytest

from operator_site.ui.words import failure_words, in_words, short_program_name, step_of

# Messages as the work site's executor and server write them.
FAILED = {
    "command 3: contact with frame not verified: 0.0 N along its normal, below 1.0 N (wrist "
    "force [-4.1, -0.6, 5.0] N; table 5.0 N along [0.0, 0.0, 1.0])": "did not press on the frame",
    "command 2: reached its target without contact": "without touching",
    "command 1: nothing between the fingers (they closed to 0.4 mm)": "closed on nothing",
    "command 1: the fingers touched something on the way down to the grasp": "on its way down",
    "command 4: external force 31.2 N exceeds the limit of 30.0 N": "more force",
    "command 5: contact did not settle in 4 s": "did not come to rest",
    "command 2: on the way: joint_3 would swing 1.20 rad at once to another arm configuration": (
        "another arm configuration"
    ),
    "command 2: on the way: no inverse kinematics solution": "cannot reach every pose",
    "command 0: the fingers closed to 57.6 mm where the hex_prism is 50.0 mm wide: they hold "
    "something else": "narrower or wider than the hex&#95;prism",
    "command 0: holding 150 g where the l_block weighs 225 g: the fingers hold something else": (
        "does not weigh what the l&#95;block does"
    ),
    "command 0: the wedge's weight pulls 17 mm from where the model puts it in the grip: the "
    "block is held elsewhere along it, or turned from where the model has it": "hangs in the "
    "gripper off",
}
REFUSED = {
    "command 6 (contact_move): gripper target [0.9, 0.0, 0.1] m is outside the workspace "
    "[0.1, -0.5, 0.0]–[0.8, 0.5, 0.6] m": "outside the robot's work area",
    "command 0 (contact_move): nothing is held (a guarded_grasp must come first)": "before it "
    "grasps",
    "command 2 (free_move): on the way, joint_5 at its limit": "cannot reach every pose",
}


@pytest.mark.parametrize(("message", "words"), FAILED.items())
def test_each_failure_the_work_site_sends_is_said_in_words(message: str, words: str) -> None:
    said = in_words("failed", message)
    assert words in said.sentence
    assert said.sentence.startswith("The robot stopped the program. At step ")
    assert "N along" not in said.sentence  # the engineering detail stays in the detail
    assert said.detail  # one click away


@pytest.mark.parametrize(("message", "words"), REFUSED.items())
def test_refusals_say_nothing_moved_and_why(message: str, words: str) -> None:
    said = in_words("refused", message)
    assert said.sentence.startswith("The work site refused the program before moving.")
    assert words in said.sentence


def test_steps_are_counted_from_one_as_the_page_lists_them() -> None:
    assert step_of("command 0 (guarded_grasp): x") == 1
    assert step_of("command 3: x") == 4
    assert step_of("program complete") is None
    assert failure_words("command 0: reached its target without contact").startswith(
        "At step 1, the block"
    )


def test_an_unknown_message_is_shown_as_it_is_and_escaped() -> None:
    said = in_words("failed", "command 2: <b>a new kind of failure</b>")
    assert "a new kind of failure" in said.sentence
    assert "<b>" not in said.sentence
    assert failure_words("something else entirely").startswith("something else")


def test_stops_name_who_stopped() -> None:
    assert in_words("stopped", "stop: operator pressed stop").sentence == "You stopped the robot."
    assert "heard nothing" in in_words("stopped", "no heartbeat from the operator for 2 s").sentence
    assert "internal fault" in in_words("stopped", "work-site fault: control: boom").sentence
    assert in_words("done", "program complete").detail == ""


def test_program_names_are_short() -> None:
    assert short_program_name("cube-1795746506-2") == "cube #2"
    assert short_program_name("tall_block-resumed-1795746506-7") == "tall&#95;block&#45;resumed #7"
    assert short_program_name("crafted") == "crafted"
