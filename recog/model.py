"""The recogniser: network + descriptor database + the objects, saved as one folder.

    MODEL/recogniser.json   format, version, objects (name, source, scale, symmetry), the
                            patch / data / training configurations, the training log summary
    MODEL/weights.pt        the network's state_dict
    MODEL/database.npz      descriptors of every training view with object and pose
    MODEL/data/             the simulated training patches (kept for retraining; may be deleted)
    MODEL/checkpoint.pt     while training: the resumable checkpoint

:meth:`Recogniser.predict` answers one detection window: patch -> descriptor -> k-NN vote for
the object -> the nearest view's pose moved to the window (:func:`recog.patches.from_ray_frame`)
-> optional ICP refinement against the measured points (:mod:`recog.refine`).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from data_tools.camera import Intrinsics
from data_tools.errors import ConfigError, FormatError
from recog.data import DataConfig
from recog.database import DescriptorDB
from recog.objects import RecogObject
from recog.patches import PatchConfig, extract_patch, from_ray_frame
from recog.train import TrainConfig

__all__ = ["Recogniser", "Prediction", "MODEL_FORMAT", "MODEL_VERSION"]

MODEL_FORMAT = "realgap-recogniser"
MODEL_VERSION = 1


@dataclass
class Prediction:
    """The recogniser's answer for one window."""

    object: str
    """Recognised object name."""
    pose: np.ndarray
    """(4, 4) object-to-camera pose (refined when ICP ran and was accepted)."""
    pose_initial: np.ndarray
    """(4, 4) pose from the nearest database view, before ICP."""
    distance: float
    """Descriptor distance to that view."""
    votes: dict = field(default_factory=dict)
    """Object name -> vote weight of the k nearest neighbours."""
    icp_fitness: float | None = None
    icp_accepted: bool | None = None
    verification: dict = field(default_factory=dict)
    """Object name -> verification score of each candidate checked by ICP (empty without ICP)."""

    @property
    def descriptor_object(self) -> str:
        """The object the descriptor vote chose (before verification)."""
        return next(iter(self.votes)) if self.votes else self.object

    def to_json(self) -> dict:
        return {"object": self.object, "pose": self.pose.tolist(), "pose_initial": self.pose_initial.tolist(),
                "distance": self.distance, "votes": self.votes, "descriptor_object": self.descriptor_object,
                "verification": self.verification, "icp_fitness": self.icp_fitness,
                "icp_accepted": self.icp_accepted}


def check_object_records(objects, path: Path) -> None:
    """The ``objects`` of recogniser.json (a list of ``{name, source, scale, symmetry, diameter_m}``,
    :meth:`Recogniser.object_records`) checked with their JSON types: a wrong one is a FormatError naming
    ``path``, the entry and the key (never a TypeError later, never a symmetry silently ignored)."""
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if not isinstance(objects, list) or not objects:
        raise FormatError(path, "'objects' must be a non-empty list of {name, source, scale, symmetry}")
    for k, rec in enumerate(objects):
        where = f"objects[{k}]"
        if not isinstance(rec, dict):
            raise FormatError(path, f"{where} must be an object, got {rec!r}")
        for key in ("name", "source"):
            if not isinstance(rec.get(key), str) or not rec.get(key):
                raise FormatError(path, f"{where}.{key} must be a non-empty string, got {rec.get(key)!r}")
        for key in ("scale", "diameter_m"):
            if key in rec and not (number(rec[key]) and rec[key] > 0):
                raise FormatError(path, f"{where}.{key} must be a number > 0, got {rec[key]!r}")
        sym = rec.get("symmetry", {})
        if not isinstance(sym, dict):
            raise FormatError(path, f"{where}.symmetry must be an object {{axis, order}}, got {sym!r}")
        axis, order = sym.get("axis"), sym.get("order", 1)
        if axis is not None and not (isinstance(axis, list) and len(axis) == 3 and all(map(number, axis))):
            raise FormatError(path, f"{where}.symmetry.axis must be null or 3 numbers, got {axis!r}")
        if isinstance(order, bool) or not isinstance(order, int) or order < 0:
            raise FormatError(path, f"{where}.symmetry.order must be a whole number >= 0 (a JSON number), "
                                    f"got {order!r}")


