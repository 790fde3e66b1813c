"""The operator's web page (viser), Fig. 5 as one page: the live camera image with the recognised
objects drawn over it, the list of recognitions to accept into the model, the 3D model in which
the operator drags the workpiece, the program to confirm, the execution log, and a stop button
that is always there.

Only this package calls viser. Each panel is its own module, mixed into :class:`OperatorPage`:
the model (:mod:`.model_panel`), the task (:mod:`.task_panel`), the program
(:mod:`.program_panel`), the 3D view (:mod:`.scene_view`), the status and the log
(:mod:`.status`).

Text from the wire or from files reaches the page's markdown only through
:func:`.text.plain`: viser renders markdown's embedded HTML as is.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np
import viser
import zenoh

from models.robot import RobotModel, load_robot
from models.scene import Scene
from operator_site.link import WorkSiteLink
from operator_site.model_editor import WorkSiteModel
from operator_site.session import OperatorSession
from operator_site.task import TaskSession
from operator_site.ui.access import (
    PageAccess,
    connection_token,
    install_gate,
    is_loopback_host,
    page_url,
)
from operator_site.ui.model_panel import ModelPanel
from operator_site.ui.overlay import draw_wireframes
from operator_site.ui.program_panel import ProgramPanel
from operator_site.ui.scene_view import VIEW_FOV_RAD, SceneView, initial_view_W
from operator_site.ui.status import status_markdown, waiting_image
from operator_site.ui.task_panel import TaskPanel
from operator_site.ui.text import plain
from operator_site.ui.words import short_program_name
from protocol import MotionProgram, ProtocolError

log = logging.getLogger("operator-site")

UI_PERIOD_S = 0.05
"""The page is refreshed from the link at most this often (20 Hz)."""
STATUS_PERIOD_S = 0.5
READ_ONLY_HELP = (
    "**Read only.** This page controls a robot: to control it, open the address with the "
    "access token that `operator-site serve` printed when it started, or type the token here."
)


class OperatorPage(ModelPanel, TaskPanel, ProgramPanel, SceneView):
    """Builds the page for ``scene`` and keeps it in step with ``link`` while running.

    ``initial_model``: "scene" starts the model from the scene file's layout (the demo without
    vision), "empty" from the fixed environment alone, waiting for recognitions.

    ``token``: only clients that show it may control the robot (:mod:`.access`); required
    when ``host`` is not loopback. ``browse_host``: the host name :attr:`url` uses when ``host``
    is a wildcard address. ``view_dpr``: the 3D view's fixed device-pixel ratio in :attr:`url`
    (:func:`~operator_site.ui.access.page_url`).
    """

    def __init__(
        self,
        scene: Scene,
        link: WorkSiteLink,
        host: str = "127.0.0.1",
        port: int = 8080,
        initial_model: str = "scene",
        token: str | None = None,
        browse_host: str | None = None,
        view_dpr: float | None = None,
    ) -> None:
        if initial_model not in ("scene", "empty"):
            raise ValueError(f"initial_model must be 'scene' or 'empty', not {initial_model!r}")
        if token is None and not is_loopback_host(host):
            raise ValueError(f"a page listening on {host} needs an access token")
        self.access = PageAccess(token)
        self.scene, self.link = scene, link
        self.robot: RobotModel = load_robot(scene.robot.urdf_path)
        self.server = viser.ViserServer(
            host=host, port=port, label="Telerobot operator site", verbose=False
        )
        install_gate(self.server, self.access)
        if browse_host is None and host in ("0.0.0.0", "127.0.0.1", "::", "::1"):
            browse_host = "localhost"
        # viser moves to the next free port if this one is taken: the URL says where it is.
        self.url = page_url(host, self.server.get_port(), token, browse_host, view_dpr)
        self.server.scene.set_up_direction("+z")
        eye_W, look_at_W = initial_view_W(scene)
        self.server.initial_camera.fov = VIEW_FOV_RAD
        self.server.initial_camera.position = tuple(eye_W)
        self.server.initial_camera.look_at = tuple(look_at_W)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self._initial_model = initial_model
        self.op = OperatorSession(scene, link)
        if initial_model == "scene":
            self.op.use_scene_layout()
        self._lock = threading.Lock()
        self._switch_to: str | None = None
        """A work site the operator chose, to switch to at the next update."""
        self._sites_listed: tuple[str, ...] = ()
        self.message = ""  # markdown: any outside text in it already went through plain()
        self.finger_meshes: list = []
        self.path_lines: list = []
        self.pending_program: MotionProgram | None = None
        self.last_program: MotionProgram | None = None
        self._recognitions_shown: int | None = None
        self._build_gui()
        self._build_scene()
        self._show_model()
        self.frames_shown = 0
        self.states_shown = 0
        self.server.on_client_connect(self._on_client_connect)
        self.server.on_client_disconnect(lambda client: self.access.forget(client.client_id))

    @property
    def model(self) -> WorkSiteModel:
        """The operator session's model of the work site."""
        return self.op.model

    @property
    def session(self) -> TaskSession:
        """The operator session's task in the simulator."""
        return self.op.task

    # ------------------------------------------------------------------------------ building

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        # The panel docked beside the 3D view, not floating over it: the view is not hidden
        # behind it, and a browser drawing in software draws a quarter fewer pixels a frame.
        gui.main_panel.dock_right()
        gui.add_markdown("### Telerobot — operator site")
        self.stop_button = gui.add_button(
            "STOP the robot", color="red", icon=None, hint="stops any motion at the work site"
        )
        self.stop_button.on_click(lambda _: self.on_stop())
        self.status_md = gui.add_markdown(self._status_text())
        self.site_dropdown = gui.add_dropdown(
            "work site",
            (self.link.site_id,),
            initial_value=self.link.site_id,
            hint="the work sites you can reach; choosing one switches this page to it",
        )
        # Only a person's choice acts: the page setting the dropdown itself calls this too.
        self.site_dropdown.on_update(
            lambda e: e.client is None or self.on_switch_site(self.site_dropdown.value)
        )
        self.site_md = gui.add_markdown("")
        cam = self.scene.camera
        self.camera_image = gui.add_image(
            # Half size: cheap to send, and never mistaken for a frame from the work site.
            waiting_image(cam.width // 2, cam.height // 2, "waiting for the work site's camera"),
            label="work-site camera (point at it and click the corner icon to enlarge)",
            format="jpeg",
            jpeg_quality=85,
        )
        with gui.add_folder("Model"):
            self._build_model_panel(gui)
        with gui.add_folder("Task"):
            self._build_task_panel(gui)
        with gui.add_folder("Program and execution log"):
            self._build_program_panel(gui)

    def _on_client_connect(self, client: viser.ClientHandle) -> None:
        """A client without the token is told it sees a read-only page, and how to get access."""
        cid = client.client_id
        if self.access.admit(cid, connection_token(self.server, cid)):
            return
        # Client-scoped: only this client sees them, and its messages to them pass the gate.
        notice = client.gui.add_markdown(READ_ONLY_HELP, order=-3.0)
        field = client.gui.add_text("access token", "", order=-2.0)
        button = client.gui.add_button("get control", order=-1.0)

        def on_token(_) -> None:
            if self.access.admit(cid, field.value.strip()):
                for handle in (notice, field, button):
                    handle.remove()
                client.add_notification("Access granted", "You control the robot now.")
                log.info("page client %d typed the access token: it controls the robot", cid)
            else:
                log.warning("page client %d typed a wrong access token", cid)
                notice.content = READ_ONLY_HELP + "  \n⚠ That is not the token."

        button.on_click(on_token)

    def _camera_view(self) -> np.ndarray:
        """The latest frame with the model's blocks outlined (green) and the blocks vision
        recognised that the model lacks (orange), drawn through the calibration the frame was
        taken with (vision runs slower than the camera: recognitions may be a frame or two
        older)."""
        frame = self.link.camera_frame
        height, width = frame.image.shape[:2]
        camera = dataclasses.replace(
            self.scene.camera, width=width, height=height, K=frame.K, dist=frame.dist,
            X_WC=frame.X_WC,
        )  # fmt: skip
        known = {o.name: o.model for o in self.scene.movable}
        objects = [(known[n], X, True) for n, X in self.model.poses.items() if n in known]
        recs = self.link.recognitions
        objects += [
            (known[r.model], r.X_WO, False)
            for r in (recs.objects if recs is not None else ())
            if r.model in known and r.model not in self.model.poses
        ]
        if not objects:
            return frame.image
        return draw_wireframes(frame.image, camera, objects)[..., ::-1]

    def on_switch_site(self, site_id: str) -> None:
        """The operator chose work site ``site_id``: the page switches to it at its next
        update; refused while a program of this page's runs at the current site, alive
        (leaving stops its heartbeats, and so the program)."""
        with self._lock:
            running = self.link.running_programs
            if running and self.link.status.work_site_alive and site_id != self.link.site_id:
                self.site_md.content = (
                    f"⚠ program {short_program_name(running[0])} has not ended at "
                    f"{plain(self.link.site_id)}: wait for its end, or STOP it, before switching"
                )
                self.site_dropdown.value = self.link.site_id
                return
            self._switch_to = site_id

    def _switch_if_asked(self) -> None:
        """Switch to the work site the operator chose, if any: a new link, and the model,
        task, program and log start afresh (the other cell's blocks are its own)."""
        with self._lock:
            site_id, self._switch_to = self._switch_to, None
            if site_id is None or site_id == self.link.site_id:
                return
            try:
                new = self.link.to_site(site_id)
            except (ProtocolError, zenoh.ZError) as e:
                self.site_md.content = f"⚠ cannot reach work site {plain(site_id)}: {plain(e)}"
                self.site_dropdown.value = self.link.site_id
                return
            old, self.link = self.link, new
            self.op = OperatorSession(self.scene, new)
            if self._initial_model == "scene":
                self.op.use_scene_layout()
            self.pending_program = self.last_program = None
            self._model_changed()
            self._show_log([])
            cam = self.scene.camera
            self.camera_image.image = waiting_image(
                cam.width // 2, cam.height // 2, "waiting for the work site's camera"
            )
            self.frames_shown = self.states_shown = 0
            if self.site_dropdown.value != site_id:
                self.site_dropdown.value = site_id
            self.site_md.content = f"switched from {plain(old.site_id)}"
            self.status_md.content = self._status_text()
        log.info("page: from work site %s to %s", old.site_id, site_id)
        old.close()  # outside the lock: it waits for its threads

    def _list_sites(self) -> None:
        """Offer every work site the link can reach (and the current one)."""
        listed = tuple(sorted({*self.link.status.sites, self.link.site_id}))
        if listed != self._sites_listed:
            self._sites_listed = listed
            self.site_dropdown.options = listed
            if self.site_dropdown.value != self.link.site_id:
                self.site_dropdown.value = self.link.site_id

    def update(self) -> None:
        """Poll the link once and show what changed."""
        self._switch_if_asked()
        new_state, new_frame = self.link.poll()
        self._list_sites()
        if new_state and self.link.robot_state is not None:
            s = self.link.robot_state
            self._show_robot(s.q, s.gripper_opening_m)
            self.states_shown += 1
        if new_frame and self.link.camera_frame is not None:
            self.camera_image.image = self._camera_view()
            self.frames_shown += 1
        self._show_recognitions()

    def run(self, stop: threading.Event) -> None:
        """Refresh the page until ``stop`` is set."""
        next_status = 0.0
        while not stop.is_set():
            t = time.monotonic()
            self.update()
            self.step_task()
            if t >= next_status:
                self.status_md.content = self._status_text()
                self._show_log(self.link.status.reports)
                self._offer_update()
                self._show_control()
                next_status = t + STATUS_PERIOD_S
            stop.wait(max(0.0, UI_PERIOD_S - (time.monotonic() - t)))

    def _status_text(self) -> str:
        return status_markdown(self.link.site_id, self.link.status, self.link.operator_id)

    def _show_control(self) -> None:
        """A watcher's controls are disabled (another operator holds the robot); STOP stays."""
        watching = self.link.watching
        self.program_button.disabled = watching
        self.send_button.disabled = watching or self.pending_program is None
        for button in self.recovery_buttons:
            button.disabled = watching

    def close(self) -> None:
        self.server.stop()
