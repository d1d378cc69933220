"""``realgap view``: check the arguments, load the session, open the window or render off-screen."""
from __future__ import annotations

import os
import sys

from data_tools.errors import ConfigError, RealgapError

__all__ = ["open_viewer", "parse_size"]


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size: expected WxH in pixels, e.g. 1600x900, got {text!r}") from None
    if not (200 <= w <= 8000 and 150 <= h <= 8000):
        raise ConfigError(f"--size: {w}x{h} is outside 200x150 .. 8000x8000")
    return w, h


def open_viewer(paths: list[str], *, lab: str | None = None, recog: list[str] | None = None, frame: int = 0,
                camera: str | None = None, screenshot: str | None = None, movie: str | None = None,
                size: str = "1600x900", overwrite: bool = False) -> list[tuple[str, str]]:
    """Run the viewer; returns the files written (path, description) when rendering off-screen."""
    from data_tools.outputs import check_output_file
    from app.viewer.data import load_session
    w, h = parse_size(size)
    if screenshot:
        check_output_file(screenshot, what="screenshot", flag="--screenshot", overwrite=overwrite)
    if movie:
        check_output_file(movie, what="movie", flag="--movie", overwrite=overwrite)
        if not str(movie).lower().endswith((".gif", ".mp4")):
            raise ConfigError(f"--movie {movie}: write a .gif or an .mp4")
    pose = None
    if camera is not None:
        from slam.render import parse_pose
        try:
            pose = parse_pose(camera)
        except RealgapError as e:
            raise ConfigError(f"--camera: {e}") from None
    offscreen = bool(screenshot or movie)
    if not offscreen and sys.platform.startswith("linux") and not os.environ.get("DISPLAY") \
            and not os.environ.get("WAYLAND_DISPLAY"):
        raise RealgapError("no display to open the viewer window on (DISPLAY is not set); render off-screen with "
                           "--screenshot OUT.png or --movie OUT.gif")
    from app.viewer.window import Viewer, check_offscreen
    if offscreen:
        check_offscreen()
    session = load_session(paths, lab=lab, recog=recog)
    if not 0 <= frame < len(session):
        raise ConfigError(f"--frame {frame}: there are {len(session)} frames (0..{len(session) - 1})")
    if pose is not None and not hasattr(session, "virtual_pose"):
        raise ConfigError("--camera places the virtual camera of a sequence view (not --lab / --recog)")
    viewer = Viewer(session, off_screen=offscreen, window_size=(w, h))
    viewer.set_frame(frame)
    if pose is not None:
        viewer.set_virtual_camera(pose)
    written = []
    if screenshot:
        viewer.screenshot(screenshot)
        written.append((screenshot, f"screenshot of frame {frame} ({w}x{h})"))
    if movie:
        n = viewer.movie(movie)
        written.append((movie, f"fly-through, {n} frames"))
    if not offscreen:
        viewer.show()
    return written
