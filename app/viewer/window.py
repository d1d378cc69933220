"""The PyVista window of ``realgap view``: panes, keys, off-screen screenshots and movies.

Three layouts, one per kind of session (:mod:`app.viewer.data`):

* sequence + runs: a 3D pane (the TSDF mesh, or the scene, or the fused frame points; the ground
  truth and every run's trajectory in its colour, each registered pose coloured by its error,
  failed frames as red spheres, the cameras of the current frame and the virtual camera as
  frusta, a legend) beside the current RGB and depth (colour bar in metres) and the novel views
  of the virtual camera from each run's model (the neural pane says "no neural run" until one
  is given);
* sensor lab: measured depth, simulated depth and the residual map (diverging, mm) of the current
  frame, the lab's breakdown figure and the effect list with the gap history; a number key
  switches effect k off/on and re-simulates the frame;
* recognition: each test scan's measured points with the recognised CAD model at the estimated
  pose, green when the class is right, red when wrong.

Keys: ``h`` help overlay; Right/Left next/previous frame (or scan); space play/pause; ``v`` put
the virtual camera at the current frame; ``i``/``k`` move it forward/back, ``j``/``l`` turn it,
``u``/``o`` raise/lower it; ``b`` hallucination toggle (neural pane); ``1``-``9`` lab effects.
Every pane's last image is kept in :attr:`Viewer.pane_images` (what tests and scripts inspect).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from app.viewer.data import TRACK_COLOURS, LabSession, RecogSession, SequenceSession, frustum_lines

__all__ = ["Viewer", "check_offscreen"]

HELP = {
    "sequence": ["Right / Left  next / previous frame", "space         play / pause", "Home / End    first / last",
                 "m             final mesh on/off (the frame points grow with the frames)",
                 "v             virtual camera at this frame", "i / k         virtual camera forward / back",
                 "j / l         turn it left / right", "u / o         raise / lower it",
                 "b             hallucination on/off (neural pane)", "h             this help"],
    "lab": ["Right / Left  next / previous frame", "1 .. 9        switch effect k off / on (re-simulates)",
            "h             this help"],
    "recog": ["Right / Left  next / previous scan", "h             this help"],
}


def check_offscreen() -> None:
    """RealgapError (one line) when PyVista cannot open an off-screen render window here."""
    from data_tools.errors import RealgapError
    try:
        import pyvista as pv
    except ImportError:
        raise RealgapError("the viewer needs pyvista (pip install pyvista); 'make setup' installs it") from None
    quiet_vtk_warnings()
    try:
        p = pv.Plotter(off_screen=True, window_size=(32, 32))
        p.screenshot(return_img=True)
        p.close()
    except Exception as e:
        raise RealgapError(f"no display and no off-screen rendering (EGL/OSMesa) here: {type(e).__name__}: "
                           f"{str(e).splitlines()[0] if str(e) else ''}".strip()) from None


def _separate_bar_title(plotter, title: str) -> None:
    """Keep a colour bar's title clear of its tick labels: labels on the far side of the bar from the
    title (below a horizontal bar, left of a vertical one) and a gap between bar and title; a horizontal
    bar needs the height for its labels below it."""
    if not title or title not in plotter.scalar_bars.keys():
        return
    bar = plotter.scalar_bars[title]
    bar.SetTextPositionToPrecedeScalarBar()
    bar.SetVerticalTitleSeparation(8)
    if not bar.GetOrientation():              # horizontal: a thinner bar leaves its labels room below it
        bar.SetBarRatio(0.25)


def quiet_vtk_warnings() -> None:
    """VTK logs a coloured "bad X server connection" warning on stderr whenever a render window
    starts without a display, although off-screen EGL rendering then works: show VTK's errors only."""
    try:
        from vtkmodules.vtkCommonCore import vtkLogger
        vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    except ImportError:                       # an older VTK without vtkLogger prints nothing of the kind
        pass


TITLE_FONT_SIZE = 8
"""Font size (points) of every image pane's title."""


def _set_text(actor, text: str) -> None:
    """Change the text of an actor of ``Plotter.add_text`` (a text actor or a corner annotation)."""
    if hasattr(actor, "SetInput"):
        actor.SetInput(text)
    else:                                   # vtkCornerAnnotation: the corner it was placed in
        for corner in range(8):
            if actor.GetText(corner):
                actor.SetText(corner, text)
                return
        actor.SetText(2, text)


