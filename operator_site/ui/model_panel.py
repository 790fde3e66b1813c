"""The page's model panel: the recognitions, accepted one by one or all at once (or the scene
file's layout instead), and blocks taken out of the model."""

from __future__ import annotations

import math
import threading

import viser

from models.scene import Scene
from operator_site.link import WorkSiteLink
from operator_site.model_editor import WorkSiteModel
from operator_site.placement import check_placement
from operator_site.session import ACCEPT_SCORE, OperatorSession
from operator_site.ui.task_panel import NO_WORKPIECE
from operator_site.ui.text import plain
from operator_site.ui.words import short_program_name
from protocol import Recognition

MODEL_HELP = (
    "On the camera image, the model's blocks are outlined green and blocks vision recognised "
    "that the model lacks orange. In the 3D view, what vision sees is drawn see-through "
    "now: **green** where the model agrees, **orange** a few millimetres off, **red** far "
    "off, **blue** not in the model. Accept them to build the model the robot will work in; "
    "after the robot moved a block, *update the model from vision*. **Remove mode**: click a "
    "block in the 3D view to take it out."
)
AGREEMENT_WORDS = {
    "agrees": "in the model, agrees",
    "off": "in the model, **a few mm off**",
    "far": "in the model, **far off**",
    "new": "not in the model",
}


