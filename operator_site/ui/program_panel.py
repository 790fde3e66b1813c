"""The page's program panel: the task made into a robot program, shown for confirmation, sent
on a second click; and the stop."""

from __future__ import annotations

import threading
import time

import viser

from operator_site.link import WorkSiteLink
from operator_site.program import choose_grasp_yaw, generate_program
from operator_site.task import TaskSession
from operator_site.ui.text import plain


class ProgramPanel:
    """The program panel of :class:`~operator_site.ui.page.OperatorPage`."""

    link: WorkSiteLink
    session: TaskSession
    pending_program: object
    _programs_made: int
    _lock: threading.Lock

    def _build_program_panel(self, gui: viser.GuiApi) -> None:
        """The panel's widgets, in the folder ``gui`` has open, and their callbacks."""
        self.program_button = gui.add_button("make the robot program")
        self.progress = gui.add_progress_bar(0.0, visible=False, animated=True)
        self.program_md = gui.add_markdown("")
        self.send_button = gui.add_button("send it to the robot", disabled=True)
        # The panel scrolls: a second stop where the operator's eyes are after sending.
        gui.add_button("STOP", color="red").on_click(lambda _: self.on_stop())
        self.program_button.on_click(lambda _: self.on_make_program())
        self.send_button.on_click(lambda _: self.on_send_program())

    def on_stop(self) -> None:
        """The stop button: stop the robot now."""
        self.link.send_stop("operator pressed stop")
        self.program_md.content = "**stop sent to the work site**"

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
            self._programs_made += 1
            program_id = f"{name}-{int(time.time())}-{self._programs_made}"
            X_GP = choose_grasp_yaw(self.session.start_X_WO, self.session.X_GP)
            try:
                made = generate_program(
                    program_id,
                    self.session.scene,
                    name,
                    self.session.path_history(),
                    X_GP,
                    attached_O=self.session.fingers_O,
                    sim_params=self.session.params,
                    X_WO=self.session.X_WO,
                    progress=self._show_progress,
                )
            except ValueError as e:  # ProgramRefusedError says which command and why
                self.pending_program = None
                self.program_md.content = f"⚠ no program: {plain(e)}"
                self.progress.visible = False
                return
            self.pending_program = made.program
        self.progress.value = 100.0
        self._show_path(made.raw.centres_W, made.deformed.path.centres_W)
        lines = [
            f"**program {plain(program_id)}**, {len(made.program.commands)} commands; path "
            f"{made.raw.length_m() * 1e3:.0f} → {made.deformed.path.length_m() * 1e3:.0f} mm "
            f"(grey: as dragged, green: as the robot will go):"
        ]
        for i, c in enumerate(made.program.commands):
            p = c.X_WP[:3, 3]
            kept = ", ".join(x.object for x in c.contacts)
            contacts = f" keeping {plain(kept)}" if c.contacts else ""
            lines.append(
                f"{i}. {plain(c.kind)} to ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m at "
                f"{c.speed_mps * 1000:.0f} mm/s{contacts}"
            )
        lines.append("Check the green path in the 3D view, then send it.")
        self.program_md.content = "  \n".join(lines)
        self.progress.visible = False
        self.send_button.disabled = False

    def _show_progress(self, fraction: float, stage: str) -> None:
        self.progress.value = 100.0 * fraction
        self.program_md.content = f"making the program: {plain(stage)}…"

    def on_send_program(self) -> None:
        """Second confirmation: send the pending program to the work site."""
        program, self.pending_program = self.pending_program, None
        self.send_button.disabled = True
        if program is None:
            return
        self.link.send_program(program)
        self.program_md.content += f"  \nsent to the work site {plain(self.link.site_id)}"
