"""One result format for every command that produces numbers (in the spirit of evo's result files).

Every result JSON (``metrics.json`` of ``sensor compare``, ``diagnosis.json``, a fitted
``model.json``, ``stats.json`` of ``slam run``, the JSON of ``eval ate|rpe|run``, ``results.json``
of ``batch``) carries the same ``header`` object beside its own keys::

    {"header": {"format": "realgap-result", "format_version": 1,
                "kind": "lab.compare",                 # what the body holds (see KINDS)
                "command": "realgap sensor compare SEQ --effects axial_noise ...",
                "realgap_version": "0.1.0", "created": "2026-11-24T18:40:00Z",
                "inputs": [{"role": "sequence", "path": "/abs/SEQ", "sha256": "...", "hashed": [...]}],
                "parameters": {...}, "seed": 0, "timings_s": {...},
                "metrics": {"gap": 1.59, ...}},         # flat {name: number}: what `realgap show` tabulates
     ...the command's own keys, unchanged...}

Content hashes: a file is hashed whole (SHA-256); a folder (a sequence) is hashed over its index
and calibration files (``*.txt``, ``*.json`` at its top level, names included), not over
thousands of images: the hash changes when frames are added, removed, renamed or re-timed, or
the calibration changes, which is what tells two runs on "the same data" apart in practice.
``hashed`` lists what went into it.

Everything here writes atomically (a temporary file in the same folder, then ``os.replace``),
so an interrupted write never leaves a truncated file. :func:`read_result` reads a result file
(or finds it in a folder) and returns a :class:`Result`; a JSON written before the header
existed is read too, with an empty header and the metrics :func:`legacy_metrics` finds.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import shlex
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from data_tools.errors import FormatError

FORMAT = "realgap-result"
FORMAT_VERSION = 1

KINDS = {
    "lab.compare": "metrics.json",
    "lab.diagnose": "diagnosis.json",
    "lab.fit": "model.json",
    "slam.run": "stats.json",
    "eval.ate": "ate.json",
    "eval.rpe": "rpe.json",
    "eval.run": "ate.json",
    "batch": "results.json",
    "recog.eval": "eval.json",
    "demo": "summary.json",
    "neural.eval": "neural_eval.json",
}
"""Result kind -> the file name it is written to by default (a folder given to
:func:`find_result` is searched for these names, in this order)."""

_FOLDER_HASH_SUFFIXES = (".txt", ".json")


# ------------------------------------------------------------------------------------------
# atomic writes
# ------------------------------------------------------------------------------------------

def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``
    (readers see the old file or the new one, never a truncated one). Creates the parent folder.
    The new file gets the permissions the umask gives an ordinary new file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        # name the file the command wanted, not the temporary one ("disk full" must say what was lost)
        raise OSError(e.errno, e.strerror or str(e), str(path)) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """``text`` (UTF-8) written with :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_image(path: str | os.PathLike, image) -> Path:
    """An image array (uint8/uint16, grey or BGR as OpenCV expects) encoded by the file's suffix
    (.png, .jpg, ...) and written with :func:`atomic_write_bytes`; RealgapError naming the file
    when it cannot be encoded."""
    import cv2
    import numpy as np
    from data_tools.errors import RealgapError
    path = Path(path)
    image = np.asarray(image)
    if (path.suffix or ".png").lower() == ".png" and image.dtype in (np.uint8, np.uint16) \
            and image.size and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3, 4))):
        from data_tools.png import encode_png  # several times faster than OpenCV's PNG encoder
        if image.ndim == 3 and image.shape[2] in (3, 4):
            image = image[:, :, [2, 1, 0, 3][:image.shape[2]]]  # BGR(A) -> the file's RGB(A)
        return atomic_write_bytes(path, encode_png(image))
    ok, buf = cv2.imencode(path.suffix or ".png", np.ascontiguousarray(image))
    if not ok:
        raise RealgapError(f"{path}: cannot encode the image as {path.suffix or '.png'}")
    return atomic_write_bytes(path, buf.tobytes())


