"""The browser viewer and editor of a trained model (``ne-jax view RUN``), built on viser.

viser serves a web page with a three.js scene (the point cloud, training cameras, transform gizmos)
and a GUI panel, and reports each browser's camera to Python; the model's render of that camera is
sent back as the page's background image. The edit logic is :mod:`ne_jax.view.edits` (pure, tested
without a browser); this module only wires it to the GUI.

Rendering is progressive per browser: while the camera moves, frames are rendered at
``1 / preview_factor`` of the resolution; once it has been still for ``settle_s`` seconds, one frame
at full resolution (the browser's size with its longer side capped at ``max_side``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import socket
import threading
import time
import traceback
from pathlib import Path

import numpy as np

from ne_jax.edit.targets import EditError
from ne_jax.train.model import TrainedModel, load_trained
from ne_jax.view import edits as E
from ne_jax.view.frames import MODES, camera_from_viewer, fit_size, look_at, render_frame, viewer_pose


class ViewerError(ValueError):
    """The viewer cannot start: a bad model, host or port (the message names it)."""


def port_in_use(host: str, port: int) -> bool:
    """Whether ``host:port`` cannot be bound now (another server listens there)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


@dataclasses.dataclass
class _ClientState:
    """One browser's camera version (bumped on every camera message) and its render thread."""

    event: threading.Event = dataclasses.field(default_factory=threading.Event)
    version: int = 0
    last_update: float = 0.0
    thread: threading.Thread | None = None


def _bbox(xyz: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = xyz.min(0), xyz.max(0)
    return 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))