class ModelPanel:
    """The model panel of :class:`~operator_site.ui.page.OperatorPage`."""

    server: viser.ViserServer
    scene: Scene
    link: WorkSiteLink
    model: WorkSiteModel
    op: OperatorSession
    _lock: threading.Lock
    _offered_after: str | None = None  # the program after which the update was offered

    def _build_model_panel(self, gui: viser.GuiApi) -> None:
        """The panel's widgets, in the folder ``gui`` has open, and their callbacks."""
        gui.add_markdown(MODEL_HELP)
        # The buttons above what changes with every frame (the list of recognitions grows
        # and shrinks as vision finds and loses blocks): a button stays where the mouse aims.
        self.accept_button = gui.add_button("accept the recognised blocks")
        self.scene_layout_button = gui.add_button("use the scene file's layout (no vision)")
        self.update_button = gui.add_button(
            "update the model from vision",
            hint="every block vision sees now goes where it sees it; the others stay",
        )
        self.show_vision = gui.add_checkbox("show what vision sees in 3D", True)
        self.remove_mode = gui.add_checkbox("remove mode", False)
        self.model_md = gui.add_markdown("")
        self.recognitions_md = gui.add_markdown("no recognitions yet")
        self._rec_folder = gui.add_folder("recognised, not in the model: click to add")
        self._rec_buttons: dict[str, object] = {}
        self.accept_button.on_click(lambda _: self.on_accept_recognitions())
        self.scene_layout_button.on_click(lambda _: self.on_use_scene_layout())
        self.update_button.on_click(lambda _: self.on_update_from_vision())
        self.show_vision.on_update(
            lambda _: setattr(self.vision_root, "visible", self.show_vision.value)
        )

    def _model_changed(self, corrections=()) -> None:
        """The model's objects changed (the session started its task afresh): show it."""
        self._nothing_picked()
        self._task_changed()
        self._show_model()
        if self.workpiece_dropdown.value != NO_WORKPIECE:
            self.workpiece_dropdown.value = NO_WORKPIECE  # nothing is picked any more
        names = ", ".join(sorted(self.model.poses))
        lines = [f"model: {len(self.model.poses)} blocks ({plain(names)})"]
        lines += [
            f"{plain(c.name)}: moved {c.moved_mm:.1f} mm, turned {c.turned_deg:.1f}° "
            f"({plain(c.why)})"
            for c in corrections
            if c.moved_mm >= 0.05 or c.turned_deg >= 0.05
        ]
        self.model_md.content = "  \n".join(lines)
        self._recognitions_shown = None  # the list says what is in the model: redraw it

    def on_accept_recognitions(self, min_score: float = ACCEPT_SCORE) -> int:
        """Accept every recognition scoring at least ``min_score`` into the model, then make
        the model consistent; the number accepted."""
        recs = self.link.recognitions
        if recs is None or not recs.objects:
            self.model_md.content = (
                "Nothing recognised yet: wait for the camera, or use the scene file's layout."
            )
            return 0
        with self._lock:
            try:
                accepted = self.op.accept_all(recs, min_score)
            except ValueError as e:
                self.model_md.content = f"⚠ the model was not changed: {plain(e)}"
                return 0
            self._model_changed(self.op.corrections)
        return accepted

    def on_accept_one(self, name: str) -> bool:
        """Accept the latest recognition of ``name`` into the model (made consistent); False
        if vision has no such object now."""
        recs = self.link.recognitions
        found = [r for r in (recs.objects if recs else ()) if r.model == name]
        if not found:
            self.model_md.content = f"{plain(name)} is not among the latest recognitions"
            return False
        with self._lock:
            try:
                self.op.accept(name, found[0].X_WO, found[0].score)
            except ValueError as e:
                self.model_md.content = f"⚠ {plain(name)} not added: {plain(e)}"
                return False
            self._model_changed(self.op.corrections)
        self._show_recognitions()
        return True

    def on_update_from_vision(self) -> int:
        """The model brought up to date with what vision sees now (after the robot moved a
        block): each block recognised goes where vision sees it, the others stay; the number
        updated."""
        accepted = self.on_accept_recognitions()
        # This answers the offer after the last program: it is not to come over the answer.
        if (ended := self._last_ended_report()) is not None:
            self._offered_after = ended.program_id
        said = self.model_md.content
        if accepted:
            self.model_md.content = (
                f"updated from vision: {accepted} blocks where the camera sees them now  \n{said}"
            )
        else:  # always an answer: the operator waits for one
            self.model_md.content = f"⚠ nothing updated from vision  \n{said}"
        return accepted

    def on_use_scene_layout(self) -> None:
        """The model from the scene file's layout: every block where the file puts it."""
        with self._lock:
            self.op.use_scene_layout()
            self._model_changed(self.op.corrections)

    def on_remove(self, name: str) -> None:
        """Take ``name`` out of the model."""
        with self._lock:
            if name in self.model.poses:
                self.op.remove(name)
                self._model_changed()

    def _show_recognitions(self) -> None:
        recs = self.link.recognitions
        if recs is None or recs.seq == self._recognitions_shown:
            return
        self._recognitions_shown = recs.seq
        if not recs.objects:
            self._show_ghosts(())
            self.recognitions_md.content = f"frame {recs.seq}: nothing recognised"
            return
        kinds = self._show_ghosts(recs.objects)
        lines = [f"frame {recs.seq}, {recs.elapsed_s * 1e3:.0f} ms:"]
        for r in sorted(recs.objects, key=lambda r: r.model):  # in one place frame to frame
            state = AGREEMENT_WORDS[kinds.get(r.model, "new")]
            lines.append(f"- {plain(r.model)}: score {r.score:.2f}, {_sureness(r)} ({state})")
        self.recognitions_md.content = "\n".join(lines)
        self._show_add_buttons({r.model for r in recs.objects if r.model not in self.model.poses})

    def _show_add_buttons(self, names: set[str]) -> None:
        """One "add" button per recognised block not in the model."""
        for name in [n for n in self._rec_buttons if n not in names]:
            self._rec_buttons.pop(name).remove()
        known = {o.name for o in self.scene.movable}
        with self._rec_folder:
            for name in sorted(names):
                if name in self._rec_buttons or name not in known:
                    continue
                # The score changes every frame: the list above shows it, the button not.
                button = self.server.gui.add_button(f"add {name}")
                button.on_click(lambda _, n=name: self.on_accept_one(n))
                self._rec_buttons[name] = button

    def _last_ended_report(self):
        """The final report of the last program that moved the robot and ended (None: none)."""
        for r in reversed(self.link.status.reports):
            if r.command_index == -1 and r.status in ("done", "failed", "stopped"):
                return r
        return None

    def _offer_update(self) -> None:
        """Once a program has ended and vision has looked since, say which blocks it sees
        away from the model, next to the button that updates the model."""
        ended = self._last_ended_report()
        recs = self.link.recognitions
        if ended is None or recs is None or ended.program_id == self._offered_after:
            return
        if recs.stamp_s <= ended.stamp_s:
            return  # vision has not looked since the robot stopped
        self._offered_after = ended.program_id
        kinds = self._ghost_kinds(recs.objects)  # as drawn for this frame: not drawn again
        moved = sorted(t for t, (_, k) in kinds.items() if k in ("off", "far", "new"))
        after = f"after {short_program_name(ended.program_id)}"
        # The block the program put down, against where it put it: "done" says only that the
        # commands were (operator_site.placement).
        placed = self.op.released(ended.program_id) if ended.status == "done" else None
        check = (
            check_placement(placed[0], placed[1], self.model.symmetries(placed[0]), [recs], 1)
            if placed is not None
            else None
        )
        if check is not None and check.verdict in ("moved", "unsure"):
            self.model_md.content = (
                f"**{after}, {plain(check.sentence())}: the task may not be done.** Look at the "
                "camera image; *update the model from vision* to try again from where it is."
            )
        elif moved:
            self.model_md.content = (
                f"**{after}, vision sees {plain(', '.join(moved))} away from the model**: "
                "*update the model from vision* to work on from where they are."
            )
        else:
            self.model_md.content = f"{after}, vision agrees with the model."


def _sureness(r: Recognition) -> str:
    """How sure vision is of a recognised pose, in words: one frame's, or the spread of the
    frames it fuses; and how many of vision's full searches found it there."""
    found = f"found by {r.searches} search{'' if r.searches == 1 else 'es'}"
    if r.rivals:
        found += f", also seen in {r.rivals} other place{'' if r.rivals == 1 else 's'}"
    if r.frames <= 1:
        return f"1 frame, {found}"
    return (
        f"{r.frames} frames within ±{r.spread_m * 1e3:.1f} mm, "
        f"±{math.degrees(r.spread_rad):.1f}°, {found}"
    )