def new_figure(width_in: float, height_in: float):
    """A matplotlib Figure (Agg canvas, constrained layout, 100 dpi) that needs no pyplot state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def atomic_save_figure(fig, path: str | os.PathLike, **kwargs) -> Path:
    """``fig.savefig`` into memory, then :func:`atomic_write_bytes` (format from the suffix)."""
    import io
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=(path.suffix.lstrip(".") or "png"), **kwargs)
    return atomic_write_bytes(path, buf.getvalue())


def atomic_save_npy(path: str | os.PathLike, array) -> Path:
    """``np.save`` into memory, then :func:`atomic_write_bytes`."""
    import io
    import numpy as np
    buf = io.BytesIO()
    np.save(buf, array)
    return atomic_write_bytes(path, buf.getvalue())


def json_safe(x):
    """JSON-safe copy of nested dicts/lists/tuples: NaN and inf -> None, numpy scalars and arrays ->
    Python numbers and lists (for files written with ``allow_nan=False``)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


def _default(x):
    """JSON fallback: objects with to_json/to_dict, dataclasses, numpy scalars and arrays."""
    for attr in ("to_json", "to_dict"):
        fn = getattr(x, attr, None)
        if callable(fn):
            return fn()
    import dataclasses
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return dataclasses.asdict(x)
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, (Path, os.PathLike)):
        return str(x)
    return repr(x)


def atomic_write_json(path: str | os.PathLike, data: Any, indent: int | None = 2, allow_nan: bool = True) -> Path:
    """``json.dumps(data)`` written with :func:`atomic_write_text` (numpy values and objects with
    ``to_json`` are converted)."""
    return atomic_write_text(path, json.dumps(data, indent=indent, allow_nan=allow_nan, default=_default) + "\n")


# ------------------------------------------------------------------------------------------
# the header
# ------------------------------------------------------------------------------------------

def realgap_version() -> str:
    try:
        from importlib.metadata import version
        return version("realgap")
    except Exception:  # pragma: no cover - not installed
        return "unknown"


def content_hash(path: str | os.PathLike) -> tuple[str, list[str]]:
    """(SHA-256 hex, names hashed) of a file, or of a folder's top-level index and calibration
    files (see the module docstring). A missing path hashes to ''."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_file():
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        return h.hexdigest(), [p.name]
    if p.is_dir():
        names = sorted(c.name for c in p.iterdir() if c.is_file() and c.suffix in _FOLDER_HASH_SUFFIXES
                       and not c.name.startswith("."))
        for n in names:
            h.update(n.encode() + b"\0")
            h.update((p / n).read_bytes())
            h.update(b"\0")
        return h.hexdigest(), names
    return "", []


def input_record(role: str, path: str | os.PathLike) -> dict:
    """``{"role", "path", "sha256", "hashed"}`` of one input of a command."""
    digest, names = content_hash(path)
    return {"role": role, "path": str(Path(path).resolve()), "sha256": digest, "hashed": names}


def _flat_numbers(d: dict | None) -> dict[str, float]:
    out = {}
    for k, v in (d or {}).items():
        if isinstance(v, bool):
            out[str(k)] = int(v)
        elif isinstance(v, (int, float)) and (not isinstance(v, float) or math.isfinite(v)):
            out[str(k)] = v
        elif hasattr(v, "item") and getattr(v, "ndim", 1) == 0:
            out[str(k)] = v.item()
    return out


_COMMAND: list[str | None] = [None]
"""The command line being run (set by :func:`running_command`), recorded in every header."""


class running_command:
    """``with running_command(argv): ...``: headers made inside record ``realgap ARGV`` as their
    command (the CLI wraps every command in it, so a command called as ``main([...])`` from
    Python records its own arguments, not the interpreter's)."""

    def __init__(self, argv: list[str]):
        self.text = " ".join(["realgap"] + [shlex.quote(str(a)) for a in argv])

    def __enter__(self) -> "running_command":
        self._saved = _COMMAND[0]
        _COMMAND[0] = self.text
        return self

    def __exit__(self, *exc) -> None:
        _COMMAND[0] = self._saved


def current_command() -> str:
    """The command line being run: the :class:`running_command` one, else this process's arguments."""
    return _COMMAND[0] or " ".join(["realgap"] + [shlex.quote(a) for a in sys.argv[1:]])


def make_header(kind: str, *, inputs: dict[str, str | os.PathLike] | None = None, parameters: dict | None = None,
                seed: int | None = None, timings_s: dict | None = None, metrics: dict | None = None,
                command: str | None = None) -> dict:
    """The ``header`` object of a result (see the module docstring). ``inputs``: role -> path;
    ``metrics``: numbers only (non-numbers and non-finite values are left out); ``command``
    defaults to the command being run (:class:`running_command`), else this process's arguments."""
    if kind not in KINDS:
        raise ValueError(f"unknown result kind {kind!r}; known: {', '.join(KINDS)}")
    if command is None:
        command = current_command()
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "command": command,
            "realgap_version": realgap_version(),
            "created": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "inputs": [input_record(r, p) for r, p in (inputs or {}).items() if p is not None],
            "parameters": json.loads(json.dumps(parameters or {}, default=_default)),
            "seed": None if seed is None else int(seed),
            "timings_s": {k: round(float(v), 3) for k, v in (timings_s or {}).items()},
            "metrics": _flat_numbers(metrics)}