class Viewer:
    """A web viewer and editor of one model.

    ``Viewer(model_or_run_dir, port=8080, host="127.0.0.1")`` starts serving at once (also from a
    notebook); open :attr:`url` in a browser, :meth:`stop` ends it. ``port=0`` picks a free port.
    ``warm_up`` (default on) compiles in the background at start, in the order a user meets them:
    the points' colours, the first frame, then the edit path (:attr:`warmed` is set when done), while
    the page already shows the point cloud and the status line says what is being compiled.

    Attributes read by tests and notebooks: :attr:`edit` (the :class:`~ne_jax.view.edits.ViewEdit`
    so far), :attr:`selection` (``[K]`` slots), :attr:`frames` (frames sent), :attr:`last_frame`
    (the last image sent, ``[H, W, 3]`` uint8)."""

    def __init__(self, model: TrainedModel | str | Path, port: int = 8080, host: str = "127.0.0.1", *,
                 max_side: int = 128, preview_factor: int = 4, settle_s: float = 0.25, warm_up: bool = True,
                 verbose: bool = False):
        import viser

        if not isinstance(model, TrainedModel):
            path = Path(model)
            if not path.is_dir():
                raise ViewerError(f"{path}: expected a run directory (from `ne-jax train` or `ne-jax edit`), "
                                  "found nothing there")
            model = load_trained(path)
        if not isinstance(port, int) or not 0 <= port < 65536:
            raise ViewerError(f"port: expected an integer in [0, 65535] (0: any free port), found {port!r}")
        if port != 0 and port_in_use(host, port):
            raise ViewerError(f"port {port} on {host}: expected a free port, found it in use (another viewer or "
                              "server?); pass another --port, or 0 for any free one")
        self.model = model
        self.max_side, self.preview_factor, self.settle_s = int(max_side), int(preview_factor), float(settle_s)
        self._points = model.state.point_state(model.scene.points)
        self._lock = threading.RLock()  # the edit state and the edited model
        self._render_lock = threading.Lock()  # one render at a time (a CPU has no room for two)
        self.edit = E.ViewEdit.identity(self._points)
        self._history: list[E.ViewEdit] = []
        self.selection = np.zeros(0, np.int64)
        self._edited = model  # what is rendered: the model, or the model edited by self.edit
        self._context = None  # what every edit of the model shares (made by the first edit: _edit_context)
        self._scene_version = 0
        self._clients: dict[int, _ClientState] = {}
        self._stopped = False
        self.frames = 0
        self.last_frame: np.ndarray | None = None
        self.last_seconds = 0.0
        self.status = ""

        alive = np.asarray(self._points.alive)
        self._center, self._extent = _bbox(np.asarray(self._points.xyz)[alive])
        # the page shows the cloud at once, shaded by confidence; the model's colours (a compile) follow
        self._colors = self._point_colors() if not warm_up else self._confidence_colors()
        self._gizmo_guard = False
        self._move_pivot = np.zeros(3)

        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.host, self.port = host, self.server.get_port()
        self.server.scene.set_up_direction("+z")
        self._setup_initial_camera()
        self._build_gui()
        self._build_scene()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self.warmed = threading.Event()
        if warm_up:
            threading.Thread(target=self._warm_up, daemon=True, name="ne-jax-view-warm-up").start()
        else:
            self.warmed.set()

    # ---------------------------------------------------------------- public
    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("127.0.0.1", "0.0.0.0", "::", "::1") else self.host
        return f"http://{host}:{self.port}"

    def stop(self) -> None:
        """Stop serving (the render threads end with it)."""
        self._stopped = True
        states = list(self._clients.values())
        for st in states:
            st.event.set()
        for st in states:  # a render in flight finishes first (JAX must not be torn down under it)
            if st.thread is not None and st.thread is not threading.current_thread():
                st.thread.join(timeout=60.0)
        self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def render(self, wxyz, position, fov_y: float, width: int, height: int, mode: str = "rgb",
               preview: bool = False):
        """``(image [H, W, 3] uint8, seconds)``: the current (edited) model from a browser camera
        (OpenCV ``wxyz``/``position``, vertical ``fov_y`` radians). A ``preview`` shoots one ray per
        pixel whatever grid the model was trained with."""
        camera = camera_from_viewer(wxyz, position, fov_y, width, height)
        with self._lock:
            model = self._edited
        with self._render_lock:
            return render_frame(model, camera, mode, 1 if preview else None)

    @property
    def edited_model(self) -> TrainedModel:
        """The model the viewer renders: the loaded one edited by :attr:`edit` (zero-shot)."""
        return self._edited

    # edit steps (the GUI's buttons call these; each raises SelectionError/EditError for bad input)
    def select_region(self, region: E.Region) -> np.ndarray:
        with self._lock:
            self.selection = E.select_region(self.edit, region)
        self._show_selection()
        return self.selection

    def select(self, indices) -> np.ndarray:
        """Set the selection to ``indices`` (slots of remaining points)."""
        with self._lock:
            idx = np.asarray(indices, np.int64)
            self.selection = np.unique(idx) if idx.size else np.zeros(0, np.int64)
        self._show_selection()
        return self.selection

    def move(self, transform: E.Transform) -> None:
        with self._lock:
            self._push(E.move_points(self.edit, self.selection, transform))

    def delete(self) -> None:
        with self._lock:
            self._push(E.delete_points(self.edit, self.selection))
            self.selection = np.zeros(0, np.int64)

    def load_edit(self, source) -> None:
        """Replace the edit by ``source`` (a benchmark edit's name, an :class:`Edit`, ``.npy``/``.ply``)."""
        from ne_jax.benchmark.edits import resolve_edit

        edit, _, _ = resolve_edit(self.model.scene_dir, source)
        with self._lock:
            self._push(E.ViewEdit.from_source(self._points, edit))
            self.selection = np.zeros(0, np.int64)

    def undo(self) -> bool:
        """Go back one edit step; ``False`` when there is none."""
        with self._lock:
            if not self._history:
                return False
            self.edit = self._history.pop()
            self.selection = self.selection[self.edit.remaining[self.selection]] if self.selection.size else \
                self.selection
            self._rebuild()
        return True

    def save(self, out_dir: str | Path) -> dict:
        """Write the edit as ``out_dir`` (an edited run directory, with ``edit.ply`` inside), atomically."""
        with self._lock:
            _, report = E.save_view_edit(self.model, self.edit, out_dir, ist=self._gui_ist.value,
                                         context=self._edit_context())
        return report

    # --------------------------------------------------------------- internals
    def _confidence_colors(self) -> np.ndarray:
        """``[C, 3]`` uint8 grey levels by confidence: shown until :meth:`_point_colors` is compiled."""
        conf = np.clip(np.nan_to_num(np.asarray(self._points.confidence, np.float32)), 0.0, 1.0)
        return np.repeat(np.round(80 + 150 * conf).astype(np.uint8)[:, None], 3, axis=1)

    def _point_colors(self) -> np.ndarray:
        from ne_jax.pointcloud.export import point_colors

        rgb = np.asarray(point_colors(self.model.run.render.shading, self.model.params, self._points))
        return np.clip(np.round(np.nan_to_num(rgb) * 255), 0, 255).astype(np.uint8)

    def _edit_context(self):
        """The :class:`~ne_jax.edit.apply.EditContext` of :attr:`model` for the current edit's
        deletions: made by the first edit and kept for the next (its neighbour table made again
        when the deletions change)."""
        from ne_jax.edit.apply import EditConfig
        from ne_jax.edit.model import model_edit_context

        alive = self.edit.remaining
        held = self._context
        self._context = model_edit_context(self.model, alive=alive) if held is None else \
            held.for_alive(EditConfig(), alive)
        return self._context

    def _push(self, new: E.ViewEdit) -> None:
        self._history.append(self.edit)
        self.edit = new
        self._rebuild()

    def _rebuild(self) -> None:
        """Make the edited model of the current edit (zero-shot) and re-render every browser."""
        from ne_jax.edit.model import edit_model

        t0 = time.perf_counter()
        if self.edit.changed(self._points):
            self._edited, _ = edit_model(self.model, self.edit.rows(), ist=self._gui_ist.value, label="viewer",
                                         context=self._edit_context())
        else:
            self._edited = self.model
        self._edit_seconds = time.perf_counter() - t0
        self._scene_version += 1
        self._show_points()
        self._show_selection()
        self._set_status(f"edit applied in {self._edit_seconds:.2f} s: {int(self.edit.deleted.sum())} deleted, "
                         f"{len(self._history)} step(s) to undo")
        self._redraw()

    def _redraw(self) -> None:
        self._scene_version += 1
        for st in list(self._clients.values()):
            st.event.set()

    def _set_status(self, text: str) -> None:
        self.status = text
        self._gui_status.content = text

    def _setup_initial_camera(self) -> None:
        self._train = None
        if self.model.scene_dir is not None and Path(self.model.scene_dir).is_dir():
            from ne_jax.data.scene import load_split

            with contextlib.suppress(Exception):
                self._train = load_split(self.model.scene_dir, "train", self.model.run.downscale)
        cam = self.server.initial_camera
        if self._train is not None:
            c2w = np.asarray(self._train.c2w[0], np.float64)
            cam.position = tuple(c2w[:3, 3])
            cam.look_at = tuple(self._center)
            h = self._train.height
            fy = float(self._train.camera(0).fy)
            cam.fov = float(2 * np.arctan(0.5 * h / fy))
        else:
            cam.position = tuple(self._center + np.array([1.0, -1.0, 0.6]) * self._extent)
            cam.look_at = tuple(self._center)
        cam.up = (0.0, 0.0, 1.0)

    def _warm_up(self) -> None:
        """Compile, in a background thread, what a user meets first (:attr:`warmed` is set when
        done): the points' colours, a frame of the model (so the first browser frame follows at
        once), then the edit path (the IST and the carried tree's traversal, through an identity
        edit rendered once). The status line says which is compiling."""
        from ne_jax.edit.model import edit_model

        try:
            self._set_status("compiling: the points' colours (the cloud is shaded by confidence until then)")
            self._colors = self._point_colors()
            with self._lock:
                self._show_points()
            # a view of the whole cloud, so that the rays that meet it are rendered (and compiled)
            eye = self._center + self._extent * np.array([0.0, -1.5, 0.75])
            camera = camera_from_viewer(look_at(eye, self._center), eye, 0.7, self.max_side, self.max_side)
            self._set_status("compiling: the renderer (the first frame follows when it is done)")
            with self._render_lock:
                render_frame(self.model, camera)
            self._set_status("compiling: the edit path (the first edit waits for it)")
            edited, _ = edit_model(self.model, self.edit.rows(), ist=True, label="warm-up",
                                   context=self._edit_context())
            with self._render_lock:
                render_frame(edited, camera)
            self._set_status("ready")
        except Exception:  # the viewer works without it; the first edit then compiles
            if not self._stopped:
                self._set_status("warm-up failed: " + traceback.format_exc(limit=2).splitlines()[-1])
        finally:
            self.warmed.set()

    # ---------------------------------------------------------------- scene
    def _build_scene(self) -> None:
        sc = self.server.scene
        self._point_size = self._extent / 250
        self._pc = sc.add_point_cloud("/points", np.zeros((1, 3), np.float32), (0, 0, 0), point_size=self._point_size,
                                      visible=False)
        self._sel = sc.add_point_cloud("/selection", np.zeros((1, 3), np.float32), (255, 0, 0),
                                       point_size=1.6 * self._point_size, visible=False)
        self._show_points()
        self._frustums = []
        if self._train is not None:
            for i in range(self._train.num_views):
                r_cv, pos = viewer_pose(self._train.c2w[i])
                cam = self._train.camera(i)
                fov = float(2 * np.arctan(0.5 * cam.height / float(cam.fy)))
                self._frustums.append(sc.add_camera_frustum(
                    f"/cameras/{i:03d}", fov, cam.width / cam.height, scale=0.04 * self._extent,
                    wxyz=E.matrix_to_quat(r_cv), position=pos, color=(40, 90, 200), visible=False))
        self._region_ctl = sc.add_transform_controls("/region", scale=0.3 * self._extent, position=tuple(self._center),
                                                     visible=False)
        self._region_shape = None
        self._move_ctl = sc.add_transform_controls("/move", scale=0.3 * self._extent, position=tuple(self._center),
                                                   visible=False)
        self._move_ctl.on_update(self._on_move_gizmo)
        self._region_ctl.on_update(lambda _: None)
        self._update_region_shape()

        @sc.on_rect_select(modifier="cmd/ctrl")
        def _(event) -> None:
            cam = event.client.camera
            c2w = np.eye(4)
            c2w[:3, :3] = E.quat_to_matrix(cam.wxyz)
            c2w[:3, 3] = cam.position
            with self._lock:
                self.selection = E.select_screen_rect(self.edit, c2w, cam.fov, cam.aspect, event.screen_min,
                                                      event.screen_max)
            self._show_selection()

    def _show_points(self) -> None:
        keep = self.edit.remaining
        self._pc.points = self.edit.xyz[keep].astype(np.float32)
        self._pc.colors = self._colors[keep]
        self._pc.visible = self._gui_points.value

    def _show_selection(self, transform: E.Transform | None = None) -> None:
        sel = self.selection
        self._gui_selected.content = f"**{sel.size}** point(s) selected"
        if sel.size == 0:
            self._sel.visible = False
            return
        xyz = self.edit.xyz[sel]
        if transform is not None:
            xyz = transform.apply(xyz)
        self._sel.points = xyz.astype(np.float32)
        self._sel.colors = np.tile(np.array([[255, 40, 40]], np.uint8), (sel.size, 1))
        self._sel.visible = True

    def _region(self) -> E.Region:
        kind = self._gui_region.value
        size = self._gui_region_size.value
        return E.Region.make(kind, self._region_ctl.position, size if kind == "box" else 0.5 * size,
                             self._region_ctl.wxyz)

    def _update_region_shape(self) -> None:
        sc = self.server.scene
        if self._region_shape is not None:
            self._region_shape.remove()
        size = self._gui_region_size.value
        vis = self._gui_show_region.value
        if self._gui_region.value == "box":
            self._region_shape = sc.add_box("/region/shape", color=(255, 160, 0), dimensions=(size, size, size),
                                            wireframe=True, visible=vis)
        else:
            self._region_shape = sc.add_icosphere("/region/shape", radius=0.5 * size, color=(255, 160, 0),
                                                  wireframe=True, visible=vis)
        self._region_ctl.visible = vis

    def _transform(self) -> E.Transform:
        """The move fields (capture coordinates) as a transform in the model's frame."""
        t, rot = E.offsets_to_model(self.model.frame, self._gui_move.value, self._gui_rotate.value)
        return E.Transform(tuple(tuple(map(float, r)) for r in rot), tuple(map(float, t)),
                           float(self._gui_scale.value), tuple(map(float, self._move_pivot)))

    def _on_move_gizmo(self, handle) -> None:
        if self._gizmo_guard:
            return
        self._gizmo_guard = True
        try:
            t, angles = E.offsets_to_capture(self.model.frame, np.asarray(handle.position) - self._move_pivot,
                                             E.quat_to_matrix(handle.wxyz))
            self._gui_move.value = tuple(np.round(t, 5))
            self._gui_rotate.value = tuple(np.round(angles, 3))
        finally:
            self._gizmo_guard = False
        self._show_selection(self._transform())

    def _on_transform_fields(self, _=None) -> None:
        with contextlib.suppress(ValueError):
            t = self._transform()
            if not self._gizmo_guard:
                self._gizmo_guard = True
                try:
                    self._move_ctl.position = tuple(self._move_pivot + np.asarray(t.translation))
                    self._move_ctl.wxyz = tuple(E.matrix_to_quat(np.asarray(t.rotation)))
                finally:
                    self._gizmo_guard = False
            self._show_selection(t)

    def _reset_transform(self) -> None:
        with self._lock:
            self._move_pivot = E.selection_center(self.edit, self.selection) if self.selection.size else self._center
        self._gizmo_guard = True
        try:
            self._gui_move.value = (0.0, 0.0, 0.0)
            self._gui_rotate.value = (0.0, 0.0, 0.0)
            self._gui_scale.value = 1.0
            self._move_ctl.position = tuple(self._move_pivot)
            self._move_ctl.wxyz = (1.0, 0.0, 0.0, 0.0)
        finally:
            self._gizmo_guard = False

    # ------------------------------------------------------------------ GUI
    def _guarded(self, fn):
        """A GUI callback that shows a bad request (no points selected, ...) as the status line."""
        def run(event=None):
            try:
                fn()
            except (EditError, ValueError, KeyError) as e:
                msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
                self._set_status(f"error: {msg}")
                client = getattr(event, "client", None)
                if client is not None:
                    with contextlib.suppress(Exception):
                        client.add_notification("ne-jax view", str(msg), color="red", auto_close_seconds=8.0)
            except Exception:  # keep the server alive; show what broke
                self._set_status("error: " + traceback.format_exc(limit=2).splitlines()[-1])
        return run

    def _build_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("View"):
            self._gui_mode = gui.add_dropdown("Render mode", MODES, initial_value="rgb")
            self._gui_max = gui.add_slider("Max side (px)", 32, 1024, 32, min(max(32, self.max_side // 32 * 32), 1024))
            self._gui_points = gui.add_checkbox("Point cloud", False)
            self._gui_cameras = gui.add_checkbox("Training cameras", False)
            self._gui_time = gui.add_markdown("render: waiting for the first frame (compiling)")
        with gui.add_folder("Select"):
            self._gui_region = gui.add_dropdown("Region", ("box", "sphere"), initial_value="box")
            self._gui_region_size = gui.add_slider("Region size", round(0.02 * self._extent, 4),
                                                   round(self._extent, 4), round(0.005 * self._extent, 4),
                                                   round(0.3 * self._extent, 4))
            self._gui_show_region = gui.add_checkbox("Show region gizmo", False)
            self._gui_select = gui.add_button("Select in region")
            self._gui_clear = gui.add_button("Clear selection")
            self._gui_selected = gui.add_markdown("**0** point(s) selected")
            gui.add_markdown("Ctrl+drag on the view: box-select")
        with gui.add_folder("Edit"):
            self._gui_move = gui.add_vector3("Move by", (0.0, 0.0, 0.0), step=0.001)
            self._gui_rotate = gui.add_vector3("Rotate (deg xyz)", (0.0, 0.0, 0.0), step=1.0)
            self._gui_scale = gui.add_number("Scale", 1.0, min=0.01, max=100.0, step=0.01)
            self._gui_show_move = gui.add_checkbox("Show move gizmo", False)
            self._gui_apply = gui.add_button("Apply move")
            self._gui_delete = gui.add_button("Delete selected")
            self._gui_ist = gui.add_checkbox("IST", True)
            self._gui_undo = gui.add_button("Undo")
            names = self._benchmark_edits()
            self._gui_bench = gui.add_dropdown("Benchmark edit", ("(none)",) + names, initial_value="(none)",
                                               disabled=not names)
            self._gui_load = gui.add_button("Load benchmark edit", disabled=not names)
            default_out = (Path(self.model.run_dir).parent / f"{Path(self.model.run_dir).name}_view_edit"
                           if self.model.run_dir is not None else Path("view_edit"))
            self._gui_out = gui.add_text("Save to", str(default_out))
            self._gui_save = gui.add_button("Save")
            self._gui_status = gui.add_markdown("")

        self._gui_mode.on_update(lambda _: self._redraw())
        self._gui_max.on_update(lambda _: self._redraw())
        self._gui_points.on_update(lambda _: setattr(self._pc, "visible", self._gui_points.value))

        def cams(_):
            for f in self._frustums:
                f.visible = self._gui_cameras.value
        self._gui_cameras.on_update(cams)
        self._gui_region.on_update(lambda _: self._update_region_shape())
        self._gui_region_size.on_update(lambda _: self._update_region_shape())
        self._gui_show_region.on_update(lambda _: self._update_region_shape())

        def select():
            self.select_region(self._region())
            self._reset_transform()
            self._set_status(f"selected {self.selection.size} point(s) in the {self._gui_region.value}")
        self._gui_select.on_click(self._guarded(select))

        def clear():
            self.select([])
            self._reset_transform()
        self._gui_clear.on_click(self._guarded(clear))
        for h in (self._gui_move, self._gui_rotate, self._gui_scale):
            h.on_update(self._on_transform_fields)
        self._gui_show_move.on_update(lambda _: setattr(self._move_ctl, "visible", self._gui_show_move.value))

        def apply():
            self.move(self._transform())
            self._reset_transform()
        self._gui_apply.on_click(self._guarded(apply))
        self._gui_delete.on_click(self._guarded(self.delete))

        def ist(_):
            with self._lock:
                self._rebuild()
        self._gui_ist.on_update(self._guarded(lambda: ist(None)))

        def undo():
            if not self.undo():
                self._set_status("nothing to undo")
        self._gui_undo.on_click(self._guarded(undo))

        def load():
            if self._gui_bench.value == "(none)":
                raise EditError("benchmark edit: expected an edit picked from the dropdown, found (none)")
            self.load_edit(self._gui_bench.value)
            self._set_status(f"loaded benchmark edit {self._gui_bench.value!r}")
        self._gui_load.on_click(self._guarded(load))

        def save():
            out = Path(self._gui_out.value.strip())
            if not str(out):
                raise EditError("save: expected a folder to write the edited run to, found an empty path")
            report = self.save(out)
            self._set_status(f"saved {report['alive']} points ({report['moved']} moved, {report['deleted']} deleted)"
                             f" -> {out} (edit.ply inside)")
        self._gui_save.on_click(self._guarded(save))

    def _benchmark_edits(self) -> tuple[str, ...]:
        from ne_jax.benchmark.scenes import HELDOUT_SCENES, SCENES, get_scene

        file = Path(self.model.scene_dir) / "scene.json" if self.model.scene_dir is not None else None
        meta = {}
        if file is not None and file.is_file():
            with contextlib.suppress(ValueError):
                meta = json.loads(file.read_text(encoding="utf-8"))
        if meta.get("scene") not in SCENES and meta.get("scene") not in HELDOUT_SCENES:
            return ()
        return tuple(sorted(get_scene(meta["scene"]).edits))

    # -------------------------------------------------------------- clients
    def _on_connect(self, client) -> None:
        st = _ClientState()
        self._clients[client.client_id] = st

        def moved(_):
            st.version += 1
            st.last_update = time.time()
            st.event.set()
        client.camera.on_update(moved)
        st.thread = threading.Thread(target=self._render_loop, args=(client, st), daemon=True,
                                     name=f"ne-jax-view-{client.client_id}")
        st.thread.start()
        st.event.set()

    def _on_disconnect(self, client) -> None:
        st = self._clients.pop(client.client_id, None)
        if st is not None:
            st.event.set()

    def _render_loop(self, client, st: _ClientState) -> None:
        full_key = preview_key = None
        while not self._stopped and client.client_id in self._clients:
            st.event.wait(0.05)
            st.event.clear()
            cam = client.camera
            key = (st.version, self._scene_version, self._gui_mode.value, self._gui_max.value)
            if key == full_key or cam.image_width <= 0 or cam.image_height <= 0:
                continue
            moving = time.time() - st.last_update < self.settle_s
            if moving and key == preview_key:
                continue  # wait for the camera to settle, then render at full resolution
            w, h = fit_size(cam.image_width, cam.image_height, int(self._gui_max.value))
            if moving and self.preview_factor > 1:
                w, h = max(1, w // self.preview_factor), max(1, h // self.preview_factor)
            try:
                img, secs = self.render(cam.wxyz, cam.position, cam.fov, w, h, self._gui_mode.value, preview=moving)
                client.scene.set_background_image(img, format="jpeg", jpeg_quality=90)
            except Exception:
                if self._stopped:
                    return
                self._set_status("render error: " + traceback.format_exc(limit=2).splitlines()[-1])
                full_key = key
                continue
            self.frames += 1
            self.last_frame, self.last_seconds = img, secs
            quality = "preview" if moving else "full"
            self._gui_time.content = f"render: {1000 * secs:.0f} ms at {w}x{h} ({quality}), frame {self.frames}"
            if moving:
                preview_key = key
            else:
                full_key = key


__all__ = ["Viewer", "ViewerError", "port_in_use"]
