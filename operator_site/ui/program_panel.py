"""The page's program panel: the task made into a robot program, shown for confirmation, sent
on a second click, saved, loaded and sent again; and the stop."""

from __future__ import annotations

import threading
from pathlib import Path

import viser

from operator_site.failures import RunError
from operator_site.link import WorkSiteLink
from operator_site.session import OperatorSession, load_program, save_program
from operator_site.task import TaskSession
from operator_site.ui.status import log_details_markdown, log_markdown
from operator_site.ui.text import plain
from operator_site.ui.words import short_program_name
from protocol import MotionProgram

DEFAULT_PROGRAM_FILE = "program.msgpack"
RECOVERY_BUTTONS = {"retract": "back off", "release": "open the gripper", "home": "go home"}
RECOVERY_HELP = (
    "**After a failure or a stop**: *back off* moves the gripper away from what it presses; "
    "*open the gripper* lets the block go; *go home* lifts clear of the blocks and parks the "
    "arm. Each is a short program the work site checks and runs; STOP ends it. *Resume* goes "
    "on with a stopped program from the command it was stopped in, if nothing ran since."
)


class ProgramPanel:
    """The program panel of :class:`~operator_site.ui.page.OperatorPage`."""

    link: WorkSiteLink
    session: TaskSession
    op: OperatorSession
    pending_program: MotionProgram | None
    last_program: MotionProgram | None
    _log_shown: object = ()  # what the log shows: (count, newest id, seq), None for none
    _lock: threading.Lock

    def _build_program_panel(self, gui: viser.GuiApi) -> None:
        """The panel's widgets, in the folder ``gui`` has open, and their callbacks."""
        self.program_button = gui.add_button("make the robot program")
        self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
        self.program_md = gui.add_markdown("")
        # The commands one click away: the send button, and the log under it, stay in view.
        with gui.add_folder("the program's commands", expand_by_default=False):
            self.commands_md = gui.add_markdown("no program yet")
        self.send_button = gui.add_button("send it to the robot", disabled=True)
        # Where the operator's eyes are after sending: what the robot does, newest first, a
        # second stop, and the ways back after a failure.
        self.log_md = gui.add_markdown(log_markdown([]))
        gui.add_button("STOP", color="red").on_click(lambda _: self.on_stop())
        gui.add_markdown(RECOVERY_HELP)
        self.recovery_buttons = []
        for action, label in RECOVERY_BUTTONS.items():
            button = gui.add_button(label)
            button.on_click(lambda _, a=action: self.on_recover(a))
            self.recovery_buttons.append(button)
        resume = gui.add_button("resume the stopped program")
        resume.on_click(lambda _: self.on_resume())
        self.recovery_buttons.append(resume)
        with gui.add_folder("the work site's own words", expand_by_default=False):
            self.log_details_md = gui.add_markdown(log_details_markdown([]))
        self.program_file = gui.add_text("program file", DEFAULT_PROGRAM_FILE)
        self.save_program_button = gui.add_button("save the program")
        self.load_program_button = gui.add_button("load a program")
        self.save_program_button.on_click(lambda _: self.on_save_program(self.program_file.value))
        self.load_program_button.on_click(lambda _: self.on_load_program(self.program_file.value))
        self.program_button.on_click(lambda _: self.on_make_program())
        self.send_button.on_click(lambda _: self.on_send_program())

    def _show_log(self, reports) -> None:
        """The execution log and its detail, redrawn only when a report came in."""
        newest = (len(reports), reports[-1].program_id, reports[-1].seq) if reports else None
        if newest == self._log_shown:
            return
        self._log_shown = newest
        self.log_md.content = log_markdown(reports)
        self.log_details_md.content = log_details_markdown(reports)

    def _task_changed(self) -> None:
        """The task the program was made from changed (another block, an undo, a reset, a new
        model, a loaded task): its program and paths are no longer it."""
        self._show_path(None, None)
        if self.pending_program is not None:
            self.pending_program = None
            self.send_button.disabled = True
            self.program_md.content = "The task changed: make its program again."
            self.commands_md.content = "no program yet"

    def on_stop(self) -> None:
        """The stop button: stop the robot now."""
        self.link.send_stop("operator pressed stop")
        # Below the program, not instead of it: the operator still sees what was stopped.
        shown = self.program_md.content
        self.program_md.content = "  \n".join(
            filter(None, [shown, "**stop sent to the work site**"])
        )

    def on_recover(self, action: str) -> None:
        """A way back after a failure or a stop (:mod:`operator_site.recovery`)."""
        try:
            with self._lock:
                program = self.op.recover(action)
        except (RuntimeError, ValueError) as e:
            self.program_md.content = f"⚠ {plain(RECOVERY_BUTTONS[action])}: {plain(e)}"
            return
        self.program_md.content = (
            f"**{plain(RECOVERY_BUTTONS[action])}** sent as "
            f"{short_program_name(program.program_id)}: follow it in the log below"
        )

    def on_resume(self) -> None:
        """Go on with the last program sent (or loaded), stopped, from the command it was
        stopped in: the work site refuses, saying why, if another program ran since."""
        program = self.last_program
        if program is None:
            self.program_md.content = "⚠ resume: no program sent or loaded to resume"
            return
        with self._lock:
            sent = self.op.resume(program)
        self.last_program = sent
        self.program_md.content = (
            f"**resume** of {short_program_name(program.program_id)} sent as "
            f"{short_program_name(sent.program_id)}: follow it in the log below"
        )

    def on_make_program(self) -> None:
        """Turn the task into a robot program (§VI: the dragged path deformed, fitted with few
        moves keeping its required contacts, checked), and show it for confirmation."""
        self.progress.visible = True
        self.progress.value = 0.0
        self.send_button.disabled = True
        with self._lock:
            name = self.session.workpiece
            sim = self.session.sim
            if name is None or sim is None or len(sim.history) < 2:
                self.program_md.content = "Pick a block and move it first."
                self.progress.visible = False
                return
            try:
                made = self.op.make_program(progress=self._show_progress)
            except (RunError, ValueError) as e:  # no grasp; refused or infeasible: why
                self.pending_program = None
                self.program_md.content = f"⚠ no program: {plain(e)}"
                self.progress.visible = False
                return
            self.pending_program = made.program
        self.progress.value = 100.0
        self._show_path(made.raw.centres_W, made.deformed.path.centres_W)
        lines = [
            f"**program {short_program_name(made.program.program_id)}**, "
            f"{len(made.program.commands)} commands; path "
            f"{made.raw.length_m() * 1e3:.0f} → {made.deformed.path.length_m() * 1e3:.0f} mm "
            f"(grey: as dragged, green: as the robot will go)."
        ]
        lines.append(
            "Check the green path in the 3D view (the commands are in the folder below), then "
            "send it."
        )
        self.program_md.content = "  \n".join(lines)
        self.commands_md.content = "  \n".join(_command_lines(made.program))
        self.progress.visible = False
        self.send_button.disabled = False

    def _show_progress(self, fraction: float, stage: str) -> None:
        self.progress.value = 100.0 * fraction
        self.program_md.content = f"making the program: {plain(stage)}…"

    def on_send_program(self) -> None:
        """Second confirmation: send the pending program to the work site (a program sent
        before goes again under a new id: the work site runs each id once)."""
        program, self.pending_program = self.pending_program, None
        self.send_button.disabled = True
        if program is None:
            return
        with self._lock:
            sent = self.op.send(program)
        self.last_program = sent
        self.program_md.content += (
            f"  \nsent to the work site {plain(self.link.site_id)} as "
            f"{short_program_name(sent.program_id)}: follow it in the log below"
        )

    def on_save_program(self, path: str) -> None:
        """Save the program made last (pending or sent) to ``path``."""
        program = self.pending_program or self.last_program
        if program is None:
            self.program_md.content = "⚠ no program to save: make one first"
            return
        try:
            save_program(path, program)
        except OSError as e:
            self.program_md.content = f"⚠ could not save to {plain(path)}: {plain(e.strerror)}"
            return
        self.program_md.content = (
            f"program {short_program_name(program.program_id)} saved to "
            f"{plain(Path(path).resolve())}"
        )

    def on_load_program(self, path: str) -> None:
        """Load a saved program and show it, ready to be sent (under a new id)."""
        try:
            program = load_program(path)
        except ValueError as e:
            self.program_md.content = f"⚠ {plain(e)}"
            return
        self.last_program = program  # as it was sent, for a resume after a restart
        self.pending_program = program = self.op.renamed(program)
        self._show_path(None, None)
        lines = [
            f"**program {short_program_name(program.program_id)}** (a new id) loaded from "
            f"{plain(path)}, {len(program.commands)} commands (in the folder below).",
            "It runs as it was made: check that the blocks lie as they did then.",
        ]
        self.program_md.content = "  \n".join(lines)
        self.commands_md.content = "  \n".join(_command_lines(program))
        self.send_button.disabled = False


def _command_lines(program: MotionProgram) -> list[str]:
    """One line a command, for the page (outside text through :func:`plain`)."""
    lines = []
    for i, c in enumerate(program.commands):
        p = c.X_WP[:3, 3]
        kept = ", ".join(x.object for x in c.contacts)
        contacts = f" keeping {plain(kept)}" if c.contacts else ""
        lines.append(
            f"{i + 1}\\. {plain(c.kind)} to ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m at "
            f"{c.speed_mps * 1000:.0f} mm/s{contacts}"
        )
    return lines