def _rgb255(c) -> tuple[int, int, int]:
    return tuple(int(round(255 * x)) for x in c)


class Viewer:
    """The viewer window (see the module docstring)."""

    def __init__(self, session, off_screen: bool = False, window_size=(1600, 900)):
        import pyvista as pv
        import vtk
        vtk.vtkObject.GlobalWarningDisplayOff()
        self.pv = pv
        self.s = session
        self.off_screen = off_screen
        self.frame = 0
        self.playing = False
        self.hallucinate = False
        self.pane_images: dict[str, np.ndarray] = {}
        self._grids: dict[str, object] = {}
        self._actors: dict[str, object] = {}
        self._help_actor = None
        if isinstance(session, SequenceSession):
            self.kind = "sequence"
            if session.simulated is None:
                self.p = pv.Plotter(shape=(2, 4), groups=[(np.s_[:], np.s_[:2])], off_screen=off_screen,
                                    window_size=window_size, border=False)
                self.panes = {"3d": (0, 0), "rgb": (0, 2), "depth": (0, 3), "novel_0": (1, 2), "novel_1": (1, 3)}
            else:       # with a simulation of the sequence: its depth and the residual beside the measured
                self.p = pv.Plotter(shape=(2, 5), groups=[(np.s_[:], np.s_[:2])], off_screen=off_screen,
                                    window_size=(int(window_size[0] * 1.2), window_size[1]), border=False)
                self.panes = {"3d": (0, 0), "rgb": (0, 2), "depth": (0, 3), "simulated": (0, 4),
                              "novel_0": (1, 2), "novel_1": (1, 3), "residual": (1, 4)}
            self._build_sequence()
        elif isinstance(session, LabSession):
            self.kind = "lab"
            self.p = pv.Plotter(shape=(2, 3), off_screen=off_screen, window_size=window_size, border=False)
            self.panes = {"measured": (0, 0), "simulated": (0, 1), "residual": (0, 2), "breakdown": (1, 0),
                          "effects": (1, 1), "history": (1, 2)}
            self._build_lab()
        elif isinstance(session, RecogSession):
            self.kind = "recog"
            if session.synda:    # the measured patch and its SynDA mapping beside the 3-D view
                self.p = pv.Plotter(shape=(2, 3), groups=[(np.s_[:], np.s_[:2])], off_screen=off_screen,
                                    window_size=window_size, border=False)
                self.panes = {"3d": (0, 0), "patch": (0, 2), "mapped": (1, 2)}
            elif session.reads_colour:    # a colour recogniser: the colour patch it read beside the 3-D view
                self.p = pv.Plotter(shape=(1, 3), groups=[(0, np.s_[:2])], off_screen=off_screen,
                                    window_size=window_size, border=False)
                self.panes = {"3d": (0, 0), "patch": (0, 2)}
            else:
                self.p = pv.Plotter(off_screen=off_screen, window_size=window_size)
                self.panes = {"3d": (0, 0)}
            self.set_frame(0)
        else:
            raise TypeError(f"unknown session {type(session).__name__}")
        self.p.set_background("#1e1e1e")
        self._keys()

    # ------------------------------------------------------------------ image panes
    def _image(self, pane: str, img: np.ndarray, title: str, cmap: str | None = None, clim=None,
               bar: str | None = None) -> None:
        """Show ``img`` ((H, W) scalars or (H, W, 3) uint8) in ``pane`` (created once, updated after)."""
        pv = self.pv
        self.p.subplot(*self.panes[pane])
        img = np.asarray(img)
        self.pane_images[pane] = img.copy()
        H, W = img.shape[:2]
        flat = img[::-1].reshape(H * W, -1) if img.ndim == 3 else np.nan_to_num(img[::-1].reshape(-1), nan=np.nan)
        g = self._grids.get(pane)
        if g is None or g.dimensions[:2] != (W, H) or (img.ndim == 3) != ("rgb" in g.point_data):
            if pane in self._actors:
                self.p.remove_actor(self._actors[pane])
            g = pv.ImageData(dimensions=(W, H, 1))
            if img.ndim == 3:
                g.point_data["rgb"] = flat.astype(np.uint8)
                self._actors[pane] = self.p.add_mesh(g, scalars="rgb", rgb=True, show_scalar_bar=False)
            else:
                g.point_data["value"] = flat.astype(np.float32)
                # a horizontal bar in the margin below the image, labelled at its ends (the title between
                # them): labels never cover the image or the title
                self._actors[pane] = self.p.add_mesh(
                    g, scalars="value", cmap=cmap or "turbo", clim=clim, nan_color="black",
                    scalar_bar_args={"title": bar or "", "vertical": False, "position_x": 0.2, "position_y": 0.0,
                                     "height": 0.17, "width": 0.6, "title_font_size": 12, "label_font_size": 10,
                                     "color": "white", "n_labels": 2, "fmt": "%.2f"})
                _separate_bar_title(self.p, bar or "")
            self._grids[pane] = g
            self._frame_image(W, H)
        else:
            g.point_data["rgb" if img.ndim == 3 else "value"] = flat.astype(np.uint8 if img.ndim == 3 else np.float32)
            if img.ndim != 3 and clim is not None:
                self._actors[pane].mapper.scalar_range = clim
        self._title(pane, title)

    def _frame_image(self, W: int, H: int) -> None:
        """Frame a W x H image in the current pane: whole, its bottom at 20 % of the pane's height (the colour
        bar's margin below it) and its top under the title (parallel projection, image-y up)."""
        self.p.view_xy()
        self.p.enable_parallel_projection()
        vx0, vy0, vx1, vy1 = self.p.renderer.GetViewport()
        ww, wh = self.p.window_size
        aspect = max((vx1 - vx0) * ww, 1.0) / max((vy1 - vy0) * wh, 1.0)
        ps = max(H / (2 * 0.7), W / (2 * aspect * 0.98))   # half the pane's height in image pixels
        cy = H / 2 - (H / 2 - 0.6 * ps)                    # image bottom at 20 % of the pane
        cam = self.p.camera
        cam.focal_point = (W / 2, cy, 0.0)
        cam.position = (W / 2, cy, max(W, H) * 2.0)
        cam.up = (0.0, 1.0, 0.0)
        cam.parallel_scale = ps

    def _title(self, pane: str, text: str) -> None:
        self.p.subplot(*self.panes[pane])
        key = f"title:{pane}"
        if key in self._actors:
            _set_text(self._actors[key], text)
        else:
            # a text actor anchored at the pane's top left in normalised viewport coordinates: one font size in
            # every pane (a corner annotation scales its font with the pane and the text's length)
            actor = self.p.add_text(text, position=(0.01, 0.985), viewport=True, font_size=TITLE_FONT_SIZE,
                                    color="white")
            actor.GetTextProperty().SetVerticalJustificationToTop()
            self._actors[key] = actor

    def _message(self, pane: str, text: str) -> None:
        """A pane without data: a centred message (the pane's image becomes None)."""
        self.p.subplot(*self.panes[pane])
        self.pane_images[pane] = None
        if pane in self._actors:
            self.p.remove_actor(self._actors.pop(pane))
            self._grids.pop(pane, None)
        key = f"msg:{pane}"
        if key in self._actors:
            _set_text(self._actors[key], text)
        else:
            self._actors[key] = self.p.add_text(text, position=(20, 120), font_size=10, color="#bbbbbb")

    def _clear_message(self, pane: str) -> None:
        key = f"msg:{pane}"
        if key in self._actors:
            _set_text(self._actors[key], "")

    # ------------------------------------------------------------------ sequence layout
    def _build_sequence(self) -> None:
        pv, s = self.pv, self.s
        self.p.subplot(*self.panes["3d"])
        mesh, what = s.reference_mesh()
        if mesh is not None:
            faces = np.hstack([np.full((len(mesh.triangles), 1), 3), mesh.triangles]).ravel()
            self._actors["mesh"] = self.p.add_mesh(pv.PolyData(mesh.vertices, faces), color="#9a9a9a", opacity=0.35,
                                                   smooth_shading=False)
        # the map grows with the frames: decimated points of every k-th frame up to the current one
        self._cloud_stride = max(1, len(s) // 60)
        self._cloud_frames: list[int] = []
        self._model_label = what
        legend = []
        if s.gt is not None:
            self.p.add_mesh(pv.lines_from_points(s.gt.positions), color=TRACK_COLOURS["ground truth"], line_width=2)
            legend.append(["ground truth", TRACK_COLOURS["ground truth"]])
        ape_max = max([np.nanmax(r.ape_m) for r in s.runs if r.ape_m is not None and np.isfinite(r.ape_m).any()]
                      + [0.01])
        bar_done = False
        for r in s.runs:
            pos = r.aligned_positions if r.aligned_positions is not None else r.trajectory.positions
            if len(pos) >= 2:
                self.p.add_mesh(pv.lines_from_points(pos), color=r.colour, line_width=3)
            if r.ape_m is not None and len(pos):
                pts = pv.PolyData(pos)
                pts["APE (cm)"] = 100 * np.nan_to_num(r.ape_m, nan=0.0)
                self.p.add_mesh(pts, scalars="APE (cm)", cmap="plasma", clim=(0, 100 * ape_max), point_size=7,
                                render_points_as_spheres=True, show_scalar_bar=not bar_done,
                                scalar_bar_args={"title": "APE (cm), origin-aligned", "color": "white",
                                                 "title_font_size": 12, "label_font_size": 10, "position_x": 0.05,
                                                 "position_y": 0.05, "width": 0.4, "height": 0.1, "fmt": "%.1f"})
                _separate_bar_title(self.p, "APE (cm), origin-aligned")
                bar_done = True
            if len(r.failed_timestamps) and s.gt is not None:
                idx = np.clip(np.searchsorted(s.gt.timestamps, r.failed_timestamps), 0, len(s.gt) - 1)
                self.p.add_mesh(pv.PolyData(s.gt.positions[idx]), color="red", point_size=14,
                                render_points_as_spheres=True)
            legend.append([r.name, r.colour])
        if any(len(r.failed_timestamps) for r in s.runs):
            legend.append(["failed frames", (1.0, 0.0, 0.0)])
        legend.append(["virtual camera", TRACK_COLOURS["virtual camera"]])
        # the legend box's size sets its font size: small, inside the 3D pane's lower right corner (the
        # APE colour bar holds the lower left), so no entry is cut by the image panes beside it
        wide = 0.2 if "simulated" not in self.panes else 0.24       # the 3D pane is narrower beside 3 columns
        self.p.add_legend(legend, bcolor=(0.12, 0.12, 0.12), border=True, size=(wide, 0.035 * len(legend) + 0.01),
                          loc="lower right", face="line")
        extent = float(np.ptp(mesh.vertices, axis=0).max()) if mesh is not None else \
            (float(np.ptp(s.gt.positions, axis=0).max()) if s.gt is not None else 1.0)
        self._frustum_size = max(0.04 * extent, 0.08)
        self.set_frame(0)
        self.set_virtual_camera(s.virtual_pose)
        self.home_view()

    def home_view(self) -> None:
        """The 3D pane's camera: from above and behind the trajectory, with the world's up (the
        mean 'up' of the cameras: -y of the OpenCV camera axes) pointing up."""
        s = self.s
        self.p.subplot(*self.panes["3d"])
        poses = np.stack([s.pose(i) for i in np.linspace(0, len(s) - 1, min(len(s), 50)).astype(int)])
        up = -poses[:, :3, 1].mean(0)
        up = up / (np.linalg.norm(up) or 1.0)
        look = poses[:, :3, 2].mean(0)
        centre = poses[:, :3, 3].mean(0) + look * self._frustum_size * 10
        self.p.reset_camera()
        dist = float(np.linalg.norm(np.asarray(self.p.camera.position) - np.asarray(self.p.camera.focal_point)))
        side = look - (look @ up) * up
        side = side / (np.linalg.norm(side) or 1.0)
        pos = centre - side * 0.6 * dist + up * 0.8 * dist
        self.p.camera_position = [tuple(pos), tuple(centre), tuple(up)]
        self.p.reset_camera_clipping_range()

    def _frusta(self) -> None:
        pv, s = self.pv, self.s
        self.p.subplot(*self.panes["3d"])
        segs, cols = [], []
        cams = [("ground truth", s.pose(self.frame), TRACK_COLOURS["ground truth"])]
        state = s.frame_state(self.frame)
        for r in s.runs:
            st = state[r.name]
            if st["registered"]:
                T = (r.alignment if r.alignment is not None else np.eye(4)) @ r.trajectory.poses[st["pose_index"]]
                cams.append((r.name, T, r.colour))
        cams.append(("virtual camera", s.virtual_pose, TRACK_COLOURS["virtual camera"]))
        size = self._frustum_size
        for _, T, c in cams:
            seg = frustum_lines(T, s.intrinsics, size)
            segs.append(seg)
            cols += [_rgb255(c)] * (len(seg) // 2)
        pts = np.concatenate(segs)
        n = len(pts) // 2
        lines = np.hstack([np.full((n, 1), 2), np.arange(2 * n).reshape(n, 2)]).ravel()
        poly = pv.PolyData(pts, lines=lines)
        poly.cell_data["colour"] = np.asarray(cols, np.uint8)
        if "frusta" in self._actors:
            self.p.remove_actor(self._actors["frusta"])
        self._actors["frusta"] = self.p.add_mesh(poly, scalars="colour", rgb=True, line_width=2,
                                                 show_scalar_bar=False)

    def _grow_cloud(self) -> None:
        """Show the points of every k-th frame up to the current one (added incrementally going
        forward, rebuilt going back): the map as it was when this frame arrived."""
        s, pv = self.s, self.pv
        want = list(range(0, self.frame + 1, self._cloud_stride))
        if want[:len(self._cloud_frames)] != self._cloud_frames:      # went back: start again
            for k in [k for k in self._actors if k.startswith("cloud:")]:
                self.p.remove_actor(self._actors.pop(k))
            self._cloud_frames = []
        self.p.subplot(*self.panes["3d"])
        for i in want[len(self._cloud_frames):]:
            pts, col = s.frame_points(i, step=8)
            self._cloud_frames.append(i)
            if not len(pts):
                continue
            cloud = pv.PolyData(pts)
            if col is not None:
                cloud["rgb"] = col
                self._actors[f"cloud:{i}"] = self.p.add_mesh(cloud, scalars="rgb", rgb=True, point_size=2)
            else:
                self._actors[f"cloud:{i}"] = self.p.add_mesh(cloud, color="#aaaaaa", point_size=2)

    def _status(self) -> str:
        s = self.s
        ts = s.reader.timestamps[self.frame]
        parts = [f"frame {self.frame} (0-{len(s) - 1})  t = {ts:.3f} s   model: {self._model_label}"]
        for name, st in s.frame_state(self.frame).items():
            if st["failed"]:
                parts.append(f"{name}: FAILED")
            elif st["ape_m"] is not None:
                parts.append(f"{name}: APE {100 * st['ape_m']:.2f} cm")
            else:
                parts.append(f"{name}: -")
        return "   ".join(parts)

    def set_frame(self, i: int) -> None:
        """Show frame (or scan) ``i``: every pane that depends on it is updated."""
        n = len(self.s)
        self.frame = int(i) % n if n else 0
        if self.kind == "sequence":
            self._set_sequence_frame()
        elif self.kind == "lab":
            self._set_lab_frame()
        else:
            self._set_recog_scan()
        self.p.render() if getattr(self.p, "ren_win", None) is not None else None

    def _set_sequence_frame(self) -> None:
        s = self.s
        rgb, depth = s.frame(self.frame)
        if rgb is not None:
            self._image("rgb", rgb, "RGB")
        else:
            self._message("rgb", "no colour in this sequence")
        d = np.where(depth > 0, depth, np.nan)
        hi = float(np.nanpercentile(d, 99)) if np.isfinite(d).any() else 1.0
        self._image("depth", d, "measured depth", "turbo", (0.0, max(hi, 0.5)), "depth (m)")
        if "simulated" in self.panes:
            sim = s.simulated_depth(self.frame)
            if sim is None:
                self._message("simulated", f"no frame at this timestamp in {s.simulated_path.name}")
                self._message("residual", "")
            else:
                self._clear_message("simulated")
                self._clear_message("residual")
                ds = np.where(sim > 0, sim, np.nan)
                self._image("simulated", ds, f"simulated depth ({s.simulated_path.name})", "turbo",
                            (0.0, max(hi, 0.5)), "depth (m)")
                res = np.where((sim > 0) & (depth > 0), (depth - sim) * 1000.0, np.nan)
                lim = float(np.nanpercentile(np.abs(res), 95)) if np.isfinite(res).any() else 1.0
                self._image("residual", res, "measured - simulated", "RdBu_r", (-max(lim, 1.0), max(lim, 1.0)),
                            "residual (mm)")
        self._grow_cloud()
        self._frusta()
        self.p.subplot(*self.panes["3d"])
        if "status" in self._actors:
            _set_text(self._actors["status"], self._status())
        else:
            self._actors["status"] = self.p.add_text(self._status(), position="upper_left", font_size=9,
                                                     color="white")

    # ------------------------------------------------------------------ novel views
    def set_virtual_camera(self, pose_c2w: np.ndarray) -> None:
        """Place the virtual camera (camera-to-world, ground-truth frame) and render the novel views."""
        s = self.s
        s.virtual_pose = np.asarray(pose_c2w, float).copy()
        views = s.novel_views(s.virtual_pose, hallucinate=self.hallucinate)
        tsdf = next((n for n, v in views.items() if n != "neural" and not isinstance(v, str)), None)
        if tsdf is None:
            self._message("novel_0", next((v for n, v in views.items() if n != "neural"), "no run with a TSDF mesh"))
            self._title("novel_0", "novel view: TSDF")
        else:
            self._clear_message("novel_0")
            what = tsdf if "reference" in tsdf else f"{tsdf} TSDF"
            self._image("novel_0", views[tsdf].rgb, f"novel view: {what} (magenta = unobserved)")
        nv = views.get("neural", "no neural run")
        if isinstance(nv, str):
            self._message("novel_1", nv + (" (hallucination on)" if self.hallucinate else ""))
            self._title("novel_1", "novel view: neural memory" + (" + hallucination" if self.hallucinate else ""))
        else:
            self._clear_message("novel_1")
            self._image("novel_1", nv.rgb, "novel view: neural memory" + (" + hallucination" if self.hallucinate else ""))
        self._frusta()

    def move_virtual(self, forward: float = 0.0, yaw_deg: float = 0.0, up: float = 0.0) -> None:
        T = self.s.virtual_pose.copy()
        step = 0.1
        T[:3, 3] += T[:3, 2] * forward * step - T[:3, 1] * up * step
        a = math.radians(yaw_deg)
        R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        T[:3, :3] = T[:3, :3] @ R
        self.set_virtual_camera(T)

    # ------------------------------------------------------------------ lab layout
    def _build_lab(self) -> None:
        s = self.s
        fig = s.breakdown_figure()
        if fig is not None:
            import cv2
            img = cv2.imread(str(fig), cv2.IMREAD_COLOR)
            self._image("breakdown", img[..., ::-1], f"breakdown ({fig.name})")
        else:
            self._message("breakdown", "no breakdown figure in the lab folder")
        hist = "\n".join(f"{e.get('label') or ', '.join(e.get('effects', [])) or 'ideal'}: gap {e.get('gap', 0):.3f}"
                         for e in s.history[-12:]) or "no history.json"
        self._message("history", "gap history\n" + hist)
        self.set_frame(0)

    def _effects_text(self) -> str:
        lines = ["effects (key: switch off/on)"]
        for k, name in enumerate(self.s.effects[:9]):
            lines.append(f"{k + 1}  [{'x' if self.s.enabled[name] else ' '}] {name}")
        return "\n".join(lines)

    def _set_lab_frame(self) -> None:
        r = self.s.simulate(self.frame)
        meas = np.where(r["measured"] > 0, r["measured"], np.nan)
        sim = np.where(r["simulated"] > 0, r["simulated"], np.nan)
        both = np.concatenate([meas[np.isfinite(meas)], sim[np.isfinite(sim)]])
        clim = (float(np.percentile(both, 1)), float(np.percentile(both, 99))) if both.size else (0.0, 1.0)
        self._image("measured", meas, f"measured depth, frame {self.frame} (0-{len(self.s) - 1})", "turbo", clim,
                    "depth (m)")
        self._image("simulated", sim, "simulated depth (model below)", "turbo", clim, "depth (m)")
        res = r["residual_mm"]
        lim = float(np.nanpercentile(np.abs(res), 95)) if np.isfinite(res).any() else 1.0
        self._image("residual", res, "measured - simulated", "RdBu_r", (-max(lim, 1.0), max(lim, 1.0)),
                    "residual (mm)")
        self._message("effects", self._effects_text())

    def toggle_effect(self, k: int) -> None:
        """Switch the k-th effect of the lab model (0-based) and re-simulate the current frame."""
        if self.kind != "lab" or k >= len(self.s.effects):
            return
        self.s.toggle(self.s.effects[k])
        self.set_frame(self.frame)

    # ------------------------------------------------------------------ recognition layout
    def _set_recog_scan(self) -> None:
        pv = self.pv
        sc = self.s.scan(self.frame)
        self.p.subplot(0, 0)
        for key in ("points", "model"):
            if key in self._actors:
                self.p.remove_actor(self._actors.pop(key))
        self._actors["points"] = self.p.add_mesh(pv.PolyData(sc["points"]), color="#cccccc", point_size=3)
        m = sc["mesh"]
        faces = np.hstack([np.full((len(m.triangles), 1), 3), m.triangles]).ravel()
        colour = "#33cc33" if sc["correct"] else "#ff3333"
        self._actors["model"] = self.p.add_mesh(pv.PolyData(m.vertices, faces), color=colour, opacity=0.7)
        summ = self.s.summary
        text = (f"scan {self.frame} (0-{len(self.s) - 1})  {sc['file']}\ntrue: {sc['object']}   recognised: "
                f"{sc['predicted']}  ({'right' if sc['correct'] else 'WRONG'})\nevaluation: accuracy "
                f"{100 * (summ.get('accuracy') or 0):.1f} % on {summ.get('n_scans')} scans")
        if "status" in self._actors:
            _set_text(self._actors["status"], text)
        else:
            self._actors["status"] = self.p.add_text(text, position="upper_left", font_size=10, color="white")
        self.p.camera_position = [(0, 0, 0), tuple(sc["pose"][:3, 3]), (0, -1, 0)]
        self.p.reset_camera()
        self.pane_images["3d"] = None
        if "patch" in sc and sc["patch"].ndim == 3:     # the colour patch (an rgb generator's or recogniser's input)
            self._image("patch", sc["patch"], "colour patch" + ("" if "mapped" in sc else " (what the recogniser reads)"))
        elif "patch" in sc:
            self._image("patch", sc["patch"], "measured patch", cmap="viridis", clim=(-1, 1), bar="depth (patch units)")
        if "mapped" in sc:
            self._image("mapped", sc["mapped"], "SynDA mapping (what the recogniser reads)", cmap="viridis",
                        clim=(-1, 1), bar="depth (patch units)")

    # ------------------------------------------------------------------ keys, help, output
    def toggle_mesh(self) -> None:
        """Show / hide the final model mesh (the growing frame points stay)."""
        a = self._actors.get("mesh")
        if a is not None:
            a.SetVisibility(not a.GetVisibility())

    def toggle_help(self) -> None:
        self.p.subplot(0, 0)
        if self._help_actor is None:
            self._help_actor = self.p.add_text("\n".join(HELP[self.kind]), position="lower_left", font_size=10,
                                               color="#ffdd66")
        else:
            self._help_actor.SetVisibility(not self._help_actor.GetVisibility())

    def _keys(self) -> None:
        p = self.p
        p.add_key_event("Right", lambda: self.set_frame(self.frame + 1))
        p.add_key_event("Left", lambda: self.set_frame(self.frame - 1))
        p.add_key_event("Home", lambda: self.set_frame(0))
        p.add_key_event("End", lambda: self.set_frame(len(self.s) - 1))
        p.add_key_event("h", self.toggle_help)
        p.add_key_event("m", self.toggle_mesh)
        p.add_key_event("space", self._toggle_play)
        if self.kind == "sequence":
            p.add_key_event("v", lambda: self.set_virtual_camera(self.s.pose(self.frame)))
            p.add_key_event("i", lambda: self.move_virtual(forward=1))
            p.add_key_event("k", lambda: self.move_virtual(forward=-1))
            p.add_key_event("j", lambda: self.move_virtual(yaw_deg=-10))
            p.add_key_event("l", lambda: self.move_virtual(yaw_deg=10))
            p.add_key_event("u", lambda: self.move_virtual(up=1))
            p.add_key_event("o", lambda: self.move_virtual(up=-1))
            p.add_key_event("b", self._toggle_hallucination)
        if self.kind == "lab":
            for k in range(min(9, len(self.s.effects))):
                p.add_key_event(str(k + 1), lambda k=k: self.toggle_effect(k))

    def _toggle_hallucination(self) -> None:
        self.hallucinate = not self.hallucinate
        self.set_virtual_camera(self.s.virtual_pose)

    def _toggle_play(self) -> None:
        self.playing = not self.playing

    def _tick(self, _step=None) -> None:
        if self.playing:
            self.set_frame(self.frame + 1)

    def screenshot(self, path: str | Path) -> np.ndarray:
        """Render off-screen and save a PNG (atomically); returns the image."""
        from data_tools.results import atomic_write_image
        img = self.p.screenshot(return_img=True)
        atomic_write_image(path, np.ascontiguousarray(img[..., :3][..., ::-1]))
        return img

    def movie(self, path: str | Path, max_frames: int = 120, fps: float = 10.0) -> int:
        """Step through the frames (at most ``max_frames``, evenly) into a GIF (Pillow) or MP4
        (OpenCV); returns the number of frames written."""
        from data_tools.errors import RealgapError
        path = Path(path)
        n = len(self.s)
        idx = sorted(set(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int).tolist()))
        images = []
        for i in idx:
            self.set_frame(i)
            images.append(self.p.screenshot(return_img=True)[..., :3])
        if path.suffix.lower() == ".gif":
            import io

            from PIL import Image

            from data_tools.results import atomic_write_bytes
            frames = [Image.fromarray(im).quantize(colors=192) for im in images]
            buf = io.BytesIO()
            frames[0].save(buf, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps),
                           loop=0)
            atomic_write_bytes(path, buf.getvalue())
        elif path.suffix.lower() == ".mp4":
            import os
            import tempfile

            import cv2
            h, w = images[0].shape[:2]
            fd, tmp = tempfile.mkstemp(suffix=".mp4", dir=path.parent)
            os.close(fd)
            vw = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
            if not vw.isOpened():
                os.unlink(tmp)
                raise RealgapError(f"{path}: this OpenCV build cannot write MP4; use a .gif")
            for im in images:
                vw.write(np.ascontiguousarray(im[..., ::-1]))
            vw.release()
            os.replace(tmp, path)
        else:
            raise RealgapError(f"{path}: --movie writes .gif or .mp4")
        return len(images)

    def look_at_point(self, point) -> None:
        """Put the virtual camera 1.5 m from ``point`` (world), at the current camera's height side,
        looking at it (what a click on the 3D pane does)."""
        from data_tools.geometry import look_at
        s = self.s
        cur = s.pose(self.frame)
        eye = np.asarray(point, float) + (cur[:3, 3] - np.asarray(point, float)) / max(
            np.linalg.norm(cur[:3, 3] - np.asarray(point, float)), 1e-6) * 1.5
        up = -cur[:3, 1]
        self.set_virtual_camera(look_at(eye, np.asarray(point, float), up=up))

    def show(self) -> None:
        """Open the interactive window (blocks until it is closed)."""
        if self.kind == "sequence":
            self.p.subplot(*self.panes["3d"])
            try:
                self.p.enable_point_picking(callback=self.look_at_point, show_message=False, left_clicking=False,
                                            show_point=False)
            except Exception:
                pass
        if self.kind in ("sequence", "lab"):
            self.p.subplot(0, 0)
            self.p.add_slider_widget(lambda v: self.set_frame(int(round(v))) if int(round(v)) != self.frame else None,
                                     [0, max(len(self.s) - 1, 1)], value=0, title="frame", fmt="%.0f",
                                     pointa=(0.05, 0.06), pointb=(0.45, 0.06), style="modern")
        try:
            self.p.add_timer_event(max_steps=10**9, duration=100, callback=self._tick)
        except Exception:
            pass
        self.p.show(title="realgap view")