def write_result(path: str | os.PathLike, header: dict, body: dict, indent: int | None = 2,
                 allow_nan: bool = True) -> Path:
    """Write ``{"header": header, **body}`` atomically to ``path``."""
    if "header" in body:
        body = {k: v for k, v in body.items() if k != "header"}
    return atomic_write_json(path, {"header": header, **body}, indent=indent, allow_nan=allow_nan)


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------

@dataclass
class Result:
    """A result file read back: its header and the rest of its keys."""

    path: Path
    """The JSON file."""
    header: dict
    """The header (empty for files written before the header existed)."""
    body: dict = field(default_factory=dict)
    """Every other key of the file."""

    @property
    def kind(self) -> str:
        return str(self.header.get("kind", "unknown"))

    @property
    def metrics(self) -> dict[str, float]:
        m = self.header.get("metrics")
        return dict(m) if isinstance(m, dict) and m else legacy_metrics(self.body)


def legacy_metrics(body: dict) -> dict[str, float]:
    """Numbers of a result JSON without a header: its top-level numbers (and ``stats``)."""
    out = _flat_numbers(body)
    if isinstance(body.get("stats"), dict):
        out.update(_flat_numbers(body["stats"]))
    return out


def find_result(path: str | os.PathLike) -> Path:
    """The result JSON at ``path``: the file itself, or in a folder the first of the
    :data:`KINDS` file names present (FormatError naming the folder otherwise)."""
    p = Path(path)
    if p.is_file():
        return p
    if p.is_dir():
        for name in dict.fromkeys(KINDS.values()):
            if (p / name).is_file():
                return p / name
        raise FormatError(p, f"no result file in this folder (looked for {', '.join(dict.fromkeys(KINDS.values()))})")
    raise FormatError(p, "result not found")


def read_result(path: str | os.PathLike) -> Result:
    """Read a result file (or the result in a folder, :func:`find_result`)."""
    p = find_result(path)
    try:
        d = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(p, f"not a JSON result file ({e})") from None
    if not isinstance(d, dict):
        raise FormatError(p, "a result file holds a JSON object")
    header = d.pop("header", {}) or {}
    if not header and p.name not in set(KINDS.values()) | {"metrics.json"}:
        raise FormatError(p, f"not a realgap result (no header, and not a result file name: "
                             f"{', '.join(dict.fromkeys(KINDS.values()))})")
    if not isinstance(header, dict) or (header and header.get("format") != FORMAT):
        raise FormatError(p, f"'header' is not a {FORMAT} header")
    if header.get("format_version", FORMAT_VERSION) > FORMAT_VERSION:
        raise FormatError(p, f"result format version {header['format_version']} is newer than this realgap "
                             f"reads ({FORMAT_VERSION})")
    return Result(p, header, d)


_COUNTS = ("frames", "frames_tracked", "frames_failed", "frames_relocalised", "failed_frames", "candidates",
           "evaluations", "pairs")
_DIMENSIONLESS = {"lab.compare": "gap score", "lab.diagnose": "gap score", "lab.fit": "gap score"}


