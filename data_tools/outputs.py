"""Checks of input and output paths done *before* a command starts work, and the marker of an
unfinished output folder.

Every long command calls :func:`check_output_dir` / :func:`check_output_file` on its outputs
first, so that a path that cannot be written (an existing file where a folder is wanted, a
folder under a file, a read-only parent, a finished result that would be replaced without
``--overwrite``) is a one-line :class:`~data_tools.errors.RealgapError` before minutes of work,
not an ``OSError`` at the final write. Inputs are checked the same way
(:func:`check_input_file`, :func:`check_input_dir`): a folder given where a file is expected is
named as such.

An output folder being written carries ``incomplete.json`` (:data:`INCOMPLETE_FILE`): the command,
how many steps of how many are finished, and whether re-running continues. It is written when
the work starts and after each finished step, and removed when the command finishes, so
``realgap data info`` and ``realgap show`` can say "incomplete: 37/100 frames" about a folder a
killed run left behind.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from data_tools.errors import FormatError, RealgapError

__all__ = ["INCOMPLETE_FILE", "check_output_dir", "check_output_file", "check_input_file", "check_input_dir",
           "check_output_not_input", "output_lock", "LOCK_FILE", "check_rerun", "RERUN_RULE",
           "mark_incomplete", "clear_incomplete", "read_incomplete", "incomplete_text"]

INCOMPLETE_FILE = "incomplete.json"
"""Marker of an output folder whose command has not finished (see :func:`mark_incomplete`)."""


def _label(what: str, flag: str | None) -> str:
    return f"{what} ({flag})" if flag else what


def _existing_ancestor(path: Path) -> Path:
    """The nearest ancestor of ``path`` (itself included) that exists; a file there is an error."""
    p = path
    while not p.exists() and not p.is_symlink():
        if p.parent == p:
            break
        p = p.parent
    return p


def _check_creatable(path: Path, what: str, flag: str | None) -> None:
    """``path`` does not exist: its nearest existing ancestor must be a writable folder."""
    anc = _existing_ancestor(path.parent if path.parent != path else path)
    if anc.exists() and not anc.is_dir():
        raise RealgapError(f"{path}: cannot create the {_label(what, flag)}: {anc} is a file, not a folder")
    if anc.exists() and not os.access(anc, os.W_OK | os.X_OK):
        raise RealgapError(f"{path}: cannot create the {_label(what, flag)}: {anc} is not writable")


def check_output_dir(path: str | os.PathLike, *, what: str = "output folder", flag: str | None = "--out",
                     finished: str | tuple[str, ...] | None = None, overwrite: bool = False,
                     overwrite_flag: str = "--overwrite") -> Path:
    """Check that ``path`` can be used as an output folder, before any work.

    Errors (one line naming ``path``): it is a file; a parent is a file; the nearest existing
    parent is not writable; it is not writable; it already holds a finished result (a file named
    in ``finished`` exists) and ``overwrite`` is false. Nothing is created. Returns ``Path(path)``.
    """
    p = Path(path)
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise RealgapError(f"{p}: the {_label(what, flag)} is an existing file, not a folder")
        if not os.access(p, os.W_OK | os.X_OK):
            raise RealgapError(f"{p}: the {_label(what, flag)} is not writable")
        names = (finished,) if isinstance(finished, str) else tuple(finished or ())
        done = [n for n in names if (p / n).exists()]
        if done and not overwrite and not (p / INCOMPLETE_FILE).exists():
            raise RealgapError(f"{p}: already holds a finished result ({done[0]}); pass {overwrite_flag} to "
                               f"replace it or choose another {flag or 'folder'}")
    else:
        _check_creatable(p, what, flag)
    return p


def check_output_file(path: str | os.PathLike, *, what: str = "output file", flag: str | None = "--out",
                      overwrite: bool = False, overwrite_flag: str = "--overwrite") -> Path:
    """Check that ``path`` can be written as a file, before any work.

    Errors (one line naming ``path``): it is a folder; a parent is a file or not writable; it
    exists and ``overwrite`` is false. Nothing is created. Returns ``Path(path)``.
    """
    p = Path(path)
    if p.is_dir():
        raise RealgapError(f"{p}: the {_label(what, flag)} is an existing folder, expected a file name")
    if p.exists():
        if not overwrite:
            raise RealgapError(f"{p}: exists; pass {overwrite_flag} to replace it or choose another "
                               f"{flag or 'file name'}")
        if not os.access(p.parent, os.W_OK | os.X_OK):
            raise RealgapError(f"{p}: cannot replace the {_label(what, flag)}: {p.parent} is not writable")
    else:
        _check_creatable(p, what, flag)
    return p


RERUN_RULE = ("a finished output is replaced only with --overwrite (without it the command stops with one line "
              "naming --overwrite); an unfinished one (incomplete.json) is continued by the same command")
"""The one rule for running a command again onto an existing output (docs/cli.md, README)."""


def check_rerun(path: str | os.PathLike | None, finished: tuple[str, ...] | None, *, overwrite: bool,
                flag: str = "--out") -> str:
    """The one re-run rule of every realgap command (:data:`RERUN_RULE`), checked before any work.

    ``finished``: names of the files whose presence makes the folder ``path`` a finished output
    (``("stats.json",)`` for a SLAM run); ``None`` when ``path`` is an output *file* (it is
    finished when it exists). Returns ``"new"`` (nothing there, or nothing of ours), ``"resume"``
    (an unfinished output: ``incomplete.json``; the command continues it where it can, else starts
    again) or ``"replace"`` (finished, and ``overwrite``). A finished output without ``overwrite``
    is a one-line :class:`RealgapError` naming ``--overwrite``; nothing is touched. The CLI applies
    it to every command from one table (:data:`app.commands.RERUN`); a command outside that table
    (e.g. the neural commands) calls it on its output first.
    """
    if path is None:
        return "new"
    p = Path(path)
    if finished is None:
        if not p.is_file():
            return "new"
        if overwrite:
            return "replace"
        raise RealgapError(f"{p}: exists (a finished output); pass --overwrite to replace it or choose another {flag}")
    if not p.is_dir():
        return "new"
    if (p / INCOMPLETE_FILE).exists():
        return "resume"
    done = [n for n in finished if (p / n).exists()]
    if not done:
        return "new"
    if overwrite:
        return "replace"
    raise RealgapError(f"{p}: already holds a finished result ({done[0]}); pass --overwrite to replace it or choose "
                       f"another {flag}")


def check_input_file(path: str | os.PathLike, what: str = "input file", flag: str | None = None) -> Path:
    """``path`` must be an existing, readable file (a folder or a missing path is one line)."""
    p = Path(path)
    if not p.exists():
        raise FormatError(p, f"{_label(what, flag)} not found")
    if p.is_dir():
        raise FormatError(p, f"the {_label(what, flag)} is a folder, expected a file")
    if not os.access(p, os.R_OK):
        raise FormatError(p, f"the {_label(what, flag)} is not readable")
    return p


def check_input_dir(path: str | os.PathLike, what: str = "input folder", flag: str | None = None) -> Path:
    """``path`` must be an existing folder (a file or a missing path is one line)."""
    p = Path(path)
    if not p.exists():
        raise FormatError(p, f"{_label(what, flag)} not found")
    if not p.is_dir():
        raise FormatError(p, f"the {_label(what, flag)} is a file, expected a folder")
    return p


def mark_incomplete(folder: str | os.PathLike, command: str, done: int, total: int | None, unit: str = "frames",
                    resumable: bool = True) -> None:
    """Write (atomically) the marker saying ``folder`` is unfinished: ``done``/``total`` ``unit``."""
    from data_tools.results import atomic_write_json
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / INCOMPLETE_FILE, {
        "command": command, "done": int(done), "total": None if total is None else int(total), "unit": unit,
        "resumable": bool(resumable), "updated": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "note": "written while the command runs; removed when it finishes"
                + ("; re-run the same command to continue" if resumable else
                   "; re-running starts again (this command cannot continue)")})


def clear_incomplete(folder: str | os.PathLike) -> None:
    """Remove the marker: the command in ``folder`` has finished."""
    (Path(folder) / INCOMPLETE_FILE).unlink(missing_ok=True)


def read_incomplete(folder: str | os.PathLike) -> dict | None:
    """The marker of an unfinished ``folder``, or None when it is finished (or not ours)."""
    p = Path(folder) / INCOMPLETE_FILE
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text())
        return d if isinstance(d, dict) else {"command": "?", "done": 0, "total": None, "unit": "steps"}
    except (OSError, ValueError):
        return {"command": "?", "done": 0, "total": None, "unit": "steps"}


def incomplete_text(marker: dict) -> str:
    """"incomplete: 37/100 frames (realgap sensor simulate; re-run to continue)"."""
    total = marker.get("total")
    count = f"{marker.get('done', 0)}/{total}" if total is not None else f"{marker.get('done', 0)}"
    how = "re-run to continue" if marker.get("resumable", True) else "re-running starts again"
    return f"incomplete: {count} {marker.get('unit', 'steps')} ({marker.get('command', '?')}; {how})"


def _real(path: str | os.PathLike) -> Path:
    """``path`` with every symlink of its existing part resolved (the rest kept as written)."""
    return Path(os.path.realpath(os.path.abspath(os.fspath(path))))


def _inside(a: Path, b: Path) -> bool:
    """True when ``a`` is ``b`` or lies below it (both resolved)."""
    return a == b or b in a.parents


REPLACEABLE_INSIDE = (".png", ".jpg", ".gif", ".mp4")
"""Files an output may replace inside an input it may live in (a picture of the input, directly in its folder)."""


def check_output_not_input(outputs, inputs, *, allow_inside: tuple = (), may_hold: tuple = ()) -> None:
    """Refuse, before any work, an output that would land in an input (or contain one).

    ``outputs`` and ``inputs`` are ``(label, path)`` pairs (label: the flag or argument name
    shown to the user, e.g. ``"--out"``, ``"SEQ"``); None paths are skipped, and so are inputs
    that do not exist (they are not ours to protect). Symlinks are resolved on both sides.
    Errors (one line naming both): the output is the input; the output lies inside an input
    folder; an input lies inside the output folder (replacing or resuming the output could touch
    it). ``allow_inside`` names inputs below which an output is expected (``eval run``'s RUN/eval,
    ``slam render``'s RUN/view.png): for those, equality is refused, and so is replacing an existing
    file of the input other than a picture directly in it (:data:`REPLACEABLE_INSIDE`: an earlier
    screenshot may be re-made, ``depth/0.png`` or ``stats.json`` never). ``may_hold`` names inputs
    an output folder may hold (a model file the lab wrote into its own folder: ``sensor compare
    --model LAB/diagnosis/best_model.json --out LAB``); the command's data never.
    """
    outs = [(lab, p) for lab, p in outputs if p not in (None, "", "-")]
    ins = [(lab, p) for lab, p in inputs if p not in (None, "", "-") and (os.path.lexists(p))]
    for olab, opath in outs:
        o = _real(opath)
        for ilab, ipath in ins:
            i = _real(ipath)
            if o == i:
                raise RealgapError(f"{opath}: the output ({olab}) is the input {ilab} ({ipath}); writing there "
                                   f"would replace the input: choose another {olab}")
            if _inside(o, i) and ilab in allow_inside and o.is_file() and \
                    (o.parent != i or o.suffix.lower() not in REPLACEABLE_INSIDE):
                raise RealgapError(f"{opath}: the output ({olab}) would replace {o.relative_to(i)}, a file of the "
                                   f"input {ilab} ({ipath}); choose a new file name so the input is never changed")
            if _inside(o, i) and ilab not in allow_inside:
                raise RealgapError(f"{opath}: the output ({olab}) lies inside the input {ilab} ({ipath}); choose "
                                   f"an {olab} outside it so the input is never changed")
            if _inside(i, o) and ilab not in may_hold:
                raise RealgapError(f"{opath}: the output ({olab}) contains the input {ilab} ({ipath}); choose an "
                                   f"{olab} that does not hold the input so the input is never changed")


LOCK_FILE = "lock.json"
"""Lock of an output folder being written (see :class:`output_lock`)."""


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:     # alive, another user's
        return True
    return True


class output_lock:
    """``with output_lock(folder, command):`` one writer at a time in ``folder``.

    Creates ``folder/lock.json`` exclusively (``O_CREAT | O_EXCL``) holding the pid, host name,
    command and start time, and removes it on exit. A lock held by a running process on this
    host is a one-line RealgapError naming its pid; a lock whose process no longer runs (a
    killed run) is stale: it is reported as a warning and taken over. A lock from another host
    cannot be checked and is an error naming the host (remove the file by hand when you know
    that run is gone). The folder is created when missing, and removed again on exit when the
    command wrote nothing into it (an input error must not leave an empty output behind).
    """

    def __init__(self, folder: str | os.PathLike, command: str):
        self.folder, self.command = Path(folder), command
        self.path = self.folder / LOCK_FILE

    def _holder(self) -> dict:
        try:
            d = json.loads(self.path.read_text())
            return d if isinstance(d, dict) else {}
        except (OSError, ValueError):
            return {}

    def __enter__(self) -> "output_lock":
        import socket
        from data_tools.errors import warn
        self._created = not self.folder.exists()
        self.folder.mkdir(parents=True, exist_ok=True)
        me = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.command,
              "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                h = self._holder()
                pid, host = h.get("pid"), h.get("host")
                if host not in (None, me["host"]):
                    raise RealgapError(f"{self.folder}: is locked by pid {pid} on host {host} ({h.get('command', '?')}, "
                                       f"started {h.get('started', '?')}); if that run is gone, delete {self.path}")
                if isinstance(pid, int) and pid != me["pid"] and _pid_alive(pid):
                    raise RealgapError(f"{self.folder}: is being written by another process (pid {pid}, "
                                       f"{h.get('command', '?')}, started {h.get('started', '?')}); wait for it to "
                                       f"finish or choose another --out")
                warn(f"{self.folder}: stale lock of pid {pid} (no longer running, started "
                              f"{h.get('started', '?')}) taken over")
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            return self
        raise RealgapError(f"{self.path}: could not take the lock (another process keeps creating it)")

    def __exit__(self, *exc) -> None:
        if self._holder().get("pid") == os.getpid():
            self.path.unlink(missing_ok=True)
        if getattr(self, "_created", False):     # a command that failed before writing leaves no empty folder
            try:
                self.folder.rmdir()
            except OSError:                       # it holds what the command wrote: kept
                pass