class Recogniser:
    """A trained recogniser (see the module docstring)."""

    def __init__(self, objects: list[dict], net, db: DescriptorDB, patch: PatchConfig, data: DataConfig,
                 train: TrainConfig, info: dict | None = None, folder: Path | None = None):
        self.objects = objects
        """Object records: name, source, scale, symmetry, diameter_m."""
        self.net = net
        self.db = db
        self.patch = patch
        self.data = data
        self.train = train
        self.info = info or {}
        self.folder = folder
        self._loaded: dict[int, RecogObject] = {}
        self._casters: dict[int, object] = {}
        self.patch_map = None
        """Optional ``(S, S) patch -> (S, S) patch`` applied to a measured patch before its descriptor (SynDA's
        generator, :func:`recog.synda.run.patch_mapper`); ICP and verification still use the measured depth."""
        self.patch_map_source: str | None = None
        """Where :attr:`patch_map` came from (the generator file), reported by the evaluation."""
        self.patch_map_domain = "depth"
        """What :attr:`patch_map` reads: ``depth`` (the measured patch) or ``rgb`` (the scan's colour image cut
        with the depth patch's virtual camera, :func:`recog.synda.colour_testset.colour_patch`)."""

    @property
    def names(self) -> list[str]:
        return [o["name"] for o in self.objects]

    # ------------------------------------------------------------------ descriptors
    @property
    def input(self) -> str:
        """What the network reads: ``depth`` or ``rgb`` (:attr:`recog.train.TrainConfig.input`)."""
        return self.train.input

    @property
    def reads_colour(self) -> bool:
        """Whether recognising a scan needs its colour image: a colour network, or an rgb generator in front."""
        return self.input == "rgb" or (self.patch_map is not None and self.patch_map_domain == "rgb")

    def describe(self, patches: np.ndarray, batch: int = 512) -> np.ndarray:
        """(N, S, S) depth patches or (N, C, S, S) patches of the network's channel count C -> (N, d) float32
        descriptors; another channel count is a one-line ConfigError (:func:`recog.net.check_input`)."""
        import torch

        from recog.net import check_input
        out = []
        with torch.no_grad():
            for i in range(0, len(patches), batch):
                x = torch.from_numpy(np.ascontiguousarray(patches[i:i + batch], np.float32))
                if x.dim() == 3:
                    x = x.unsqueeze(1)
                check_input(self.net, x, f"this recogniser ({self.input})")
                out.append(self.net(x).numpy())
        return np.concatenate(out) if out else np.zeros((0, self.train.descriptor), np.float32)

    # ------------------------------------------------------------------ objects (for ICP)
    def object(self, k: int) -> RecogObject:
        """The k-th object with its meshes (loaded from its source on first use)."""
        if k not in self._loaded:
            from recog.objects import load_objects
            rec = self.objects[k]
            src = rec["source"]
            if src.startswith("embedded:"):
                objs = {o.name: o for o in load_objects(src.split(":", 1)[1])}
                if rec["name"] not in objs:
                    raise FormatError(self.folder or Path("."), f"embedded object {rec['name']!r} not found")
                obj = objs[rec["name"]]
            else:
                if not Path(src).is_file():
                    raise FormatError(src, f"model file of object {rec['name']!r} not found (needed for ICP; "
                                           f"moved? use --no-icp)")
                obj = load_objects([src], scale=rec["scale"])[0]
            obj.symmetry = rec.get("symmetry", {})
            self._loaded[k] = obj
        return self._loaded[k]

    def index_of(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise ConfigError(f"unknown object {name!r}: this recogniser knows {', '.join(self.names)}") from None

    # ------------------------------------------------------------------ prediction
    def predict(self, depth_m: np.ndarray, intr: Intrinsics, bbox, icp: bool = True, k: int = 5,
                verify: int = 6, inits: int = 3, colour: np.ndarray | None = None) -> Prediction:
        """Recognise the object in window ``bbox`` of ``depth_m`` ((H, W) metres).

        The k nearest descriptors vote for the object. With ``icp`` and ``verify`` > 1, the
        ``verify`` objects whose nearest database entry is nearest to the query (the vote's winner
        always among them) are each placed at the poses of their ``inits`` nearest entries (poses
        at least 10 deg apart), refined by ICP and scored by
        :func:`recog.refine.verification_score` against the measurement; the best-scoring pose of
        the best-scoring object is the answer (hypothesis verification with the CAD models:
        look-alike objects that differ in size are told apart by how their geometry fits the
        window; several starts keep ICP from deciding by a bad initial pose). Measured on a
        validation set of T-LESS obj_01-06 (structure sensor, 120 scans): 1 start 95.0 %,
        3 starts 97.5 % correct. ``colour``: the (H, W, 3) uint8 image registered to ``depth_m``, needed when
        :attr:`patch_map_domain` is ``rgb`` or the network reads colour (:attr:`input` ``rgb``: it describes the
        colour image cut with the depth patch's virtual camera; verification and ICP use the depth)."""
        p = extract_patch(depth_m, intr, bbox, self.patch)
        image = p.image
        if self.input == "rgb":
            if self.patch_map is not None:
                raise ConfigError("a SynDA generator maps its input to depth, this recogniser reads colour "
                                  "(--input rgb): use a depth recogniser with --synda")
            if colour is None:
                raise ConfigError("this recogniser reads colour patches (recog train --input rgb); the scan has no "
                                  "colour image (a colour test set: 'realgap synda testset')")
            from recog.synda.colour_testset import colour_patch
            image = colour_patch(colour, intr, p, self.patch)
        elif self.patch_map is not None and self.patch_map_domain == "rgb":
            if colour is None:
                raise ConfigError("the SynDA generator reads colour images; this scan has none")
            from recog.synda.colour_testset import colour_patch
            image = np.asarray(self.patch_map(colour_patch(colour, intr, p, self.patch)), np.float32)
        elif self.patch_map is not None:
            image = np.asarray(self.patch_map(p.image), np.float32)
        m = self.db.query(self.describe(image[None]), k, per_object=max(inits, 1))[0]
        votes = {self.names[o]: round(w, 4) for o, w in sorted(m.votes.items(), key=lambda t: -t[1])}

        def initial(o: int) -> tuple[np.ndarray, float]:
            j, dist = m.nearest_by_object[o]
            return from_ray_frame(self.db.R_local[j], self.db.offset[j], p), dist

        T0, dist0 = initial(m.object_index)
        pred = Prediction(self.names[m.object_index], T0, T0.copy(), dist0, votes)
        if not icp:
            return pred
        from recog.refine import verification_score
        cands = [m.object_index] + [o for o in sorted(m.nearest_by_object, key=lambda o: m.nearest_by_object[o][1])
                                    if o != m.object_index][:max(verify, 1) - 1]
        results = []
        for o in cands:
            for j, di in m.poses_by_object[o]:
                Ti = from_ray_frame(self.db.R_local[j], self.db.offset[j], p)
                r = self._refine(o, Ti, depth_m, intr, p.bbox)
                score = verification_score(self._casters[o], r.pose, depth_m, intr, p.bbox) \
                    if len(cands) > 1 or inits > 1 else 1.0
                results.append((score, o, Ti, di, r))
        score, o, Ti, di, r = max(results, key=lambda t: t[0])
        # the pose "before ICP" is the chosen object's nearest database entry (the descriptor's answer)
        pred.object, (pred.pose_initial, pred.distance) = self.names[o], initial(o)
        pred.pose, pred.icp_fitness, pred.icp_accepted = r.pose, r.fitness, r.accepted
        ver: dict[str, float] = {}
        for sc, oo, *_ in results:
            ver[self.names[oo]] = max(ver.get(self.names[oo], 0.0), round(float(sc), 4))
        pred.verification = ver
        return pred

    def _refine(self, o: int, T0: np.ndarray, depth_m, intr, bbox):
        from recog.refine import ModelRaycaster, refine_pose
        if o not in self._casters:
            self._casters[o] = ModelRaycaster(self.object(o))
        return refine_pose(self.object(o), T0, depth_m, intr, bbox, self._casters[o])

    # ------------------------------------------------------------------ files
    def save(self, folder: str | os.PathLike) -> Path:
        import io

        import torch

        from data_tools.results import atomic_write_bytes, atomic_write_json
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        torch.save(self.net.state_dict(), buf)
        atomic_write_bytes(folder / "weights.pt", buf.getvalue())
        self.db.save(folder / "database.npz")
        atomic_write_json(folder / "recogniser.json", {
            "format": MODEL_FORMAT, "version": MODEL_VERSION, "objects": self.objects,
            "patch": asdict(self.patch), "data": asdict(self.data), "train": asdict(self.train), "info": self.info})
        self.folder = folder
        return folder

    @classmethod
    def load(cls, folder: str | os.PathLike, index: str = "auto") -> "Recogniser":
        import torch

        from data_tools.config import config_from_dict
        from recog.net import INPUT_CHANNELS, make_network
        folder = Path(folder)
        meta_path = folder / "recogniser.json"
        if folder.is_file():
            raise FormatError(folder, "a recogniser is a folder (MODEL/recogniser.json, weights.pt, database.npz)")
        if not meta_path.is_file():
            raise FormatError(folder, "not a recogniser folder (recogniser.json missing; made by 'realgap recog train')")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise FormatError(meta_path, f"not valid JSON ({e})") from None
        if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
            raise FormatError(meta_path, f"not a {MODEL_FORMAT} file")
        if meta.get("version") != MODEL_VERSION:
            raise FormatError(meta_path, f"recogniser format version {meta.get('version')!r}, this realgap reads "
                                         f"version {MODEL_VERSION}: retrain it with 'realgap recog train'")
        patch = config_from_dict(PatchConfig, meta.get("patch", {}), f"{meta_path}: patch", strict=True)
        data = config_from_dict(DataConfig, meta.get("data", {}), f"{meta_path}: data", strict=True)
        train = config_from_dict(TrainConfig, meta.get("train", {}), f"{meta_path}: train", strict=True)
        check_object_records(meta.get("objects"), meta_path)
        net = make_network(train.network, patch.size, train.descriptor, INPUT_CHANNELS[train.input])
        try:
            net.load_state_dict(torch.load(folder / "weights.pt", map_location="cpu", weights_only=True))
        except FileNotFoundError:
            raise FormatError(folder / "weights.pt", "file not found") from None
        except Exception as e:
            raise FormatError(folder / "weights.pt", f"weights do not fit the network ({type(e).__name__})") from None
        net.eval()
        db = DescriptorDB.load(folder / "database.npz", index)
        if db.descriptors.shape[1] != train.descriptor:
            raise FormatError(folder / "database.npz", "descriptor size differs from the network's")
        return cls(meta["objects"], net, db, patch, data, train, meta.get("info", {}), folder)