def metric_unit(kind: str, key: str, header: dict | None = None) -> str:
    """The unit of metric ``key`` of a result of ``kind``: the header's ``units`` entry when it
    has one, else from the name (``*_m`` metres, ``*_deg`` degrees, counts, frames/s) and, for the
    bare statistics of ``eval`` (rmse, mean, ...), from the kind (ATE and RPE translation in m,
    rotations in deg). The lab's gap and its terms are dimensionless scores ("gap score"), a
    diagnosis gain and an accuracy are fractions; a fitted parameter's unit is the effect's
    (``realgap sensor effects NAME``), given by the caller in ``header["units"]``."""
    units = (header or {}).get("units")
    if isinstance(units, dict) and key in units:
        return str(units[key])
    name = key.rsplit(".", 1)[-1] if kind == "batch" else key
    if name.endswith("per_second"):
        return "frames/s"
    if name in _COUNTS or name.endswith("pairs") or name.endswith("_pairs"):
        return "count"
    if name.endswith("_deg") or "_deg_" in name or "rotation" in name:
        return "deg"
    if name.endswith("_m") or "_m_" in name:
        return "m"
    if name.endswith("_s") or name == "seconds":
        return "s"
    if name == "accuracy" or name.startswith("gain."):
        return "fraction"
    if kind in ("eval.ate", "eval.rpe", "eval.run") and (name in STAT_NAMES or name.split("_")[-1] in STAT_NAMES):
        return "m"
    if kind in _DIMENSIONLESS and (name.startswith("gap") or name.startswith("term.") or name == "spatial_term"):
        return _DIMENSIONLESS[kind]
    return "?"


STAT_NAMES = ("rmse", "mean", "median", "std", "min", "max", "sse")
"""The statistics every error metric reports (evo's), in the unit of its errors."""


def results_table(results: list[Result], names: list[str] | None = None) -> tuple[list[str], list[list[str]]]:
    """(column header, rows) lining results up side by side: one row per metric (the union of
    the results' metrics, in first-seen order) with its unit (:func:`metric_unit`) in the
    second column, plus kind, seed and created rows."""
    cols = ["", "unit", *(names or [str(r.path) for r in results])]
    keys: dict[str, None] = {}
    for r in results:
        keys.update(dict.fromkeys(r.metrics))
    rows = [["kind", "", *(r.kind for r in results)],
            ["seed", "", *("" if r.header.get("seed") is None else str(r.header["seed"]) for r in results)],
            ["created", "", *(str(r.header.get("created", "")) for r in results)]]
    aligned = [_alignment(r) for r in results]
    if any(aligned):        # trajectory errors: the alignment they were computed after (one metric, one meaning)
        rows.append(["alignment", "", *(a or "-" for a in aligned)])
    for k in keys:
        unit = "|".join(dict.fromkeys(metric_unit(r.kind, k, r.header) for r in results if k in r.metrics))
        rows.append([k, unit, *(_fmt(r.metrics.get(k)) for r in results)])
    return cols, rows


def _alignment(result: Result) -> str:
    """How a trajectory result's estimate was aligned (``auto: se3``), '' for other results."""
    p = result.header.get("parameters") or {}
    return str(p.get("alignment_used") or p.get("align") or "") if isinstance(p, dict) else ""


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, int):
        return str(v)
    return f"{v:.6g}"


def format_table(cols: list[str], rows: list[list[str]], align: str | None = None) -> str:
    """Rows as an aligned text table under a dashed rule. ``align``: one letter per column, ``l``
    or ``r`` (default: the first column left-aligned, the others - numbers - right-aligned)."""
    widths = [max(len(str(c)) for c in col) for col in zip(cols, *rows)]
    align = align or "l" + "r" * (len(widths) - 1)

    def line(cells):
        text = "  ".join(str(c).ljust(w) if a == "l" else str(c).rjust(w) for c, w, a in zip(cells, widths, align))
        return text.rstrip() if align.endswith("l") else text   # no padding after a left-aligned last column
    return "\n".join([line(cols), "  ".join("-" * w for w in widths), *(line(r) for r in rows)])
